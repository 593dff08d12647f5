"""The MAVLink mapping, units, codec robustness, Zenoh keys and JSON Schemas."""

from __future__ import annotations

import math
import os

import pytest

from protocols import keys
from protocols.mapping import CommandRejected, TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.samples import BallastCommand, TelemetrySample
from protocols.schemas import SCHEMA_NAMES, load_schema, validate, validation_errors
from protocols.units import InputScale, PressureDepth


def test_pressure_depth_round_trip_and_bar30_convention():
    fresh = PressureDepth(water_density=997.0, surface_hpa=1000.0)
    assert fresh.depth_m(1000.0) == 0.0
    assert fresh.depth_m(1000.0 + 997.0 * 9.80665 / 100.0) == pytest.approx(1.0)
    sea = PressureDepth()
    assert sea.depth_m(sea.pressure_hpa(123.4)) == pytest.approx(123.4)
    with pytest.raises(ValueError):
        PressureDepth(water_density=0.0)


def test_input_scale_maps_full_scale_to_one():
    scale = InputScale(full_scale=2.0)
    assert scale.to_wire(2.0) == 1.0 and scale.to_model(-0.5) == -1.0
    with pytest.raises(ValueError):
        InputScale(full_scale=-1.0)


def test_telemetry_round_trip_through_frames():
    mapping = TelemetryMapping()
    sender, receiver = MavlinkCodec(1, 1), MavlinkCodec(255, 191)
    sample = TelemetrySample(1, 42_000, depth=17.25, pitch=-0.1, u_depth=1.5, u_pitch=-2.0)
    frames = b"".join(sender.pack(m) for m in mapping.encode_telemetry(sample))
    messages = receiver.parse(frames)
    kinds = [m.get_type() for m in messages]
    assert kinds == ["ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD", "ACTUATOR_OUTPUT_STATUS"]
    attitude, pressure, hud, actuators = messages
    assert attitude.time_boot_ms == pressure.time_boot_ms == actuators.time_usec // 1000 == 42_000
    assert mapping.depth_from_pressure(pressure) == pytest.approx(17.25, abs=1e-4)
    assert hud.alt == pytest.approx(-17.25)
    assert attitude.pitch == pytest.approx(-0.1)
    assert mapping.inputs_from_actuators(actuators) == pytest.approx((1.5, -2.0))


def test_ballast_command_round_trip_nan_keeps_and_bad_values_refused():
    mapping = TelemetryMapping()
    message = mapping.ballast_command(BallastCommand(1.0, math.nan), target_system=3)
    assert message.target_system == 3 and message.command == dialect.MAV_CMD_DO_SET_ACTUATOR
    parsed = mapping.parse_ballast_command(message)
    assert parsed.u_depth == 1.0 and math.isnan(parsed.u_pitch)
    for p1, p2 in ((math.nan, math.nan), (math.inf, 0.0), (0.0, -1.01)):
        bad = mapping.ballast_command(BallastCommand(0.0, 0.0), 1)
        bad.param1, bad.param2 = p1, p2
        with pytest.raises(CommandRejected):
            mapping.parse_ballast_command(bad)


def test_codec_counts_garbage_and_keeps_good_frames():
    sender, receiver = MavlinkCodec(1, 1), MavlinkCodec(255, 191)
    good = sender.pack(dialect.MAVLink_attitude_message(1, 0, 0.2, 0, 0, 0, 0))
    corrupt = bytearray(good)
    corrupt[10] ^= 0x55
    noise = bytes(b for b in os.urandom(5000) if b not in (0xFD, 0xFE))
    messages = receiver.parse(noise + good + bytes(corrupt) + good, datagram=True)
    assert [m.get_type() for m in messages] == ["ATTITUDE", "ATTITUDE"]
    assert receiver.counters.bad_frames >= 1


def test_each_datagram_parses_on_its_own_whatever_came_before():
    sender, receiver = MavlinkCodec(1, 1), MavlinkCodec(255, 191)
    good = sender.pack(dialect.MAVLink_attitude_message(1, 0, 0.2, 0, 0, 0, 0))
    for _ in range(200):
        receiver.parse(os.urandom(300), datagram=True)
        receiver.parse(good[:9], datagram=True)  # a truncated frame
        assert [m.pitch for m in receiver.parse(good, datagram=True)] == [pytest.approx(0.2)]
    assert receiver.counters.bad_frames >= 200


def test_zenoh_keys_follow_the_contract():
    assert keys.telemetry(1) == "glider/1/telemetry"
    assert keys.umodel(7, "pitch") == "glider/7/umodel/pitch"
    assert keys.command_ballast(1) == "glider/1/command/ballast"
    assert keys.setpoint(1, "depth") == "glider/1/setpoint/depth"
    assert keys.control(1) == "glider/1/control"
    assert keys.health(1) == "glider/1/health"
    assert keys.service(1) == "glider/1/service"
    assert keys.schema_for_key("glider/3/command/ballast") == "command_ballast"
    with pytest.raises(ValueError):
        keys.umodel(1, "roll")
    with pytest.raises(ValueError):
        keys.telemetry(0)


@pytest.mark.parametrize("name", SCHEMA_NAMES)
def test_schemas_are_valid_draft_2020_12(name):
    assert load_schema(name)["$schema"].endswith("2020-12/schema")
    validation_errors(name, {})  # compiles


def test_schemas_accept_real_payloads_and_reject_wrong_ones():
    sample = TelemetrySample(1, 1000, 15.0, 0.1, 0.5, -0.5)
    validate("telemetry", sample.to_payload())
    validate("setpoint", {"value": 12.5})
    validate("control", {"enabled": False})
    with pytest.raises(ValueError, match="enabled"):
        validate("control", {"enabled": "yes"})
    with pytest.raises(ValueError):
        validate("setpoint", {"value": "deep"})


def test_ballast_command_fields_on_the_wire():
    """Every field of the COMMAND_LONG the service sends, as decoded by the vehicle."""
    from protocols.mapping import AUTOPILOT_COMPONENT, is_ballast_command

    mapping = TelemetryMapping()
    frame = MavlinkCodec(255, 191).pack(mapping.ballast_command(BallastCommand(1.0, math.nan), 7))
    (message,) = MavlinkCodec(7, 1).parse(frame, datagram=True)
    assert is_ballast_command(message)
    assert (message.target_system, message.target_component) == (7, AUTOPILOT_COMPONENT)
    assert message.command == dialect.MAV_CMD_DO_SET_ACTUATOR
    assert message.confirmation == 0  # a first transmission, never a retry
    assert message.param1 == 0.5  # 1.0 model unit at the default full scale 2.0
    assert math.isnan(message.param2)  # pitch left unchanged
    assert all(
        math.isnan(p) for p in (message.param3, message.param4, message.param5, message.param6)
    )
    assert message.param7 == 0.0  # actuator set 0: the ballast pair, not another set


def test_only_do_set_actuator_commands_are_ballast_commands():
    from protocols.mapping import is_ballast_command

    nan = math.nan
    arm = dialect.MAVLink_command_long_message(
        1, 1, dialect.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, nan, nan, nan, nan, 0
    )
    assert not is_ballast_command(arm)
    ack = dialect.MAVLink_command_ack_message(dialect.MAV_CMD_DO_SET_ACTUATOR, 0, 0, 0, 1, 1)
    assert not is_ballast_command(ack)  # the right command number, another message
