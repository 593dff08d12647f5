"""``emulate``, ``demo``, ``experiment`` and ``campaign`` refuse bad flags before anything runs
(one line naming the flag, exit 2): NaN, infinite and negative numbers where a duration,
timeout, rate, depth, seed or count is expected, an unknown demo scenario, missions too short
for the identifier, a ``--plots`` path that cannot be a directory, a log whose telemetry
holds null values. A demo whose child exits early says which and shows its error; a
campaign whose every mission failed exits 1."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

from hil_service.cli import build_parser, main
from hil_service.cli.processes import run_verb
from hil_service.mcap.recorder import McapRecorder
from protocols import keys
from tests.refused_flags import must_not_run, refused_by_argparse

#: A run short enough to end by itself, should a refused flag get through.
SHORT_EMULATION = ("--connect", "udpout:127.0.0.1:9", "--duration", "1", "--speed", "100")


# ---- emulate -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("flag", "value", "profile"),
    [
        ("--duration", "nan", "glider"),
        ("--duration", "inf", "glider"),
        ("--duration", "-1", "glider"),
        ("--trim-depth", "nan", "ardusub"),
        ("--trim-depth", "-5", "glider"),
        ("--seed", "-1", "glider"),
        ("--rate-attitude", "nan", "ardusub"),
        ("--rate-attitude", "-1", "ardusub"),
        ("--rate-attitude", "inf", "ardusub"),
        ("--command-timeout", "nan", "glider"),
        ("--command-timeout", "0", "glider"),
        ("--rate-limit", "nan", "glider"),
        ("--rate-limit", "-0.5", "glider"),
        ("--change-at", "-1", "glider"),
        ("--print-every", "-1", "glider"),
        ("--lockstep-timeout", "inf", "glider"),
    ],
)
def test_emulate_refuses_a_number_its_flag_cannot_take(
    capsys: pytest.CaptureFixture[str], flag: str, value: str, profile: str
) -> None:
    err = refused_by_argparse(
        capsys, ["emulate", *SHORT_EMULATION, "--profile", profile, flag, value]
    )
    assert f"argument {flag}: expected" in err and repr(value) in err


def test_emulate_takes_the_boundary_values_its_flags_allow() -> None:
    args = build_parser("emulate").parse_args(
        ["emulate", "--rate-attitude", "0", "--trim-depth", "0", "--seed", "0", "--duration",
         "0.5", "--print-every", "0", "--change-at", "0"]
    )  # fmt: skip
    assert (args.rate_attitude, args.trim_depth, args.seed, args.duration) == (0.0, 0.0, 0, 0.5)


# ---- demo ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("flag", "value"),
    [("--scenario", "bogus"), ("--duration", "nan"), ("--speed", "nan"), ("--seed", "-1")],
)
def test_demo_refuses_a_bad_flag_before_it_starts_a_process(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, flag: str, value: str
) -> None:
    monkeypatch.setattr("hil_service.cli.demo.start_service", must_not_run)
    err = refused_by_argparse(capsys, ["demo", "--duration", "5", flag, value])
    assert f"argument {flag}" in err


def test_demo_names_an_emulator_that_exits_early_and_shows_its_error(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import hil_service.cli.demo as demo

    start_verb = demo.start_verb
    monkeypatch.setattr(
        demo, "start_verb", lambda *args, **kw: start_verb(*args, "--no-such-flag", **kw)
    )
    code = main(["demo", "--duration", "30", "--log-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 1
    assert "demo: the emulator exited with status 2 before the demo's end" in err
    assert "unrecognized arguments: --no-such-flag" in err


def test_demo_names_a_service_that_exits_early(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import hil_service.cli.demo as demo

    start_service = demo.start_service

    def dying_service(*args: str, **kw: Any) -> subprocess.Popen[str]:
        service = start_service(*args, **kw)
        service.kill()
        service.wait(10)
        return service

    monkeypatch.setattr(demo, "start_service", dying_service)
    code = main(["demo", "--duration", "30", "--log-dir", str(tmp_path)])
    assert code == 1
    assert "demo: the service exited with status -9" in capsys.readouterr().err


# ---- experiment ----------------------------------------------------------------------------
def _log_with_null_inputs(directory: Path, field: dict[str, Any] | None) -> Path:
    """40 telemetry samples, every fourth ``u_depth`` null (how the recorder writes a NaN);
    with ``field``, the log reads as a field import of that grid."""
    metadata = {} if field is None else {"field": json.dumps(field)}
    recorder = McapRecorder(directory, metadata).start()
    for k in range(40):
        payload = {"t": float(k), "depth": 10.0 + 0.1 * k, "pitch": 0.01 * k, "u_pitch": 0.0}
        payload["u_depth"] = None if k % 4 == 0 else 0.5
        recorder.zenoh(keys.telemetry(1), payload, "out", t_ns=(k + 1) * 1_000_000_000)
    recorder.close()
    (path,) = recorder.status.files
    return Path(path)


@pytest.mark.parametrize(
    "field",
    [
        None,
        {
            "format": "test",
            "grid": {
                "period_s": 1.0,
                "segments": [
                    {"dive": 1, "start": 0, "stop": 20},
                    {"dive": 2, "start": 20, "stop": 40},
                ],
            },
        },
    ],
    ids=["recorded", "field-import"],
)
def test_experiment_log_with_null_values_is_a_clear_error(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, field: dict[str, Any] | None
) -> None:
    log = _log_with_null_inputs(tmp_path, field)
    assert main(["experiment", "--log", str(log)]) == 2
    err = capsys.readouterr().err
    assert str(log) in err and "u_depth in 10 of 40" in err
    assert "Traceback" not in err


def test_experiment_refuses_a_plots_path_that_is_a_file_before_it_runs(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr("hil_service.cli.experiment.run_identification", must_not_run)
    monkeypatch.setattr("hil_service.cli.experiment.run_closed_loop", must_not_run)
    a_file = tmp_path / "afile"
    a_file.write_text("")
    for mode in ([], ["--closed-loop"]):
        assert main(["experiment", "--samples", "500", *mode, "--plots", str(a_file)]) == 2
        err = capsys.readouterr().err
        assert f"--plots {a_file}: cannot create the directory" in err


def test_experiment_refuses_a_negative_seed(capsys: pytest.CaptureFixture[str]) -> None:
    assert "argument --seed: expected an integer >= 0" in refused_by_argparse(
        capsys, ["experiment", "--seed", "-1"]
    )


# ---- campaign ------------------------------------------------------------------------------
@pytest.fixture
def no_missions(monkeypatch: pytest.MonkeyPatch) -> None:
    """Neither a local campaign nor a Dask one may start."""
    monkeypatch.setattr("hil_service.campaign.runner.run_campaign", must_not_run)
    monkeypatch.setattr("hil_service.campaign.dask_engine.run_campaign_dask", must_not_run)


@pytest.mark.parametrize(
    "flags",
    [
        ["--scheduler", "tcp://127.0.0.1:1", "--scheduler-timeout", "nan"],
        ["--scheduler", "tcp://127.0.0.1:1", "--scheduler-timeout", "-1"],
        ["--lockstep-timeout", "nan"],
        ["--lockstep-timeout", "0"],
        ["--steps", "0"],
        ["--steps", "5"],
        ["--steps", "300"],
        ["--identify", "-1"],
        ["--step-every", "0"],
    ],
)
@pytest.mark.usefixtures("no_missions")
def test_campaign_refuses_a_bad_number_before_it_connects_or_runs(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, flags: list[str]
) -> None:
    err = refused_by_argparse(capsys, ["campaign", "-o", str(tmp_path / "c"), *flags])
    assert f"argument {flags[-2]}: expected" in err


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (
            ["--steps", "600"],
            "--identify 200 (a third of --steps 600) is shorter than the identifier's burn-in "
            "of 300 steps",
        ),
        (["--steps", "500", "--identify", "100"], "--identify 100 is shorter than"),
        (
            ["--steps", "500", "--identify", "300", "--step-every", "250"],
            "--steps 500 leaves 200 steps of control after --identify 300",
        ),
    ],
)
@pytest.mark.usefixtures("no_missions")
def test_campaign_refuses_missions_too_short_for_the_identifier_and_a_step(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, flags: list[str], message: str
) -> None:
    assert main(["campaign", "-o", str(tmp_path / "c"), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


@pytest.mark.wire
def test_a_campaign_whose_every_mission_failed_exits_1(tmp_path: Path) -> None:
    out = tmp_path / "c"
    done = run_verb(
        "campaign", "--scenarios", "disturbed",
        "--seeds", "0", "--steps", "400", "--identify", "300", "--step-every", "60",
        "--no-oracle", "--no-figures", "--kill-service", "disturbed-s0000:1", "-o", str(out),
        timeout=120,
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "every mission failed" in done.stderr
    assert (out / "runs.csv").exists() and (out / "summary.md").exists()
