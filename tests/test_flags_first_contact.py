"""Bad input that once ran without a word is refused at first contact, naming the flag or
key (exit 2, one line, no traceback), and what is right still runs:

1. a vehicle profile with a signal's ``scale = 0``, a ``[sampling] delay`` longer than the
   sampler can serve (or one in a lockstep profile, which waits for nothing), an empty name,
   a ``[sampling] period`` in a lockstep profile (one sample per plant step), a ``scale`` or
   ``offset`` on a ``pressure_to_depth`` source (which converts with ``[units]`` alone);
2. ``experiment`` flags typed for an experiment that does not use them, ``--step-every``
   with no second setpoint step within the run, ``--plots ""``, ``--samples`` beyond
   ``MAX_SAMPLES``, ``--bench`` with a ``--scenario`` it does not time (``all``, ``random``,
   ``family``); no default and no documented invocation is refused;
3. ``emulate`` with more ``--fleet-connect`` links than ``--vehicles``, or one link twice.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

import hil_service.cli.experiment as experiment_cli
import plant_emulator.cli as emulate_cli
from hil_service.cli import main
from hil_service.config import StoredConfigError, stored_profile
from hil_service.sources.sampler import SamplerConfig, StreamSampler
from protocols.profiles import (
    BUILTIN,
    MAX_DELAY_INTERVALS,
    ProfileError,
    builtin_text,
    load_profile,
    parse_profile,
)
from tests.refused_flags import must_not_run, refused_by_argparse, refused_line

#: A run short enough to end by itself, should a refused flag get through (it cannot: the
#: run itself is replaced by ``must_not_run``). Port 9 (discard) sends nowhere that listens.
SHORT = ("--connect", "udpout:127.0.0.1:9", "--duration", "3", "--speed", "100", "--period", "0.5")
LINK = "udpout:127.0.0.1:{}"
PAPER_LOG = Path(__file__).parent / "data" / "paper.mcap"


@pytest.fixture
def no_emulation(monkeypatch: pytest.MonkeyPatch) -> None:
    """An ``emulate`` that gets past its checks fails the test instead of running."""
    monkeypatch.setattr(emulate_cli, "_emulate", must_not_run)
    monkeypatch.setattr(emulate_cli, "run_fleet", must_not_run)


#: What ``experiment`` runs once its flags passed, one per experiment and scenario kind.
RUNNERS = (
    "run_identification",
    "run_closed_loop",
    "run_random_closed_loop",
    "run_family_closed_loop",
    "measure_all",
    "run_field_experiment",
)


class _Started(Exception):
    """An experiment started: every check of its flags passed."""


def _started(*_: object, **__: object) -> None:
    raise _Started


@pytest.fixture
def no_experiment(monkeypatch: pytest.MonkeyPatch) -> None:
    """An ``experiment`` that gets past its checks fails the test instead of running."""
    for name in RUNNERS:
        monkeypatch.setattr(experiment_cli, name, must_not_run)


@pytest.fixture
def stops_at_the_start(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """An ``experiment`` whose flags pass raises ``_Started`` instead of running (in a
    scratch directory, where a ``--plots`` directory is made)."""
    monkeypatch.chdir(tmp_path)
    for name in RUNNERS:
        monkeypatch.setattr(experiment_cli, name, _started)


# ---- 1. vehicle profiles ---------------------------------------------------------------------
def _ardusub_with(old: str, new: str) -> str:
    """The built-in ardusub profile with the one line ``old`` replaced by ``new``."""
    text, replaced = re.subn(rf"(?m)^{re.escape(old)}$", new, builtin_text("ardusub"))
    assert replaced == 1
    return text


def _glider_with(old: str, new: str) -> str:
    """The built-in glider profile with the one line ``old`` replaced by ``new``."""
    text, replaced = re.subn(rf"(?m)^{re.escape(old)}$", new, builtin_text("glider"))
    assert replaced == 1
    return text


def _refused_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str) -> str:
    """``emulate --profile FILE`` with ``text`` as FILE: the line it is refused with."""
    path = tmp_path / "vehicle.toml"
    path.write_text(text, encoding="utf-8")
    line = refused_line(capsys, "emulate", *SHORT, "--profile", str(path))
    assert str(path) in line
    return line


@pytest.mark.parametrize("zero", ["0", "0.0", "-0.0"])
def test_a_profile_refuses_a_zero_scale(tmp_path, capsys, no_emulation, zero) -> None:
    line = _refused_profile(tmp_path, capsys, _ardusub_with("scale = -1.0", f"scale = {zero}"))
    assert re.search(r"line \d+: \[signals\.depth\] scale: must not be 0", line), line


@pytest.mark.parametrize("tiny", ["1e-300", "-5e-10", "5e-324"])
def test_a_profile_refuses_a_scale_too_small_to_read_by(tmp_path, capsys, no_emulation, tiny):
    line = _refused_profile(tmp_path, capsys, _ardusub_with("scale = -1.0", f"scale = {tiny}"))
    assert re.search(r"line \d+: \[signals\.depth\] scale: must be at least 1e-09", line), line


def test_a_profile_takes_the_smallest_scale_a_unit_conversion_needs(tmp_path) -> None:
    """degE7 to degrees (1e-7) and the bound itself are read, not refused."""
    for scale in ("1e-7", "-1e-9"):
        path = tmp_path / "vehicle.toml"
        path.write_text(_ardusub_with("scale = -1.0", f"scale = {scale}"), encoding="utf-8")
        assert load_profile(str(path)).signals["depth"][1].scale == float(scale)


@pytest.mark.parametrize("name", ['""', '"   "'])
def test_a_profile_refuses_an_empty_name(tmp_path, capsys, no_emulation, name) -> None:
    line = _refused_profile(tmp_path, capsys, _ardusub_with('name = "ardusub"', f"name = {name}"))
    assert re.search(r"line 4: \[profile\] name: must not be empty", line), line


@pytest.mark.parametrize(
    ("delay", "interval", "limit"),
    [
        ("1e9", None, "1 s"),  # within the 1e9 every number keeps to
        ("50", None, "1 s"),
        ("1.5", None, "1 s"),  # 15 intervals of 10 Hz streams: every sample lost
        ("0.5", "0.02", "0.2 s"),  # ATTITUDE asked for at 50 Hz: 16 values span 0.3 s
    ],
)
def test_a_profile_refuses_a_delay_the_sampler_cannot_serve(
    tmp_path, capsys, no_emulation, delay, interval, limit
) -> None:
    text = _ardusub_with("period = 0.1", f"period = 0.1\ndelay = {delay}")
    if interval is not None:
        text = text.replace('field = "pitch"\n', f'field = "pitch"\ninterval = {interval}\n')
    line = _refused_profile(tmp_path, capsys, text)
    assert re.search(rf"line 10: \[sampling\] delay: must be at most {limit}\b", line), line


def test_a_lockstep_profile_refuses_a_delay(tmp_path, capsys, no_emulation) -> None:
    text = builtin_text("glider").replace("[sampling]", "[sampling]\ndelay = 0.5")
    assert "delay = 0.5" in text
    line = _refused_profile(tmp_path, capsys, text)
    assert re.search(r"line \d+: \[sampling\] delay: is for periodic sampling", line), line


@pytest.mark.parametrize("period", ["0.1", "1.0"])  # 1.0: the glider's plant step
def test_a_lockstep_profile_refuses_a_period(tmp_path, capsys, no_emulation, period) -> None:
    """Lockstep takes one sample per plant step, whatever period the profile names."""
    text = _glider_with('mode = "lockstep"', f'mode = "lockstep"\nperiod = {period}')
    line = _refused_profile(tmp_path, capsys, text)
    assert re.search(
        r"line 10: \[sampling\] period: is for periodic sampling \(lockstep takes one sample "
        r"per plant step",
        line,
    ), line


@pytest.mark.parametrize(("key", "value"), [("scale", "2.0"), ("scale", "1.0"), ("offset", "-3")])
def test_a_pressure_to_depth_source_refuses_a_scale_or_offset(
    tmp_path, capsys, no_emulation, key, value
) -> None:
    text = _glider_with(
        'convert = "pressure_to_depth"', f'convert = "pressure_to_depth"\n{key} = {value}'
    )
    line = _refused_profile(tmp_path, capsys, text)
    assert re.search(
        rf'line 19: \[signals\.depth\] {key}: is for convert = "linear": pressure_to_depth '
        r"converts hPa to depth with \[units\] water_density and surface_pressure_hpa",
        line,
    ), line


def test_a_linear_source_keeps_its_scale_and_offset() -> None:
    """``scale`` and ``offset`` are refused only where they would go unread."""
    text = _glider_with('convert = "pressure_to_depth"', "scale = 0.01\noffset = -10.13")
    source = parse_profile(text).signals["depth"][0]
    assert (source.convert, source.scale, source.offset) == ("linear", 0.01, -10.13)


def test_the_builtins_and_a_delay_at_its_limit_load() -> None:
    for name in BUILTIN:
        assert load_profile(name).name == name
    at_limit = parse_profile(_ardusub_with("period = 0.1", "period = 0.1\ndelay = 1.0"))
    assert at_limit.sampling.delay == at_limit.delay_limit(0.1) == MAX_DELAY_INTERVALS * 0.1
    # A limit computed in binary (10 × 0.011 is 0.10999999999999999) takes its decimal.
    odd = parse_profile(_ardusub_with("period = 0.1", "period = 0.011\ndelay = 0.11"))
    assert odd.sampling.delay == 0.11


@pytest.mark.parametrize(("delay", "formed"), [(1.0, True), (1.5, False)])
def test_the_delay_limit_is_what_the_sampler_can_serve(delay: float, formed: bool) -> None:
    """The reason for the limit: 10 Hz streams sampled every 0.1 s form their samples with
    a delay of 10 periods, and none with 15 (the values of a sample's time are gone)."""
    profile = load_profile("ardusub")
    sampler = StreamSampler(
        SamplerConfig(period=0.1, staleness={"depth": (0.2,), "pitch": (0.2,)}, delay=delay)
    )
    for k in range(1, 201):
        sampler.observe([("depth", 0, 15.0)], ("ms32", 100 * k))
        sampler.observe([("pitch", 0, 0.1)], ("ms32", 100 * k + 3))
    assert (delay <= profile.delay_limit(0.1)) is formed
    assert (sampler.counters.samples > 150) is formed, sampler.counters.as_dict()


# ---- 2. experiment ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--closed-loop", "--fit-split", "100"],
         "--fit-split does not apply to --closed-loop: it is for the identification experiment"),
        (["--closed-loop", "--channel", "depth"],  # the default's value, typed
         "--channel does not apply to --closed-loop"),
        (["--closed-loop", "--horizon", "7"], "--horizon does not apply to --closed-loop"),
        (["--closed-loop", "--burn-in", "100"], "--burn-in does not apply to --closed-loop"),
        (["--no-oracle"],
         "--no-oracle does not apply to the identification experiment: it is for --closed-loop"),
        (["--step-every", "100"], "--step-every does not apply to the identification"),
        (["--identify", "100"], "--identify does not apply to the identification"),
        (["--input-lags", "4"], "--input-lags does not apply to the identification"),
        (["--split", "first"], "--split does not apply to the identification experiment: "
         "it is for --log"),
        (["--bench", "--excitation", "prbs"], "--excitation does not apply to --bench: it is "
         "for the identification experiment or --closed-loop"),
        (["--bench", "--channel", "pitch"], "--channel does not apply to --bench"),
        (["--bench", "--plots", "figures"], "--plots does not apply to --bench"),
        (["--log", str(PAPER_LOG), "--seed", "1"], "--seed does not apply to --log: it is for "
         "the identification experiment, --closed-loop or --bench"),
        (["--log", str(PAPER_LOG), "--samples", "100"], "--samples does not apply to --log"),
        (["--log", str(PAPER_LOG), "--scenario", "paper"], "--scenario does not apply to --log"),
        (["--log", str(PAPER_LOG), "--plots", "figures"], "--plots does not apply to --log"),
        (["--closed-loop", "--plants", "3"], "--plants does not apply to --scenario paper"),
        (["--closed-loop", "--scenario", "all", "--plants", "3"],
         "--plants does not apply to --scenario all"),
        (["--closed-loop", "--scenario", "random", "--plots", "figures"],
         "--plots: the closed loop's --scenario random draws no figures"),
        (["--bench", "--scenario", "all"], "--scenario all does not apply to --bench: it "
         "times one plant scenario, paper, disturbed or nonlinear (default paper)"),
        (["--bench", "--scenario", "random"], "--scenario random does not apply to --bench"),
        (["--bench", "--scenario", "family"], "--scenario family does not apply to --bench"),
    ],
)  # fmt: skip
def test_experiment_refuses_a_flag_its_experiment_does_not_use(
    capsys, no_experiment, tmp_path, monkeypatch, argv, says
) -> None:
    monkeypatch.chdir(tmp_path)  # a --plots directory, were one made, goes here
    line = refused_line(capsys, "experiment", *argv)
    assert says in line, line
    assert not (tmp_path / "figures").exists()


@pytest.mark.parametrize("samples", ["1000001", "1000000000"])
def test_experiment_bounds_the_samples(capsys, no_experiment, samples) -> None:
    for mode in ([], ["--closed-loop"], ["--bench"]):
        line = refused_line(capsys, "experiment", *mode, "--samples", samples)
        assert f"--samples must be at most 1,000,000 (a run holds about 1 kB per sample), " \
            f"got {samples}" in line  # fmt: skip


@pytest.mark.parametrize("scenario", ["random", "family"])
@pytest.mark.parametrize("plants", ["10001", "0", "-3"])
def test_experiment_bounds_the_plants(capsys, no_experiment, scenario, plants) -> None:
    line = refused_line(
        capsys, "experiment", "--closed-loop", "--scenario", scenario, "--plants", plants
    )
    assert "--plants must be 1..10,000 (the most is an hour's run or more; another --seed " \
        f"draws other plants), got {plants}" in line  # fmt: skip


@pytest.mark.parametrize("step_every", ["400", "1000"])
def test_experiment_refuses_a_step_every_with_no_second_step(
    capsys, no_experiment, step_every
) -> None:
    line = refused_line(
        capsys, "experiment", "--closed-loop", "--samples", "900", "--identify", "500",
        "--step-every", step_every,
    )  # fmt: skip
    assert (
        f"--step-every {step_every} leaves one setpoint: the run controls 400 samples "
        "(--samples 900 minus --identify 500), and a second step needs --step-every below 400"
    ) in line


def test_experiment_refuses_an_empty_plots_directory(capsys, no_experiment) -> None:
    err = refused_by_argparse(capsys, ["experiment", "--samples", "300", "--plots", ""])
    assert "argument --plots: expected a directory, got ''" in err


def _starts(argv: list[str]) -> None:
    """``glider-hil experiment ARGV`` gets past every check of its flags."""
    with pytest.raises(_Started):
        main(["experiment", *argv])


#: The defaults and every invocation README.md, docs/ and tests/ make (values as documented).
DOCUMENTED = [
    [],
    ["--scenario", "all", "--channel", "all"],
    ["--scenario", "nonlinear", "--channel", "pitch", "--samples", "400", "--json"],
    ["--samples", "400", "--horizon", "7"],
    ["--samples", "300", "--plots", "figures"],
    ["--closed-loop"],
    ["--closed-loop", "--samples", "20000", "--seed", "0", "--scenario", "disturbed", "--json"],
    ["--closed-loop", "--scenario", "paper", "--samples", "5000", "--seed", "0", "--no-oracle"],
    ["--closed-loop", "--input-lags", "4"],
    ["--closed-loop", "--scenario", "paper", "--samples", "900", "--identify", "500",
     "--step-every", "200", "--json", "--plots", "figures"],
    ["--closed-loop", "--scenario", "random", "--seed", "29", "--plants", "1", "--samples",
     "3600", "--identify", "1200", "--step-every", "600"],
    ["--closed-loop", "--scenario", "family", "--plants", "200", "--seed", "3", "--samples",
     "2000", "--identify", "800", "--step-every", "300"],
    ["--closed-loop", "--samples", "2000"],  # one setpoint: --step-every not typed
    ["--bench"],
    ["--bench", "--samples", "5000"],
    ["--log", "sea035.mcap", "--split", "both", "--json"],
    ["--log", "sea035.mcap"],
]  # fmt: skip


@pytest.mark.parametrize("argv", DOCUMENTED, ids=" ".join)
def test_experiment_defaults_and_documented_invocations_start(stops_at_the_start, argv) -> None:
    _starts(argv)


@pytest.mark.parametrize("scenario", ["paper", "disturbed", "nonlinear"])
def test_experiment_bench_times_the_scenario_asked_for(
    stops_at_the_start, monkeypatch, scenario
) -> None:
    timed: list[str] = []

    def measure(samples: int, asked: str, seed: int) -> None:
        timed.append(asked)
        raise _Started

    monkeypatch.setattr(experiment_cli, "measure_all", measure)
    _starts(["--bench", "--scenario", scenario])
    assert timed == [scenario]


def test_experiment_accepts_the_bounds_themselves(stops_at_the_start) -> None:
    _starts(["--samples", "1000000"])
    _starts(["--closed-loop", "--samples", "900", "--identify", "500", "--step-every", "399"])


# ---- 3. emulate --fleet-connect --------------------------------------------------------------
def _links(*ports: int) -> list[str]:
    return [arg for port in ports for arg in ("--fleet-connect", LINK.format(port))]


@pytest.mark.parametrize(("vehicles", "ports"), [(2, (9, 10, 11)), (None, (9, 10))])
def test_emulate_refuses_more_links_than_vehicles(capsys, no_emulation, vehicles, ports) -> None:
    count = [] if vehicles is None else ["--vehicles", str(vehicles)]
    line = refused_line(capsys, "emulate", *SHORT, *count, *_links(*ports))
    given = 1 if vehicles is None else vehicles
    assert (
        f"--fleet-connect gives {len(ports)} links for --vehicles {given}: "
        f"{len(ports) - given} would carry no vehicle"
    ) in line


def test_emulate_refuses_a_link_given_twice(capsys, no_emulation) -> None:
    line = refused_line(capsys, "emulate", *SHORT, "--vehicles", "4", *_links(9, 10, 9))
    assert f"--fleet-connect {LINK.format(9)} is given more than once" in line


def test_emulate_refuses_a_link_given_twice_in_two_cases(capsys, no_emulation) -> None:
    """``UDPOUT:`` opens as ``udpout:``: the two would be one socket's block twice."""
    shouted = LINK.format(9).replace("udpout:", "UDPOUT:")
    line = refused_line(
        capsys, "emulate", *SHORT, "--vehicles", "4", *_links(9, 10), "--fleet-connect", shouted
    )
    assert f"--fleet-connect {LINK.format(9)} is given more than once" in line


def test_emulate_runs_a_fleet_with_a_vehicle_on_every_link(capsys, monkeypatch) -> None:
    started: list[argparse.Namespace] = []
    monkeypatch.setattr(emulate_cli, "run_fleet", lambda args: started.append(args) or 0)
    assert main(["emulate", *SHORT, "--vehicles", "3", *_links(9, 10, 11)]) == 0
    assert len(started) == 1, capsys.readouterr().err


@pytest.mark.parametrize(
    "text",
    [
        builtin_text("glider").replace('mode = "lockstep"', 'mode = "lockstep"\nperiod = 0.1'),
        builtin_text("glider").replace('mode = "lockstep"', 'mode = "lockstep"\ndelay = 0.5'),
        _ardusub_with("period = 0.1", "period = 0.1\ndelay = 50"),
        _ardusub_with("scale = -1.0", "scale = 0"),
        _ardusub_with('name = "ardusub"', 'name = ""'),
        builtin_text("glider").replace(
            'convert = "pressure_to_depth"', 'convert = "pressure_to_depth"\nscale = 2.0'
        ),
    ],
    ids=["lockstep-period", "lockstep-delay", "long-delay", "zero-scale", "no-name", "p2d-scale"],
)
def test_a_profile_a_log_stores_replays_without_the_advice(text: str) -> None:
    """A log ran with its profile, so reading it back to replay (``stored_profile``) lets
    through what is refused only as advice to whoever writes a profile."""
    with pytest.raises(ProfileError):
        parse_profile(text)
    profile = stored_profile({"profile": {"name": "stored", "text": text}})
    assert profile is not None and profile.text == text


def test_a_stored_profile_the_service_cannot_run_is_stillrefused_line() -> None:
    text = builtin_text("ardusub").replace('mode = "periodic"', 'mode = "sometimes"')
    with pytest.raises(StoredConfigError, match=r"profile\.text.*\[sampling\] mode"):
        stored_profile({"profile": {"name": "stored", "text": text}})
