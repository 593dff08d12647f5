"""``glider-hil report``: the free-run fit and k-step NMSE lines, from a committed log."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hil_service.experiment.multistep import longest_contiguous
from hil_service.offline.report import write_report

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return write_report(DATA / "disturbed.mcap", tmp_path_factory.mktemp("report"))


def test_report_has_a_fit_and_k_step_nmse_per_channel(report):
    by_channel = {s.channel: s for s in report.summaries}
    # The log's configuration: the controller's horizons (depth 150, pitch 3).
    assert (by_channel["depth"].horizon, by_channel["pitch"].horizon) == (150, 3)
    for summary in by_channel.values():
        assert summary.fit is not None and math.isfinite(summary.fit) and summary.fit <= 100.0
        assert summary.k_step_nmse is not None and summary.k_step_nmse >= 0.0
    text = report.markdown.read_text()
    header = next(line for line in text.splitlines() if line.startswith("| glider"))
    assert "fit %" in header and "k-step NMSE" in header
    assert f"| {by_channel['pitch'].fit:.1f} | 3 |" in text


def test_longest_contiguous_stretch_skips_gaps_and_reversals():
    assert longest_contiguous([]) == (0, 0)
    assert longest_contiguous([0.0, 1.0, 2.0, 5.0, 6.0]) == (0, 3)
    assert longest_contiguous([0.0, 1.0, 4.0, 5.0, 6.0, 7.0, 6.5]) == (2, 6)
