"""``glider-hil report``: figures and report.md from the committed fixture logs."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from hil_service.cli import main
from hil_service.mcap.reader import LogReader
from hil_service.offline.report import write_report
from hil_service.umodel import build_model
from tests.markdown_tables import misshapen_tables

DATA = Path(__file__).parent / "data"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _skill_from_log(path: Path, channel: str, burn_in: int) -> float:
    """Skill recomputed straight from the recorded estimates, independently of the report."""
    y, y_hat, base = [], [], []
    for message in LogReader(path).messages({f"glider/1/umodel/{channel}"}):
        payload = message.json()
        if payload["status"] in ("rejected", "diverged"):
            continue
        y.append(payload["y"])
        y_hat.append(payload["y_hat"])
        base.append(payload["baseline_y_hat"])
    y, y_hat, base = (np.asarray(v)[burn_in:] for v in (y, y_hat, base))
    return 1.0 - float(np.sum((y - y_hat) ** 2) / np.sum((y - base) ** 2))


@pytest.fixture(scope="module")
def disturbed_report(tmp_path_factory):
    return write_report(DATA / "disturbed.mcap", tmp_path_factory.mktemp("report"))


def test_report_writes_readable_figures_for_each_channel(disturbed_report):
    names = sorted(p.name for p in disturbed_report.figures)
    assert names == [
        "glider1_depth_control.png",
        "glider1_depth_identification.png",
        "glider1_pitch_control.png",
        "glider1_pitch_identification.png",
    ]
    for path in disturbed_report.figures:
        data = path.read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 20_000


def test_report_markdown_embeds_every_figure_and_has_the_table(disturbed_report):
    text = disturbed_report.markdown.read_text()
    embedded = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert sorted(embedded) == sorted(p.name for p in disturbed_report.figures)
    assert all((disturbed_report.markdown.parent / name).exists() for name in embedded)
    header = next(line for line in text.splitlines() if line.startswith("| glider"))
    for column in ("NMSE", "skill", "converged at", "tracking MAE"):
        assert column in header
    rows = [line for line in text.splitlines() if re.match(r"\| 1 \| (depth|pitch) \|", line)]
    assert len(rows) == 2
    assert "packet loss: 0.00 %" in text


def test_report_scores_match_the_recorded_estimates(disturbed_report):
    by_channel = {s.channel: s for s in disturbed_report.summaries}
    for channel in ("depth", "pitch"):
        summary = by_channel[channel]
        assert summary.samples == 2000 - build_model("dynamic").history_length
        assert summary.skill == pytest.approx(
            _skill_from_log(DATA / "disturbed.mcap", channel, 500)
        )
        assert summary.commands > 0 and summary.tracking_mae is not None
        assert summary.tracking_rms >= summary.tracking_mae


def test_report_of_a_log_cut_short_says_so(tmp_path):
    source = (DATA / "paper.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(source[: len(source) // 2])
    report = write_report(cut, tmp_path / "out")
    text = report.markdown.read_text()
    assert "not finished" in text
    samples = {s.channel: s.samples for s in report.summaries}
    assert 0 < samples["depth"] < 2000


def test_report_cli_fails_clearly_on_a_file_that_is_not_a_log(tmp_path, capsys):
    bogus = tmp_path / "bogus.mcap"
    bogus.write_bytes(b"not an mcap file at all" * 10)
    assert main(["report", str(bogus), "-o", str(tmp_path / "out")]) == 2
    assert "glider-hil report:" in capsys.readouterr().err


def test_report_cli_prints_where_it_wrote(tmp_path, capsys):
    assert main(["report", str(DATA / "nonlinear.mcap"), "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / 'report.md'}" in out
    assert misshapen_tables((tmp_path / "report.md").read_text()) == []


def test_the_link_section_says_when_the_last_health_stops_short_of_the_log():
    """A lockstep mission ends between two health publications: the report's link counts
    are the last health's, and it says how many of the log's samples they cover."""
    from hil_service.offline.report import _link_lines
    from hil_service.offline.series import VehicleSeries

    vehicle = VehicleSeries(system_id=1, telemetry_t=[0.1 * k for k in range(10)])
    vehicle.last_health = {"counters": {"samples": 7, "commands_sent": 5}}
    lines = _link_lines(vehicle)
    assert lines[0] == (
        "- as of the last health, after 7 of the log's 10 samples "
        "(health is periodic: the counts below stop there)"
    )
    assert "- commands sent 5, acknowledged –, refused –" in lines
    vehicle.last_health = {"counters": {"samples": 10}}
    assert not _link_lines(vehicle)[0].startswith("- as of the last health")
