"""Vehicle profiles: the built-ins read what the emulators send, bad files name their line."""

from __future__ import annotations

import math

import pytest

from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import (
    BUILTIN,
    ProfileError,
    PwmRange,
    builtin_text,
    load_profile,
    message_clock,
    parse_profile,
)
from protocols.samples import BallastCommand, TelemetrySample


def _roundtrip(message):
    """Through the wire, as the service would see it."""
    codec = MavlinkCodec(1, 1)
    (decoded,) = MavlinkCodec(255, 0).parse(codec.pack(message), datagram=True)
    return decoded


def test_builtins_load_and_name_themselves():
    for name in BUILTIN:
        profile = load_profile(name)
        assert profile.name == name
        assert profile.text == builtin_text(name)
    assert load_profile("glider").sampling.mode == "lockstep"
    ardusub = load_profile("ardusub")
    assert ardusub.sampling.mode == "periodic"
    assert ardusub.sampling.period == pytest.approx(0.1)


def test_glider_profile_reads_what_the_mapping_sends():
    """The built-in ``glider`` profile is today's contract: same values as mapping.py."""
    profile = load_profile("glider")
    sample = TelemetrySample(1, 12_345, 17.25, -0.125, 0.75, -1.5, 0.01, -0.2)
    readings = {}
    for message in TelemetryMapping().encode_telemetry(sample):
        for reading in profile.readings(_roundtrip(message)):
            readings[reading.signal] = reading.value
    assert readings["depth"] == pytest.approx(sample.depth, abs=1e-3)
    assert readings["pitch"] == pytest.approx(sample.pitch, abs=1e-6)
    assert readings["pitch_rate"] == pytest.approx(sample.pitch_rate, abs=1e-6)
    assert readings["climb"] == pytest.approx(sample.climb, abs=1e-6)
    assert readings["u_depth"] == pytest.approx(sample.u_depth, abs=1e-6)
    assert readings["u_pitch"] == pytest.approx(sample.u_pitch, abs=1e-6)
    # Commands: the same DO_SET_ACTUATOR the mapping builds, read back by the mapping.
    (command,) = profile.command_messages(0.5, -1.0, target_system=1)
    parsed = TelemetryMapping().parse_ballast_command(_roundtrip(command))
    assert parsed == BallastCommand(0.5, -1.0)


def test_ardusub_depth_pitch_servos_and_fallback():
    profile = load_profile("ardusub")
    pressure = dialect.MAVLink_scaled_pressure2_message(
        1000, profile.pressure.pressure_hpa(12.0), 0.0, 1500, 0
    )
    hud = dialect.MAVLink_vfr_hud_message(0.0, 0.0, 0, 0, -11.5, 0.3)
    attitude = dialect.MAVLink_attitude_message(1000, 0.0, 0.2, 0.0, 0.0, 0.05, 0.0)
    servos = [1500] * 16
    servos[8], servos[9] = 1900, 1300  # servo9 (depth) full up, servo10 (pitch) half down
    servo = dialect.MAVLink_servo_output_raw_message(123, 0, *servos)
    got = {
        (r.signal, r.rank): r.value
        for m in (pressure, hud, attitude, servo)
        for r in profile.readings(_roundtrip(m))
    }
    assert got[("depth", 0)] == pytest.approx(12.0, abs=1e-3)
    assert got[("depth", 1)] == pytest.approx(11.5)  # VFR_HUD.alt, the fallback
    assert got[("pitch", 0)] == pytest.approx(0.2)
    assert got[("u_depth", 0)] == pytest.approx(2.0)  # 1900 µs = wire 1 = 2 model units
    assert got[("u_pitch", 0)] == pytest.approx(-1.0)  # 1300 µs = wire −0.5
    commands = profile.command_messages(1.0, math.nan, target_system=7)
    assert len(commands) == 1  # NaN leaves pitch alone
    command = _roundtrip(commands[0])
    assert command.command == dialect.MAV_CMD_DO_SET_SERVO
    assert (command.target_system, command.param1, command.param2) == (7, 9.0, 1700.0)
    both = profile.command_messages(-2.0, 2.0, target_system=7)
    assert [(c.param1, c.param2) for c in both] == [(9.0, 1100.0), (10.0, 1900.0)]
    assert profile.intervals(0.1) == {
        "SCALED_PRESSURE2": 0.1,
        "VFR_HUD": 0.1,
        "ATTITUDE": 0.1,
        "SERVO_OUTPUT_RAW": 0.1,
    }
    assert profile.staleness(0.25)["depth"] == (0.5, 0.5)


def test_clocks_of_messages():
    attitude = dialect.MAVLink_attitude_message(77, 0, 0, 0, 0, 0, 0)
    servo = dialect.MAVLink_servo_output_raw_message(0xFFFFFFFF, 0, *([1500] * 16))
    actuators = dialect.MAVLink_actuator_output_status_message(1 << 40, 0, [0.0] * 32)
    assert message_clock(attitude) == ("ms32", 77)
    assert message_clock(servo) == ("us32", 0xFFFFFFFF)
    assert message_clock(actuators) == ("us64", 1 << 40)
    assert message_clock(dialect.MAVLink_vfr_hud_message(0, 0, 0, 0, 0, 0)) is None


def test_pwm_range_is_linear_each_side_and_editable():
    pwm = PwmRange(1000, 2000, 1400)
    assert pwm.to_wire(2000) == 1.0
    assert pwm.to_wire(1000) == -1.0
    assert pwm.to_wire(1700) == pytest.approx(0.5)
    assert pwm.to_wire(1200) == pytest.approx(-0.5)
    assert pwm.to_wire(2400) == 1.0  # clipped
    for wire in (-1.0, -0.3, 0.0, 0.6, 1.0):
        assert pwm.to_wire(pwm.from_wire(wire)) == pytest.approx(wire, abs=1 / 600)


def test_edited_servo_numbers_and_range(tmp_path):
    text = builtin_text("ardusub").replace("output = 9", "output = 5")
    text = text.replace("pwm_max = 1900", "pwm_max = 2000")
    path = tmp_path / "mine.toml"
    path.write_text(text)
    profile = load_profile(str(path))
    (command,) = profile.command_messages(2.0, math.nan, 1)
    assert (command.param1, command.param2) == (5.0, 2000.0)


BAD = [
    ("sampling", 'mode = "sometimes"', "mode", "'sometimes' is not one of"),
    ("signals.pitch", 'field = "pich"', "field", "ATTITUDE has no field 'pich'"),
    ("signals.depth", 'message = "NO_SUCH"', "message", "no message 'NO_SUCH'"),
    ("ballast", "pwm_neutral = 2000", "pwm_neutral", "pwm_min < pwm_neutral < pwm_max"),
    ("ballast.pitch", "output = 9", "output", "different outputs"),
    ("ballast.depth", "output = 17", "output", "must be an integer 1..16"),
    ("signals.pitch", 'scale = "big"', "scale", "must be a number"),
    ("signals.pitch", "colour = 3", "colour", "unknown field"),
]


@pytest.mark.parametrize(("table", "line", "key", "message"), BAD)
def test_bad_profile_names_the_line(table, line, key, message):
    lines = builtin_text("ardusub").splitlines()
    # Put the bad line in the (first) table named, replacing the key if it is there.
    header = next(
        i for i, text in enumerate(lines) if text.strip() in (f"[{table}]", f"[[{table}]]")
    )
    end = next((i for i in range(header + 1, len(lines)) if lines[i].startswith("[")), len(lines))
    lines = [
        text
        for i, text in enumerate(lines)
        if not (header < i < end and text.split("=")[0].strip() == key)
    ]
    lines.insert(header + 1, line)
    with pytest.raises(ProfileError) as error:
        parse_profile("\n".join(lines), "bad.toml")
    assert f"bad.toml line {header + 2}:" in str(error.value)
    assert message in str(error.value)


def test_toml_syntax_error_and_missing_things(tmp_path):
    with pytest.raises(ProfileError, match=r"bad\.toml: not valid TOML: .*line 3"):
        parse_profile('[profile]\nname = "x"\nperiod = = 1\n', "bad.toml")
    with pytest.raises(ProfileError, match=r"signal 'pitch' is required"):
        parse_profile(
            '[profile]\nname = "x"\n[[signals.depth]]\nmessage = "VFR_HUD"\nfield = "alt"\n',
            "p.toml",
        )
    with pytest.raises(ProfileError, match=r"p\.toml line 4: \[sampling\] mode: periodic"):
        parse_profile('[profile]\nname = "x"\n[sampling]\nmode = "periodic"\n', "p.toml")
    with pytest.raises(ProfileError, match="neither a built-in"):
        load_profile(str(tmp_path / "absent.toml"))
