"""``glider-hil campaign``: a few short lockstep missions, their tables, summary and figure; a
mission whose service is killed; ``--resume``; ``campaign compare``."""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hil_service.campaign.compare import compare, t_interval
from hil_service.campaign.hil_run import SERVICE_SUMMARY, HilOutcome, _collect
from hil_service.campaign.metrics import divergence
from hil_service.campaign.mission import Mission, Trace
from hil_service.campaign.runner import parse_seeds
from hil_service.cli.processes import last_json, run_verb
from tests.markdown_tables import misshapen_tables

pytestmark = pytest.mark.wire

#: Short missions: enough for the identifier to converge and the controller to command.
SHORT = ("--steps", "500", "--identify", "300", "--step-every", "60", "--no-figures")


def campaign(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return run_verb("campaign", *args, timeout=timeout)


def rows(directory: Path) -> list[dict[str, str]]:
    with (directory / "runs.csv").open() as handle:
        return list(csv.DictReader(handle))


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """Two scenarios x two seeds, figures on; the service of disturbed seed 1 is killed."""
    out = tmp_path_factory.mktemp("campaign") / "a"
    done = campaign(
        "--scenarios", "disturbed,random", "--seeds", "0-1", "--steps", "500",
        "--identify", "300", "--step-every", "60", "--jobs", "2", "-o", str(out),
        "--kill-service", "disturbed-s0001:400", "--lockstep-timeout", "2",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert last_json(done.stdout, "campaign")["runs"] == 4
    return out


def test_a_campaign_writes_its_tables_summary_figure_and_logs(small: Path) -> None:
    table = rows(small)
    assert [(r["scenario"], r["seed"]) for r in table] == [
        ("disturbed", "0"), ("disturbed", "1"), ("random", "0"), ("random", "1"),
    ]  # fmt: skip
    ok = [r for r in table if r["status"] == "ok"]
    assert len(ok) == 3
    for r in ok:
        assert float(r["depth_iae"]) > 0 and float(r["depth_iae_reference"]) > 0
        ratio = float(r["depth_iae"]) / float(r["depth_iae_reference"])
        assert float(r["depth_ratio_reference"]) == pytest.approx(ratio, rel=1e-3)
        assert int(r["commands_sent"]) > 0
        assert r["lockstep_timeouts"] == "0"
        assert (small / r["log"]).stat().st_size > 0
    assert json.loads((small / "runs.json").read_text())[0]["scenario"] == "disturbed"
    summary = (small / "summary.md").read_text()
    assert "| disturbed | 2 | 1 | 0 | 1 | depth |" in summary
    assert misshapen_tables(summary) == []
    assert "![IAE ratios per scenario](iae_ratios.png)" in summary
    assert (small / "iae_ratios.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_mission_whose_service_is_killed_is_failed_and_the_others_finish(small: Path) -> None:
    killed = next(r for r in rows(small) if r["scenario"] == "disturbed" and r["seed"] == "1")
    assert killed["status"] == "failed"
    assert "killed by signal 9" in killed["reason"]
    assert "runs not ok" in (small / "summary.md").read_text().lower()
    assert "killed by signal 9" in (small / "summary.md").read_text()


def test_resume_runs_only_what_is_missing(small: Path, tmp_path: Path) -> None:
    refused = campaign("--scenarios", "disturbed", "--seeds", "0", *SHORT, "-o", str(small))
    assert refused.returncode == 2 and "--resume" in refused.stderr
    before = {r["seed"]: r for r in rows(small) if r["scenario"] == "disturbed"}
    # Seeds 0-2 of disturbed: 0 and 1 are recorded (1 failed: recorded too), only 2 runs.
    done = campaign(
        "--scenarios", "disturbed", "--seeds", "0-2", *SHORT, "-o", str(small), "--resume",
        "--jobs", "1",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    after = {r["seed"]: r for r in rows(small)}
    assert after.keys() == {"0", "1", "2"}
    assert after["0"]["wall_s"] == before["0"]["wall_s"]  # read back, not run again
    assert after["1"]["status"] == "failed"
    assert after["2"]["status"] == "ok"


def test_compare_of_two_campaigns_of_the_same_revision_finds_no_difference(
    tmp_path: Path,
) -> None:
    for name in ("a", "b"):
        done = campaign(
            "--scenarios", "random", "--seeds", "0-1", *SHORT, "-o", str(tmp_path / name)
        )
        assert done.returncode == 0, done.stderr
    printed = run_verb(
        "campaign", "compare", str(tmp_path / "a"), str(tmp_path / "b"), "--json", timeout=120
    )
    assert printed.returncode == 0, printed.stderr
    results = {r["metric"]: r for r in last_json(printed.stdout, "compare")}
    # Same revision, same seeds: lockstep runs are reproducible, so every difference is 0.
    for metric in ("depth_iae", "pitch_iae", "depth_ratio_reference"):
        assert results[metric]["pairs"] == 2
        assert results[metric]["mean_difference"] == 0.0
        assert results[metric]["ci95"] == [0.0, 0.0]
    table = run_verb("campaign", "compare", str(tmp_path / "a"), str(tmp_path / "b"), timeout=120)
    assert "| random | depth_iae | 2 | +0 |" in table.stdout
    assert misshapen_tables(table.stdout) == []


def test_t_interval_and_pairing_by_seed() -> None:
    # Differences 1, 2, 3: mean 2, s = 1, t(0.975, 2) = 4.3027: 2 ± 4.3027/sqrt(3).
    low, high = t_interval([1.0, 2.0, 3.0])
    assert (low, high) == pytest.approx((2 - 2.48418, 2 + 2.48418), abs=1e-4)
    assert t_interval([1.0]) is None
    a = [{"scenario": "x", "seed": s, "status": "ok", "depth_iae": 10.0} for s in range(3)]
    b = [{"scenario": "x", "seed": s, "status": "ok", "depth_iae": 10.0 - s} for s in (2, 0, 1)]
    b.append({"scenario": "x", "seed": 9, "status": "ok", "depth_iae": 0.0})  # no pair
    (result,) = [r for r in compare(a, b) if r["metric"] == "depth_iae"]
    assert result["pairs"] == 3
    assert result["mean_difference"] == pytest.approx(-1.0)
    assert result["b_better"] == 2


def test_seeds_parse_and_refuse() -> None:
    assert parse_seeds("0-3,7") == (0, 1, 2, 3, 7)
    with pytest.raises(ValueError, match="--seeds"):
        parse_seeds("3-1")


def test_a_run_whose_output_runs_away_counts_as_diverged() -> None:
    mission = Mission("disturbed", 0, steps=500, identify=300, step_every=60)
    schedule = mission.schedule()
    trace = Trace.empty(mission.steps)
    for ch in ("depth", "pitch"):
        trace.y[ch][:] = np.nan_to_num(schedule[ch], nan=0.0)
    assert divergence(mission, trace, schedule) is None
    trace.y["pitch"][450] += 100.0  # far beyond ten times the largest step (0.25 rad)
    assert divergence(mission, trace, schedule) == "pitch error 100 at step 450"
    trace.y["depth"][400] = np.inf
    assert divergence(mission, trace, schedule) == "depth not finite at step 400"


def test_the_oracle_is_on_by_default_and_off_on_request(tmp_path: Path) -> None:
    out = tmp_path / "oracle"
    done = campaign("--scenarios", "random", "--seeds", "0", *SHORT, "-o", str(out))
    assert done.returncode == 0, done.stderr
    (row,) = rows(out)
    assert row["status"] == "ok"
    for ch in ("depth", "pitch"):
        ratio = float(row[f"{ch}_iae"]) / float(row[f"{ch}_iae_oracle"])
        assert float(row[f"{ch}_ratio_oracle"]) == pytest.approx(ratio, rel=1e-3)
    assert row["oracle_failures"] == "0"
    off = tmp_path / "no-oracle"
    done = campaign("--scenarios", "random", "--seeds", "0", *SHORT, "--no-oracle", "-o", str(off))
    assert done.returncode == 0, done.stderr
    (row_off,) = rows(off)
    assert row_off["depth_iae_oracle"] == "" and row_off["oracle_failures"] == ""
    assert row_off["depth_iae"] == row["depth_iae"]  # the HIL run itself is the same


@pytest.mark.parametrize("scenario", ["paper", "disturbed", "nonlinear", "random"])
def test_a_missions_plants_are_fresh_independent_copies_and_its_period_is_theirs(
    scenario: str,
) -> None:
    """``Mission.plant`` copies one plant built per process: a copy stepped first leaves the
    next one at rest, and both step as a plant built from scratch; ``period`` is read from
    the configuration, without building a plant."""
    from hil_service.campaign.mission import _pristine_plant

    mission = Mission(scenario, 3, 1200, 400, 200)
    first, second = mission.plant(), mission.plant()
    assert first is not second
    built = _pristine_plant.__wrapped__(mission, 1)  # not the cached one
    assert mission.period == float(built.config.period)
    inputs = [(0.4 * np.sin(k / 17), -0.3 * np.cos(k / 11)) for k in range(300)]
    stepped_first = [tuple(first.step(*u)) for u in inputs]
    stepped_second = [tuple(second.step(*u)) for u in inputs]
    from_scratch = [tuple(built.step(*u)) for u in inputs]
    assert stepped_first == stepped_second == from_scratch


def test_compare_refuses_campaigns_of_different_missions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two campaigns whose missions differ in length or schedule do not pair: their IAEs
    sum over other samples and setpoints. Same missions pair."""
    from hil_service.cli import main

    for name, steps in (("a", 2400), ("b", 1800), ("c", 2400)):
        directory = tmp_path / name
        directory.mkdir()
        row = {"scenario": "random", "seed": 0, "status": "ok", "depth_iae": steps / 100}
        (directory / "runs.json").write_text(json.dumps([row]))
        spec = {"steps": steps, "identify": steps // 3, "step_every": steps // 6}
        (directory / "campaign.json").write_text(json.dumps(spec))
    assert main(["campaign", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    assert (
        "ran different missions (steps 2400 against 1800, identify 800 against 600, "
        "step_every 400 against 300): their figures do not pair"
    ) in capsys.readouterr().err
    assert main(["campaign", "compare", str(tmp_path / "a"), str(tmp_path / "c")]) == 0
    assert "| random | depth_iae | 1 | +0 |" in capsys.readouterr().out


def _collected(tmp_path: Path, served: int, sent: int) -> HilOutcome:
    """What a mission's outcome says when its service took ``served`` of ``sent`` samples."""
    (tmp_path / SERVICE_SUMMARY).write_text(json.dumps({"counters": {"samples": served}}))
    stats = SimpleNamespace(steps=sent, as_dict=lambda codec: {"steps": sent})
    autopilot = SimpleNamespace(stats=stats, codec=None)
    runner = SimpleNamespace(stats=SimpleNamespace(as_dict=lambda: {"timeouts": 0}))
    outcome = HilOutcome(Trace.empty(sent), 1.0)
    _collect(outcome, autopilot, runner, tmp_path)  # type: ignore[arg-type]
    return outcome


def test_a_mission_whose_service_did_not_take_every_sample_is_failed(tmp_path: Path) -> None:
    """In lockstep the service releases every step; steps it did not take were released by
    another process on its port, so the row must not be scored as the service's."""
    assert _collected(tmp_path, served=500, sent=500).failure is None
    assert _collected(tmp_path, served=0, sent=500).failure == (
        "the service took 0 of the 500 samples sent: another process received the rest"
    )
    assert "took 499 of the 500" in str(_collected(tmp_path, served=499, sent=500).failure)
