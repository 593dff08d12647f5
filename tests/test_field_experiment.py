"""`glider-hil experiment --log`: the identification experiment on recorded samples."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from hil_service.cli.processes import run_verb

DATA = Path(__file__).parent / "data"
SEA = DATA / "field" / "seaexplorer-sea035"
DEPTH_MODELS = [
    "persistence",
    "rls-arx",
    "dynamic",
    "paper",
    "glide-u",
    "steady-glide",
    "steady-glide-buoyancy-only",
]
PITCH_MODELS = ["persistence", "rls-arx", "dynamic", "paper", "static-balance"]


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return run_verb(*args, timeout=300)


@pytest.fixture(scope="module")
def sea035_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("exp") / "sea035.mcap"
    done = _cli("import", str(SEA), "-o", str(log))
    assert done.returncode == 0, done.stderr
    return log


def test_every_model_scored_on_the_held_out_dives_of_a_field_import(sea035_log: Path) -> None:
    done = _cli("experiment", "--log", str(sea035_log), "--split", "both", "--json")
    assert done.returncode == 0, done.stderr
    first, alternate = json.loads(done.stdout)
    assert (first["split"], alternate["split"]) == ("first", "alternate")
    assert first["source"] == "field import (seaexplorer)" and first["period_s"] == 20.0
    for result in (first, alternate):
        depth, pitch = result["channels"]["depth"], result["channels"]["pitch"]
        assert list(depth["models"]) == DEPTH_MODELS
        assert list(pitch["models"]) == PITCH_MODELS
        assert not set(depth["train"]) & set(depth["scored"])
        persistence = depth["models"]["persistence"]
        assert persistence["skill"] == 0.0  # the baseline of the skill
        for name in ("rls-arx", "dynamic", "glide-u", "steady-glide"):
            scores = depth["models"][name]
            assert scores["skill"] > 0.9, (name, scores)
            assert scores["fit"] > persistence["fit"] + 50.0, (name, scores)
            assert scores["k_step_nmse"] < persistence["k_step_nmse"], (name, scores)
            assert len(scores["fits"]) == len(depth["scored"])
    assert first["channels"]["depth"]["scored"] != alternate["channels"]["depth"]["scored"]
    table = _cli("experiment", "--log", str(sea035_log))
    assert table.returncode == 0, table.stderr
    assert "steady-glide" in table.stdout and "k-step NMSE" in table.stdout


def test_a_recorded_session_is_cut_into_runs(tmp_path: Path) -> None:
    done = _cli("experiment", "--log", str(DATA / "paper.mcap"), "--json")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["source"] == "recorded samples" and result["runs"] == 2
    depth = result["channels"]["depth"]
    assert (depth["train"], depth["scored"]) == ([0], [1])
    # The emulator's depth is what the single-input models identify.
    assert depth["models"]["dynamic"]["fit"] > 90.0


def test_bad_logs_are_clear_errors(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_text("not a log")
    for path, message in ((junk, "not an MCAP file"), (tmp_path / "none.mcap", "no such log")):
        done = _cli("experiment", "--log", str(path))
        assert done.returncode == 2 and message in done.stderr, done.stderr
    done = _cli("experiment", "--log", str(junk), "--closed-loop")
    assert done.returncode == 2 and "--log runs the identification" in done.stderr
