"""``glider-hil report``: the free-run fit and k-step NMSE lines, from a committed log."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hil_service.offline.report import recorded_horizon, write_report
from hil_service.offline.series import load_series
from hil_service.umodel.multistep import longest_contiguous

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    return write_report(DATA / "disturbed.mcap", tmp_path_factory.mktemp("report"))


def test_report_has_a_fit_and_k_step_nmse_per_channel(report):
    by_channel = {s.channel: s for s in report.summaries}
    # The horizons the service's controller derived and reported in its last health, capped
    # at an eighth of the log's 1,996-sample stretch; not the fallback's 150 and 3.
    reported = _reported_horizons()
    for channel, summary in by_channel.items():
        assert summary.horizon == min(reported[channel], 1996 // 8), channel
    assert (by_channel["depth"].horizon, by_channel["pitch"].horizon) != (150, 3)
    for summary in by_channel.values():
        assert summary.fit is not None and math.isfinite(summary.fit) and summary.fit <= 100.0
        assert summary.k_step_nmse is not None and summary.k_step_nmse >= 0.0
    text = report.markdown.read_text()
    header = next(line for line in text.splitlines() if line.startswith("| glider"))
    assert "fit %" in header and "k-step NMSE" in header
    assert f"| {by_channel['pitch'].fit:.1f} | {by_channel['pitch'].horizon} |" in text


def _reported_horizons() -> dict[str, int]:
    """health → identifier.{channel}.multistep_horizon, as the log holds it."""
    health = load_series(DATA / "disturbed.mcap").vehicles[1].last_health or {}
    return {ch: entry["multistep_horizon"] for ch, entry in health["identifier"].items()}


def test_longest_contiguous_stretch_skips_gaps_and_reversals():
    assert longest_contiguous([]) == (0, 0)
    assert longest_contiguous([0.0, 1.0, 2.0, 5.0, 6.0]) == (0, 3)
    assert longest_contiguous([0.0, 1.0, 4.0, 5.0, 6.0, 7.0, 6.5]) == (2, 6)


def test_report_quotes_the_services_own_multistep_accuracy(report):
    text = report.markdown.read_text()
    section = text[text.index("### Multi-step accuracy, as the service measured it") :]
    depth = next(line for line in section.splitlines() if line.startswith("- depth:"))
    horizon = _reported_horizons()["depth"]
    assert f"restarted every {horizon} samples" in depth and "free-run fit" in depth


def test_recorded_horizon_reads_the_last_health_or_gives_none():
    vehicle = load_series(DATA / "disturbed.mcap").vehicles[1]
    assert recorded_horizon(vehicle, "depth") == _reported_horizons()["depth"] > 150
    vehicle.last_health = {"identifier": {"depth": {"multistep_horizon": True}}}
    assert recorded_horizon(vehicle, "depth") is None
    vehicle.last_health = {}
    assert recorded_horizon(vehicle, "pitch") is None
