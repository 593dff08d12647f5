"""``emulate`` and ``experiment`` refuse bad input with one line on stderr naming the flag or
file and what is wrong (exit 2, no traceback) before anything runs: values that would
overflow a MAVLink float32 field, a profile nested too deeply to read, connection strings
that cannot be a link, an uptime past the ms clock's wrap, unit flags a periodic profile
would ignore, plant events outside the run, ``--bench --samples 0``. ``experiment --log``
says when the log it read was damaged."""

from __future__ import annotations

import argparse
import json
import re
import shutil
from pathlib import Path

import pytest

import hil_service.cli.experiment as experiment_cli
import plant_emulator.cli as emulate_cli
from hil_service.cli import main
from protocols.profiles import ProfileError, builtin_text, load_profile
from tests.refused_flags import must_not_run, refused_line

#: A run short enough to end by itself, should a refused flag get through (it cannot: the
#: run itself is replaced by ``must_not_run``). Port 9 (discard) sends nowhere that listens.
SHORT = ("--connect", "udpout:127.0.0.1:9", "--duration", "3", "--speed", "100", "--period", "0.5")
PAPER = Path(__file__).parent / "data" / "paper.mcap"


@pytest.fixture
def no_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """A flag that gets past ``emulate``'s checks fails the test instead of running."""
    monkeypatch.setattr(emulate_cli, "_emulate", must_not_run)
    monkeypatch.setattr(emulate_cli, "run_fleet", must_not_run)


def _profile(tmp_path: Path, text: str, name: str = "vehicle.toml") -> str:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return str(path)


# ---- 1. values that overflow a float32 on the wire -----------------------------------------
@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (("--trim-depth", "1e308"), "--trim-depth"),
        (("--trim-depth", "1e40"), "--trim-depth"),
        (("--full-scale", "1e-300"), "--full-scale"),
        (("--surface-pressure", "1e308"), "--surface-pressure"),
        (("--water-density", "1e308"), "--water-density"),
        (("--vehicles", "2", "--trim-depth", "1e40"), "--trim-depth"),
        (("--vehicles", "2", "--surface-pressure", "1e308"), "--surface-pressure"),
        (("--vehicles", "2", "--full-scale", "1e-300"), "--full-scale"),
    ],
)
def test_emulate_refuses_a_value_beyond_any_vehicle(capsys, no_run, flags, named) -> None:
    line = refused_line(capsys, "emulate", *SHORT, *flags)
    assert named in line and "must be" in line and flags[-1] in line.replace("+", "")


def _ardusub_with(key: str, value: str) -> str:
    """The built-in ardusub profile with ``key``'s value (a line of its own) replaced."""
    text, replaced = re.subn(rf"(?m)^{key} = .*$", f"{key} = {value}", builtin_text("ardusub"))
    assert replaced == 1
    return text


@pytest.mark.parametrize(
    ("table", "key", "value"),
    [
        ("units", "surface_pressure_hpa", "1e308"),
        ("units", "water_density", "1e-300"),
        ("ballast", "full_scale", "1e-300"),
    ],
)
def test_a_profile_refuses_a_unit_beyond_any_vehicle(tmp_path, capsys, no_run, table, key, value):
    path = _profile(tmp_path, _ardusub_with(key, value))
    with pytest.raises(ProfileError, match=rf"line \d+: \[{table}\] {key}: must be"):
        load_profile(path)
    refused = refused_line(capsys, "emulate", *SHORT, "--profile", path)
    assert path in refused and key in refused


def test_a_profile_refuses_a_number_no_field_comes_near(tmp_path) -> None:
    text = _ardusub_with("scale", "-1e300")
    with pytest.raises(ProfileError, match=r"scale: must be at most 1e\+09 in magnitude"):
        load_profile(_profile(tmp_path, text))


def test_the_units_bounds_take_every_real_vehicle(capsys, monkeypatch) -> None:
    """Fresh water, a high lake, a buoyancy engine's cc: accepted, and the run starts."""
    started: list[argparse.Namespace] = []
    monkeypatch.setattr(emulate_cli, "_emulate", lambda args, vehicle: started.append(args) or 0)
    code = main(
        ["emulate", *SHORT, "--water-density", "997", "--surface-pressure", "600",
         "--full-scale", "500", "--trim-depth", "6000"]
    )  # fmt: skip
    assert code == 0 and len(started) == 1, capsys.readouterr().err


# ---- 2. a profile nested too deeply ---------------------------------------------------------
def test_a_deeply_nested_profile_isrefused_line(tmp_path, capsys, no_run) -> None:
    deep = "[" * 5000 + "]" * 5000
    path = _profile(tmp_path, f'[profile]\nname = "deep"\n[units]\nwater_density = {deep}\n')
    line = refused_line(capsys, "emulate", *SHORT, "--profile", path)
    assert path in line and "nested too deeply" in line


# ---- 3. connection strings ------------------------------------------------------------------
@pytest.mark.parametrize(
    ("connection", "says"),
    [
        ("bogus:xyz", "unknown scheme 'bogus'"),
        ("udpout:127.0.0.1", "wants HOST:PORT"),
        ("", "is empty"),
        ("udpout:127.0.0.1:99999", "port must be an integer 1..65535"),
        ("udpout:127.0.0.1:0", "port must be an integer 1..65535"),
        ("tcp:localhost:http", "port must be an integer 1..65535"),
        ("/no/such/serial/device", "no such serial device"),
        ("/no/such/serial/device,57600", "no such serial device"),
        ("serial:/dev/ttyUSB0:57600", "unknown scheme 'serial'"),
        ("udpout:999.1.1.1:14550", "host '999.1.1.1' is not an address"),
    ],
)
def test_emulate_refuses_a_connection_that_cannot_be_a_link(capsys, no_run, connection, says):
    line = refused_line(capsys, "emulate", *SHORT, "--connect", connection)
    assert line.startswith("glider-hil emulate: --connect ") and says in line


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (("--vehicles", "0"), "--vehicles must be at least 1, got 0"),
        (("--vehicles", "-3"), "--vehicles must be at least 1, got -3"),
        (("--vehicles", "3", "--sysid", "0"), "--sysid must be 1..255, got 0"),
        (("--vehicles", "3", "--sysid", "256"), "--sysid must be 1..255, got 256"),
        (("--vehicles", "3", "--sysid", "254"), "--vehicles 3 from --sysid 254 leaves 1..255"),
    ],
)
def test_a_fleet_s_size_and_first_id_are_refused_for_what_is_wrong_with_them(
    capsys, flags, says
) -> None:
    """A fleet of no vehicles, or one starting at an id MAVLink has not, is refused naming
    that flag; a fleet that runs past id 255 names both."""
    line = refused_line(capsys, "emulate", "--connect", "udpout:127.0.0.1:9", *flags)
    assert line.startswith(f"glider-hil emulate: {says}")


def test_emulate_says_when_its_tcp_peer_is_not_listening(capsys) -> None:
    """A TCP link whose peer refuses the connection (a SITL or companion not up yet) is one
    line and exit 2, not pymavlink's traceback."""
    from tests.conftest import free_tcp_port

    port = free_tcp_port()  # nothing listens on it
    assert main(["emulate", "--connect", f"tcp:127.0.0.1:{port}", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert f"glider-hil emulate: cannot open tcp:127.0.0.1:{port}: " in err
    assert "Traceback" not in err


def test_emulate_refuses_a_regular_file_as_a_serial_device(tmp_path, capsys, no_run) -> None:
    afile = tmp_path / "ttyUSB0"
    afile.write_bytes(b"")
    line = refused_line(capsys, "emulate", *SHORT, "--connect", str(afile))
    assert "--connect" in line and "is a file, not a link" in line


@pytest.mark.parametrize("connection", ["udpout:127.0.0.1:99999", "bogus:xyz"])
def test_a_fleet_names_its_bad_connection(capsys, no_run, connection) -> None:
    line = refused_line(
        capsys, "emulate", *SHORT, "--vehicles", "2", "--fleet-connect", "udpout:127.0.0.1:9",
        "--fleet-connect", connection,
    )  # fmt: skip
    assert line.startswith("glider-hil emulate: --fleet-connect ") and connection in line


# ---- 4. experiment --bench --samples ---------------------------------------------------------
@pytest.mark.parametrize("samples", ["0", "-1"])
def test_bench_refuses_no_samples(capsys, monkeypatch, samples) -> None:
    monkeypatch.setattr(experiment_cli, "measure_all", must_not_run)
    line = refused_line(capsys, "experiment", "--bench", "--samples", samples)
    assert "--samples must be at least 1" in line and samples in line


# ---- 5. experiment --log of a damaged log -----------------------------------------------------
def test_experiment_says_its_log_was_damaged(tmp_path, capsys) -> None:
    """The first chunk (every Schema and Channel record) damaged: the samples are read all
    the same (the summary section defines the channels), and the damage is said on stderr
    and in --json."""
    damaged = tmp_path / "damaged.mcap"
    shutil.copyfile(PAPER, damaged)
    data = bytearray(damaged.read_bytes())
    data[2000] ^= 0xFF
    damaged.write_bytes(bytes(data))
    code = main(["experiment", "--log", str(damaged), "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    result = json.loads(captured.out)
    assert result["samples"] > 1000
    assert "1 damaged chunk(s) skipped" in result["recovery"]
    (line,) = captured.err.strip().splitlines()
    assert line == f"glider-hil experiment: {result['recovery']}"


def test_experiment_of_an_intact_log_says_nothing_of_recovery(capsys) -> None:
    code = main(["experiment", "--log", str(PAPER), "--json"])
    captured = capsys.readouterr()
    assert code == 0 and captured.err == ""
    assert "recovery" not in json.loads(captured.out)


# ---- 6. --uptime -------------------------------------------------------------------------------
@pytest.mark.parametrize("uptime", ["1e30", "4294967.296", "nan", "-1"])
def test_emulate_refuses_an_uptime_past_the_clock(capsys, no_run, uptime) -> None:
    line = refused_line(capsys, "emulate", *SHORT, "--profile", "ardusub", "--uptime", uptime)
    assert "--uptime" in line and "uint32 of ms" in line


def test_an_uptime_near_the_wrap_is_taken(capsys, monkeypatch) -> None:
    started: list[object] = []
    monkeypatch.setattr(emulate_cli, "_emulate", lambda args, vehicle: started.append(vehicle) or 0)
    code = main(["emulate", *SHORT, "--profile", "ardusub", "--uptime", "4294967"])
    assert code == 0 and started, capsys.readouterr().err


# ---- 7. unit flags a periodic profile would ignore --------------------------------------------
@pytest.mark.parametrize(
    ("flag", "value"),
    [("--full-scale", "7"), ("--water-density", "1000"), ("--surface-pressure", "1000")],
)
def test_a_periodic_profile_refuses_unit_flags(capsys, no_run, flag, value) -> None:
    line = refused_line(capsys, "emulate", *SHORT, "--profile", "ardusub", flag, value)
    assert flag in line and "gives its own units" in line


# ---- 8. --change-at and --reboot-at -------------------------------------------------------------
def test_change_at_needs_change(capsys, no_run) -> None:
    line = refused_line(capsys, "emulate", *SHORT, "--change-at", "3")
    assert "--change-at needs --change" in line


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (("--change", "flip", "--change-at", "6"), "--change-at 6"),
        (("--profile", "ardusub", "--reboot-at", "7"), "--reboot-at 7"),
    ],
)
def test_an_event_beyond_the_run_isrefused_line(capsys, no_run, flags, named) -> None:
    line = refused_line(capsys, "emulate", *SHORT, *flags)
    assert named in line and "beyond the run" in line and "6 plant steps" in line


@pytest.mark.parametrize(
    "flags",
    [
        ("--change", "flip", "--change-at", "5"),
        ("--change", "gain5"),
        ("--profile", "ardusub", "--reboot-at", "6"),
    ],
)
def test_an_event_within_the_run_is_taken(capsys, monkeypatch, flags) -> None:
    started: list[object] = []
    monkeypatch.setattr(emulate_cli, "_emulate", lambda args, vehicle: started.append(vehicle) or 0)
    assert main(["emulate", *SHORT, *flags]) == 0 and started, capsys.readouterr().err


# ---- 9. messages ------------------------------------------------------------------------------
def test_a_bad_unit_in_a_profile_names_its_file_once(tmp_path, capsys, no_run) -> None:
    path = _profile(tmp_path, _ardusub_with("water_density", "nan"))
    line = refused_line(capsys, "emulate", *SHORT, "--profile", path)
    assert line.count(path) == 1 and "[units] water_density: must be" in line


def test_a_bad_period_is_blamed_on_period_not_family(capsys, no_run) -> None:
    line = refused_line(capsys, "emulate", "--connect", "udpout:127.0.0.1:9", "--duration", "3",
                    "--family", "1:2", "--period", "nan")  # fmt: skip
    assert "--period" in line and "--family" not in line


def test_experiment_log_names_a_directory(tmp_path, capsys) -> None:
    line = refused_line(capsys, "experiment", "--log", str(tmp_path))
    assert "a directory, not a log" in line


def test_a_profile_with_a_byte_order_mark_is_read(tmp_path) -> None:
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + builtin_text("ardusub").encode())
    assert load_profile(path).name == "ardusub"
