"""`serve` and `replay` refuse flags and profile values that would silently switch a safety
check off or make sampling meaningless, with one line naming the flag (exit 2), before
anything starts; and `replay` takes the sample period the user chose over the recorded one.
"""

from __future__ import annotations

import json
import math
import signal
from types import SimpleNamespace

import pytest

import hil_service.cli.serve as serve_cli
from hil_service.cli import main
from hil_service.config import ServiceConfig
from hil_service.inputs import SetpointLimits
from hil_service.mcap.recorder import McapRecorder
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import ProfileError, builtin_text, load_profile

#: The ardusub profile's line ``period = 0.1`` (line 9 of the built-in file).
ARDUSUB_PERIOD_LINE = "period = 0.1"


def _refused(tmp_path, capsys, monkeypatch, *flags: str) -> str:
    """``glider-hil serve FLAGS`` in this process must exit 2 with one line on stderr, before
    it opens its first part (the log: opening it fails the test, and starts nothing)."""

    def got_past_the_checks(*_: object) -> None:
        raise AssertionError("serve got past its checks and opened its log")

    monkeypatch.setattr(serve_cli, "open_recorder", got_past_the_checks)
    quiet = SimpleNamespace(signal=lambda *_: None, SIGINT=signal.SIGINT, SIGTERM=signal.SIGTERM)
    monkeypatch.setattr(serve_cli, "signal", quiet)  # pytest keeps its own handlers
    code = main(["serve", "--log-dir", str(tmp_path / "logs"), *flags])
    err = capsys.readouterr().err
    assert code == 2, err
    (line,) = err.strip().splitlines()
    assert line.startswith("glider-hil serve: ")
    return line


# ---- setpoint limits -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "flag", ["--max-depth", "--min-depth", "--max-pitch"], ids=lambda flag: flag
)
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_non_finite_limit_is_refused_naming_the_flag(tmp_path, capsys, monkeypatch, flag, value):
    line = _refused(tmp_path, capsys, monkeypatch, f"{flag}={value}")
    assert f"{flag} must be a finite number" in line


def test_a_negative_largest_pitch_is_refused(tmp_path, capsys, monkeypatch):
    line = _refused(tmp_path, capsys, monkeypatch, "--max-pitch", "-1")
    assert "--max-pitch" in line and "≥ 0" in line


def test_a_minimum_depth_deeper_than_the_maximum_is_refused(tmp_path, capsys, monkeypatch):
    line = _refused(tmp_path, capsys, monkeypatch, "--min-depth", "10", "--max-depth", "5")
    assert "--min-depth 10 m is deeper than --max-depth 5 m" in line


def test_equal_minimum_and_maximum_depth_admit_that_one_depth():
    limits = SetpointLimits(min_depth=5.0, max_depth=5.0, max_abs_pitch=0.0)
    assert limits.violation("depth", 5.0) == ""
    assert limits.violation("depth", 5.5) and limits.violation("depth", 4.5)
    assert limits.violation("pitch", 0.0) == "" and limits.violation("pitch", 0.1)


@pytest.mark.parametrize("channel", ["depth", "pitch"])
@pytest.mark.parametrize(
    "limits",
    [SetpointLimits(), SetpointLimits(min_depth=0.0, max_depth=50.0, max_abs_pitch=0.5)],
    ids=["no limits", "limits"],
)
def test_a_nan_setpoint_is_refused_by_the_limits(channel, limits):
    assert "not a finite number" in limits.violation(channel, math.nan)


# ---- stale timeout -------------------------------------------------------------------------


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0"])
def test_a_stale_timeout_that_never_expires_or_always_has_is_refused(
    tmp_path, capsys, monkeypatch, value
):
    line = _refused(tmp_path, capsys, monkeypatch, f"--stale-timeout={value}")
    assert "--stale-timeout must be a positive finite number of s" in line


# ---- sample period: serve ------------------------------------------------------------------


@pytest.mark.parametrize("value", ["0", "-0.1", "nan", "1e-6", "1e308", "inf"])
def test_serve_refuses_a_sample_period_out_of_range(tmp_path, capsys, monkeypatch, value):
    line = _refused(
        tmp_path, capsys, monkeypatch, "--profile", "ardusub", f"--sample-period={value}"
    )
    assert "--sample-period must be 0.001..2000 s" in line


def test_serve_without_sample_period_takes_the_profiles():
    from hil_service.cli import build_parser
    from hil_service.cli.serve import config_from_args

    args = build_parser("serve").parse_args(["serve", "--profile", "ardusub"])
    assert config_from_args(args).service.sample_period == 0.1


@pytest.mark.parametrize("period", ["1e-12", "1e308", "0.0001"])
def test_a_profile_period_out_of_range_names_the_file_and_line(
    tmp_path, capsys, monkeypatch, period
):
    path = tmp_path / "vehicle.toml"
    path.write_text(builtin_text("ardusub").replace(ARDUSUB_PERIOD_LINE, f"period = {period}"))
    with pytest.raises(ProfileError) as refused:
        load_profile(path)
    assert f"{path} line 9: [sampling] period: must be 0.001..2000 s" in str(refused.value)
    line = _refused(tmp_path, capsys, monkeypatch, "--profile", str(path))
    assert f"{path} line 9: [sampling] period" in line


# ---- log directory -------------------------------------------------------------------------


def test_serve_refuses_a_log_directory_that_is_a_file(tmp_path, capsys, monkeypatch):
    taken = tmp_path / "afile"
    taken.write_text("not a directory")
    line = _refused(tmp_path, capsys, monkeypatch, "--log-dir", str(taken))
    assert f"--log-dir {taken}: not a directory" in line
    assert taken.read_text() == "not a directory"


def test_serve_refuses_a_log_directory_it_cannot_create(tmp_path, capsys, monkeypatch):
    taken = tmp_path / "afile"
    taken.write_text("")
    line = _refused(tmp_path, capsys, monkeypatch, "--log-dir", str(taken / "logs"))
    assert f"--log-dir {taken / 'logs'}: cannot create" in line


# ---- replay: sample period -----------------------------------------------------------------

STEPS = 60  # vehicle stream ticks, 0.1 s apart: 6 s of log


def _periodic_log(tmp_path, recorded_period: float):
    """A log as ``serve --profile ardusub --sample-period RECORDED_PERIOD`` writes it: the
    stored configuration, then every stream (attitude, Bar30 pressure, servo readback)
    every 0.1 s on the vehicle's clock."""
    profile = load_profile("ardusub")
    config = ServiceConfig(profile=profile, sample_period=recorded_period)
    directory = tmp_path / "recorded"
    recorder = McapRecorder(directory, config.to_metadata()).start()
    vehicle = MavlinkCodec(1, 1)
    for k in range(STEPS):
        ms = 1000 + 100 * k
        hpa = profile.pressure.pressure_hpa(10.0 + 0.01 * k)
        messages = (
            dialect.MAVLink_attitude_message(ms, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0),
            dialect.MAVLink_scaled_pressure2_message(ms, hpa, 0.0, 1500, 0),
            dialect.MAVLink_servo_output_raw_message(ms * 1000, 0, *([1500] * 16)),
        )
        for i, message in enumerate(messages):
            recorder.raw("in", vehicle.pack(message), t_ns=(ms + i) * 1_000_000)
    recorder.close()
    (path,) = directory.glob("*.mcap")
    return path


def _replayed_samples(capsys, log, *flags: str) -> int:
    assert main(["replay", "--fast", "--json", str(log), *flags]) == 0
    return json.loads(capsys.readouterr().out)["samples"]


def _profile_file(tmp_path, period: float):
    path = tmp_path / f"every-{period}.toml"
    path.write_text(builtin_text("ardusub").replace(ARDUSUB_PERIOD_LINE, f"period = {period}"))
    return path


def test_replay_period_precedence_flag_then_profile_given_then_recorded(tmp_path, capsys):
    log = _periodic_log(tmp_path, recorded_period=0.2)
    slow = _profile_file(tmp_path, 0.5)
    # 6 s of streams: about 30 samples at 0.2 s, 12 at 0.5 s, 60 at 0.1 s.
    recorded = _replayed_samples(capsys, log)
    assert STEPS / 2 - 3 <= recorded <= STEPS / 2, "the recorded period, not the profile's"
    given_profile = _replayed_samples(capsys, log, "--profile", str(slow))
    assert STEPS / 5 - 3 <= given_profile <= STEPS / 5, "the period of the --profile given"
    flag = _replayed_samples(capsys, log, "--profile", str(slow), "--sample-period", "0.1")
    assert STEPS - 3 <= flag <= STEPS, "--sample-period over both"


@pytest.mark.parametrize("value", ["0", "-1", "nan", "1e-4", "1e308"])
def test_replay_refuses_a_sample_period_out_of_range(tmp_path, capsys, value):
    log = _periodic_log(tmp_path, recorded_period=0.1)
    assert main(["replay", "--fast", str(log), f"--sample-period={value}"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "glider-hil replay: --sample-period must be 0.001..2000 s" in err


def test_replay_refuses_a_sample_period_for_a_lockstep_log(tmp_path, capsys):
    log = _periodic_log(tmp_path, recorded_period=0.1)
    assert main(["replay", "--fast", str(log), "--profile", "glider", "--sample-period", "1"]) == 2
    assert "--sample-period needs a periodic profile; glider is not" in capsys.readouterr().err


def test_serve_refuses_a_sample_period_the_profiles_delay_is_too_long_for(
    tmp_path, capsys, monkeypatch
):
    """A delay within its profile's own period can be too long for a shorter period asked
    for on the command line: the sampler keeps the same 16 values a source."""
    profile = tmp_path / "slow.toml"
    profile.write_text(
        builtin_text("ardusub").replace("period = 0.1\n", "period = 0.1\ndelay = 1.0\n"),
        encoding="utf-8",
    )
    assert load_profile(str(profile)).sampling.delay == 1.0  # its own period allows it
    line = _refused(
        tmp_path, capsys, monkeypatch, "--profile", str(profile), "--sample-period", "0.01"
    )
    assert "--sample-period 0.01: the profile's [sampling] delay must be at most 0.1 s" in line
    config = ServiceConfig(profile=load_profile(str(profile)), sample_period=0.1)
    assert config.sample_period == 0.1  # at the profile's own period it serves


def test_replay_refuses_a_sample_period_the_profiles_delay_is_too_long_for(tmp_path, capsys):
    log = _periodic_log(tmp_path, recorded_period=0.1)
    waiting = tmp_path / "waiting.toml"
    text = builtin_text("ardusub").replace("period = 0.1\n", "period = 0.1\ndelay = 1.0\n")
    waiting.write_text(text)
    assert _replayed_samples(capsys, log, "--profile", str(waiting)) > 0  # its own period
    flags = ["--profile", str(waiting), "--sample-period", "0.01"]
    assert main(["replay", "--fast", str(log), *flags]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "--sample-period 0.01: the profile's [sampling] delay must be at most 0.1 s" in err


# ---- links ---------------------------------------------------------------------------------


@pytest.mark.parametrize("connection", ["udpout:999.1.1.1:14550", "tcp:192.168.1.2.3:5760"])
def test_a_link_whose_host_is_no_address_is_refused(tmp_path, capsys, monkeypatch, connection):
    """pymavlink would take it and swallow every send error: serve would be ready and
    reach no one. The host is parsed, never looked up (digits and dots only)."""
    line = _refused(tmp_path, capsys, monkeypatch, "--mavlink", connection)
    host = connection.split(":")[1]
    assert f"--mavlink {connection!r}: host {host!r} is not an address" in line


@pytest.mark.parametrize(
    "connection",
    ["udpin:0.0.0.0:14550", "udpout:127.0.0.1:14550", "tcp:localhost:5760", "/dev/null,57600"],
)
def test_a_link_whose_host_is_an_address_or_no_host_passes_the_check(connection):
    """An address, a name the hosts file resolves, and a serial device that exists (no host
    at all)."""
    from protocols.link_address import connection_problem

    assert connection_problem(connection) == ""


@pytest.mark.parametrize(
    ("connection", "says"),
    [
        ("bogus:xyz", "unknown scheme 'bogus'"),
        ("serial:/dev/ttyUSB0:57600", "unknown scheme 'serial'"),  # not pymavlink's form
        ("udpout:127.0.0.1", "wants HOST:PORT"),
        ("udpout:127.0.0.1:0", "port must be an integer 1..65535, got '0'"),  # sends nowhere
        ("udpin:127.0.0.1:70000", "port must be an integer 0..65535"),
        ("/no/such/serial/device,57600", "no such serial device"),
        ("/dev/null,fast", "the baud rate after the comma must be a positive integer"),
        ("csv:track.csv", "is a CSV log, not a link"),
        ("", "is empty"),
    ],
)
def test_a_link_that_cannot_be_opened_is_refused_for_what_is_wrong_with_it(
    tmp_path, capsys, monkeypatch, connection, says
):
    """pymavlink would answer these with a message about something else ("UDP ports must
    be specified as host:port" for a device with a colon, "invalid literal for int()" for
    an unknown scheme), or send every datagram to port 0; serve names what is wrong, as
    emulate does."""
    line = _refused(tmp_path, capsys, monkeypatch, "--mavlink", connection)
    assert line.startswith("glider-hil serve: --mavlink "), line
    assert says in line and (not connection or repr(connection) in line)


@pytest.mark.parametrize(
    ("connection", "free_port", "problem"),
    [
        ("/dev/null,57600", False, ""),  # a device that exists, with its baud rate
        ("/dev/null", False, ""),
        ("udpin:127.0.0.1:0", True, ""),  # serve: a free port, named when ready
        ("tcpin:127.0.0.1:0", True, ""),
        ("udpin:127.0.0.1:0", False, "port must be an integer 1..65535"),  # emulate
        ("udpout:127.0.0.1:0", True, "port must be an integer 1..65535"),
        ("tcp:127.0.0.1:0", True, "port must be an integer 1..65535"),
    ],
)
def test_serial_devices_with_a_baud_rate_and_free_ports_where_they_listen(
    connection, free_port, problem
):
    from protocols.link_address import connection_problem

    found = connection_problem(connection, free_port=free_port)
    assert (problem in found) if problem else found == ""


def test_a_regular_file_named_with_a_baud_rate_is_still_a_file(tmp_path):
    from protocols.link_address import connection_problem

    afile = tmp_path / "ttyUSB0"
    afile.write_bytes(b"")
    assert "is a file, not a link" in connection_problem(f"{afile},57600")
