"""Damaged campaign files: ``campaign compare`` on a bad runs.json, ``campaign --resume`` on
a directory made with other settings or holding a run.json that is not its mission's."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from hil_service.campaign.runner import CampaignSpec, clear_result, prepare, run_dir, write_row
from hil_service.cli import main


def row(seed: int, depth_iae: object = 10.0, scenario: str = "paper") -> dict[str, object]:
    return {
        "scenario": scenario,
        "seed": seed,
        "status": "ok",
        "steps": 900,
        "depth_iae": depth_iae,
    }


def campaign_dir(path: Path, rows: object) -> Path:
    path.mkdir(parents=True)
    (path / "runs.json").write_text(json.dumps(rows))
    return path


@pytest.fixture
def baseline(tmp_path: Path) -> Path:
    return campaign_dir(tmp_path / "a", [row(0), row(1), row(2)])


def compare(capsys, a: Path, b: Path, *extra: str) -> tuple[int, str, str]:
    code = main(["campaign", "compare", str(a), str(b), *extra])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize(
    "content",
    [[1, 2, 3], [None], [{"status": "ok", "depth_iae": 1}], [dict(row(0), seed="0")]],
    ids=["ints", "nulls", "no-keys", "string-seed"],
)
def test_compare_refuses_a_runs_json_without_a_usable_row(
    capsys, baseline: Path, tmp_path: Path, content: object
) -> None:
    code, out, err = compare(capsys, baseline, campaign_dir(tmp_path / "b", content))
    assert code == 2 and out == ""
    assert "b/runs.json: none of its" in err and "Traceback" not in err


def test_compare_refuses_a_runs_json_that_is_a_directory(
    capsys, baseline: Path, tmp_path: Path
) -> None:
    (tmp_path / "b" / "runs.json").mkdir(parents=True)
    code, _, err = compare(capsys, baseline, tmp_path / "b")
    assert code == 2 and "runs.json: cannot be read" in err


def test_compare_skips_and_counts_unusable_rows(capsys, baseline: Path, tmp_path: Path) -> None:
    b = campaign_dir(tmp_path / "b", [row(0), row(1), dict(row(2), seed=[2]), None])
    code, out, err = compare(capsys, baseline, b, "--json")
    assert code == 0
    assert "skipped 2 of 4 rows" in err
    printed = json.loads(out)
    assert printed["skipped_rows"] == {"a": 0, "b": 2}
    (depth,) = printed["compare"]
    assert depth["pairs"] == 2


def test_compare_refuses_a_mission_recorded_twice(capsys, baseline: Path, tmp_path: Path) -> None:
    b = campaign_dir(tmp_path / "b", [row(0), row(1), row(0, depth_iae=0.0)])
    code, _, err = compare(capsys, baseline, b)
    assert code == 2 and "paper seed 0 is recorded more than once" in err


def test_compare_leaves_out_and_counts_metrics_that_are_not_finite_numbers(
    capsys, baseline: Path, tmp_path: Path
) -> None:
    b = campaign_dir(tmp_path / "b", [row(0, float("nan")), row(1, "abc"), row(2, 7.0)])
    code, out, _ = compare(capsys, baseline, b, "--json")
    assert code == 0
    (depth,) = json.loads(out)["compare"]
    assert (depth["pairs"], depth["excluded"], depth["mean_difference"]) == (1, 2, -3.0)
    code, out, _ = compare(capsys, baseline, b)
    assert "Left out of paper depth_iae: 2 pair(s)" in out


def test_compare_without_pairs_says_so_and_fails(capsys, baseline: Path, tmp_path: Path) -> None:
    b = campaign_dir(tmp_path / "b", [{"scenario": "paper", "seed": 0, "status": "ok", "foo": 1}])
    code, out, err = compare(capsys, baseline, b)
    assert code == 1 and out == ""
    assert "no pairs to compare" in err


def spec(out: Path, steps: int = 900, resume: bool = True) -> CampaignSpec:
    return CampaignSpec(scenarios=("paper",), seeds=(0, 1), out=out, steps=steps, resume=resume)


def recorded(out: Path) -> CampaignSpec:
    """A finished two-mission campaign directory (rows written, no mission run)."""
    done = spec(out, resume=False)
    prepare(done, io.StringIO())
    for mission in done.missions():
        write_row(run_dir(done, mission), {**row(mission.seed), "steps": mission.steps})
    return done


def test_resume_refuses_a_directory_made_with_other_settings(tmp_path: Path, capsys) -> None:
    recorded(tmp_path / "c")
    before = (tmp_path / "c" / "campaign.json").read_text()
    code = main(
        ["campaign", "--scenarios", "paper", "--seeds", "0-1", "--steps", "1800", "--no-oracle",
         "-o", str(tmp_path / "c"), "--resume", "--no-figures"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2
    assert "--steps 900 there, 1800 here" in err
    assert (tmp_path / "c" / "campaign.json").read_text() == before


def test_resume_refuses_a_directory_whose_campaign_json_is_unreadable(tmp_path: Path) -> None:
    recorded(tmp_path / "c")
    (tmp_path / "c" / "campaign.json").write_bytes(b"\xff\x00garbage")
    with pytest.raises(ValueError, match=r"cannot read .*campaign\.json"):
        prepare(spec(tmp_path / "c"), io.StringIO())


@pytest.mark.parametrize(
    "content",
    ['{"scenario": "nonlinear", "seed": 7, "status": "ok", "steps": 5000}', "{}", "[1]", None],
    ids=["other-mission", "empty-object", "list", "directory"],
)
def test_resume_runs_again_a_mission_whose_run_json_is_not_its_own(
    tmp_path: Path, content: str | None
) -> None:
    done = recorded(tmp_path / "c")
    first = run_dir(done, done.missions()[0]) / "run.json"
    first.unlink()
    if content is None:
        first.mkdir()
    else:
        first.write_text(content)
    report = io.StringIO()
    rows, pending = prepare(spec(tmp_path / "c"), report)
    assert [m.run_id for m in pending] == ["paper-s0000"]
    assert list(rows) == ["paper-s0001"]
    assert "paper-s0000 runs again" in report.getvalue()
    assert "1 recorded result(s) not usable" in report.getvalue()
    clear_result(done, pending[0])  # what the runner does before the mission runs again
    assert not first.exists()
