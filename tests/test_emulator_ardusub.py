"""`glider-hil emulate --profile ardusub` as a real process: streams the ArduSub way and
answers a ground station as an autopilot does, watched by a MAVLink peer on loopback UDP."""

from __future__ import annotations

import itertools
import math
import struct

import pytest

from hil_service.cli.processes import last_json
from protocols.mavlink_io import dialect
from protocols.profiles import load_profile
from tests.mavlink_peer import UdpPeer

SPEED = 10.0
PROFILE = load_profile("ardusub")
US32_SPAN = (1 << 32) / 1e6


@pytest.fixture
def peer():
    p = UdpPeer()
    yield p
    p.close()


def start(processes, peer, *extra: str):
    return processes.start(
        "emulate",
        "--profile",
        "ardusub",
        "--connect",
        f"udpout:127.0.0.1:{peer.port}",
        "--speed",
        str(SPEED),
        "--duration",
        "600",
        "--excitation",
        "none",
        "--seed",
        "4",
        *extra,
    )


def of(received, kind):
    return [r.message for r in received if r.message.get_type() == kind]


def command_long(command, *params, target=1):
    values = [*params, *([0.0] * (7 - len(params)))]
    return dialect.MAVLink_command_long_message(target, 1, command, 0, *values)


def wait_for(peer, predicate, timeout=20.0):
    """Messages until ``predicate(messages)`` holds; fails with what arrived otherwise."""
    received = peer.receive_until(lambda got: predicate([r.message for r in got]), timeout)
    messages = [r.message for r in received]
    assert predicate(messages), sorted({m.get_type() for m in messages})
    return received


def ack_for(command):
    def check(messages):
        return any(m.get_type() == "COMMAND_ACK" and m.command == command for m in messages)

    return check


def rate(received, kind) -> float:
    """Messages per simulated second, from their own stamps."""
    messages = of(received, kind)
    stamps = [m.time_boot_ms / 1000 for m in messages]
    return (len(stamps) - 1) / (stamps[-1] - stamps[0])


def test_streams_at_their_own_rates_stamped_when_sent_and_the_us_clock_wraps(processes, peer):
    emulator = start(processes, peer, "--uptime", f"{US32_SPAN - 3:.3f}")
    received = peer.receive_until(lambda got: len(got) > 0, 20.0)
    received += peer.receive_for(12.0 / SPEED)  # 12 simulated seconds, across the wrap
    kinds = {r.message.get_type() for r in received}
    assert {"ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD", "SERVO_OUTPUT_RAW", "HEARTBEAT"} <= kinds
    assert "ACTUATOR_OUTPUT_STATUS" not in kinds
    # Stamped when sent: ATTITUDE and SCALED_PRESSURE2 never share a timestamp in lockstep.
    attitude = {m.time_boot_ms for m in of(received, "ATTITUDE")}
    pressure = {m.time_boot_ms for m in of(received, "SCALED_PRESSURE2")}
    assert len(attitude & pressure) < 0.2 * len(pressure)
    assert rate(received, "ATTITUDE") == pytest.approx(10.0, rel=0.15)
    assert rate(received, "SCALED_PRESSURE2") == pytest.approx(4.0, rel=0.2)
    # Jitter: the intervals between ATTITUDE stamps vary.
    stamps = sorted(attitude)
    gaps = {b - a for a, b in itertools.pairwise(stamps)}
    assert len(gaps) > 3
    # The uint32 µs clock of SERVO_OUTPUT_RAW wraps, time_boot_ms (ms32) does not.
    usec = [m.time_usec for m in of(received, "SERVO_OUTPUT_RAW")]
    assert any(b < a for a, b in itertools.pairwise(usec))
    assert min(attitude) / 1000 < US32_SPAN < max(attitude) / 1000
    # PWM outputs: thrusters neutral, ballast servos in range.
    servo = of(received, "SERVO_OUTPUT_RAW")[-1]
    assert servo.servo1_raw == 1500
    assert 1100 <= servo.servo9_raw <= 1900 and 1100 <= servo.servo10_raw <= 1900
    out, _ = processes.stop(emulator)
    summary = last_json(out, "emulator")
    assert summary["streams_sent"]["ATTITUDE"] > 0


def test_rates_change_by_message_interval_data_stream_and_parameter(processes, peer):
    start(processes, peer)
    peer.receive_until(lambda got: len(got) > 5, 20.0)
    att_id = dialect.MAVLINK_MSG_ID_ATTITUDE
    peer.send(command_long(dialect.MAV_CMD_SET_MESSAGE_INTERVAL, att_id, 50_000))  # 20 Hz
    ack = of(wait_for(peer, ack_for(dialect.MAV_CMD_SET_MESSAGE_INTERVAL)), "COMMAND_ACK")
    assert ack[-1].result == dialect.MAV_RESULT_ACCEPTED
    assert rate(peer.receive_for(5.0 / SPEED), "ATTITUDE") == pytest.approx(20, rel=0.15)
    # REQUEST_DATA_STREAM: the RAW_SENSORS group (SCALED_PRESSURE2) stops.
    peer.send(
        dialect.MAVLink_request_data_stream_message(1, 1, dialect.MAV_DATA_STREAM_RAW_SENSORS, 0, 0)
    )
    peer.receive_for(0.3)
    later = peer.receive_for(3.0 / SPEED)
    assert of(later, "SCALED_PRESSURE2") == [] and of(later, "ATTITUDE")
    # A parameter: SR0_EXTRA1 (ATTITUDE's group) set to 2 Hz takes effect.
    peer.send(
        dialect.MAVLink_param_set_message(1, 1, b"SR0_EXTRA1", 2.0, dialect.MAV_PARAM_TYPE_REAL32)
    )
    values = of(
        wait_for(peer, lambda ms: any(m.get_type() == "PARAM_VALUE" for m in ms)), "PARAM_VALUE"
    )
    assert (values[-1].param_id, values[-1].param_value) == ("SR0_EXTRA1", 2.0)
    peer.receive_for(0.3)
    assert rate(peer.receive_for(10.0 / SPEED), "ATTITUDE") == pytest.approx(2, rel=0.25)
    # Unknown message: refused.
    peer.send(command_long(dialect.MAV_CMD_SET_MESSAGE_INTERVAL, 65000, 50_000))
    ack = of(wait_for(peer, ack_for(dialect.MAV_CMD_SET_MESSAGE_INTERVAL)), "COMMAND_ACK")
    assert ack[-1].result == dialect.MAV_RESULT_DENIED


def test_do_set_servo_moves_the_ballast(processes, peer):
    start(processes, peer, "--command-timeout", "1000")
    peer.receive_until(lambda got: len(got) > 5, 20.0)
    for servo, pwm in ((9, 1900), (10, 1100)):
        peer.send(command_long(dialect.MAV_CMD_DO_SET_SERVO, servo, pwm))
        ack = of(wait_for(peer, ack_for(dialect.MAV_CMD_DO_SET_SERVO)), "COMMAND_ACK")
        assert ack[-1].result == dialect.MAV_RESULT_ACCEPTED
    # The actuator's rate limit takes a few steps; then the outputs read back the command.
    received = wait_for(
        peer,
        lambda ms: any(
            m.get_type() == "SERVO_OUTPUT_RAW" and m.servo9_raw == 1900 and m.servo10_raw == 1100
            for m in ms
        ),
    )
    assert received
    # A thruster (SERVO3_FUNCTION 35, a motor) fails as on ArduPilot, with its message.
    peer.send(command_long(dialect.MAV_CMD_DO_SET_SERVO, 3, 1500))
    got = wait_for(peer, ack_for(dialect.MAV_CMD_DO_SET_SERVO))
    assert of(got, "COMMAND_ACK")[-1].result == dialect.MAV_RESULT_FAILED
    texts = [m.text for m in of(got, "STATUSTEXT")]  # sent before the ack
    assert "ServoRelayEvent: Channel 3 is already in use" in texts
    for servo, pwm in ((9, math.nan), (9, 3000)):  # NaN, out of range
        peer.send(command_long(dialect.MAV_CMD_DO_SET_SERVO, servo, pwm))
        ack = of(wait_for(peer, ack_for(dialect.MAV_CMD_DO_SET_SERVO)), "COMMAND_ACK")
        assert ack[-1].result == dialect.MAV_RESULT_DENIED


def test_answers_a_ground_station(processes, peer):
    emulator = start(processes, peer)
    peer.receive_until(lambda got: len(got) > 5, 20.0)
    # Parameters: the whole list, one by name, and a change that takes effect.
    peer.send(dialect.MAVLink_param_request_list_message(1, 1))
    params = of(
        wait_for(
            peer,
            lambda ms: (lambda v: bool(v) and len(v) >= v[0].param_count)(
                [m for m in ms if m.get_type() == "PARAM_VALUE"]
            ),
        ),
        "PARAM_VALUE",
    )
    names = {p.param_id: p.param_value for p in params}
    assert {"SYSID_THISMAV", "CMD_TIMEOUT", "SR0_EXTRA1", "SERVO9_MIN", "SERVO10_TRIM"} <= set(
        names
    )
    assert names["SERVO9_MIN"] == 1100 and names["SR0_EXTRA1"] == 10
    peer.send(dialect.MAVLink_param_request_read_message(1, 1, b"CMD_TIMEOUT", -1))
    read = of(
        wait_for(peer, lambda ms: any(m.get_type() == "PARAM_VALUE" for m in ms)), "PARAM_VALUE"
    )
    assert (read[-1].param_id, read[-1].param_value) == ("CMD_TIMEOUT", 10.0)
    peer.send(
        dialect.MAVLink_param_set_message(1, 1, b"SYSID_THISMAV", 7.0, dialect.MAV_PARAM_TYPE_INT32)
    )
    kept = of(
        wait_for(peer, lambda ms: any(m.get_type() == "PARAM_VALUE" for m in ms)), "PARAM_VALUE"
    )
    assert kept[-1].param_value == 1.0  # read-only: the value in force
    # Mission, version, home, an unknown command, COMMAND_INT.
    peer.send(dialect.MAVLink_mission_request_list_message(1, 1, 0))
    count = of(
        wait_for(peer, lambda ms: any(m.get_type() == "MISSION_COUNT" for m in ms)), "MISSION_COUNT"
    )
    assert count[-1].count == 0
    peer.send(
        command_long(dialect.MAV_CMD_REQUEST_MESSAGE, dialect.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    )
    got = wait_for(
        peer,
        lambda ms: (
            ack_for(dialect.MAV_CMD_REQUEST_MESSAGE)(ms)
            and any(m.get_type() == "AUTOPILOT_VERSION" for m in ms)
        ),
    )
    assert of(got, "AUTOPILOT_VERSION")[-1].capabilities & dialect.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    expected = {
        dialect.MAV_CMD_GET_HOME_POSITION: dialect.MAV_RESULT_ACCEPTED,  # the surfacing point
        dialect.MAV_CMD_NAV_TAKEOFF: dialect.MAV_RESULT_UNSUPPORTED,
    }
    for command, result in expected.items():
        peer.send(command_long(command))
        ack = of(wait_for(peer, ack_for(command)), "COMMAND_ACK")
        assert ack[-1].result == result
    peer.send(
        dialect.MAVLink_command_int_message(
            1, 1, 0, dialect.MAV_CMD_DO_REPOSITION, 0, 0, 0, 0, 0, 0, 0, 0, 0
        )
    )
    ack = of(wait_for(peer, ack_for(dialect.MAV_CMD_DO_REPOSITION)), "COMMAND_ACK")
    assert ack[-1].result == dialect.MAV_RESULT_UNSUPPORTED
    # MAVLink FTP: a NAK for the request (sequence + 1, the request's opcode).
    request = struct.pack("<HBBBBBBI", 41, 0, 4, 0, 0, 0, 0, 0) + b"@PARAM/param.pck"
    peer.send(
        dialect.MAVLink_file_transfer_protocol_message(
            0, 1, 1, list(request + b"\0" * (251 - len(request)))
        )
    )
    ftp = of(
        wait_for(peer, lambda ms: any(m.get_type() == "FILE_TRANSFER_PROTOCOL" for m in ms)),
        "FILE_TRANSFER_PROTOCOL",
    )
    seq, _session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(ftp[-1].payload))
    assert (seq, opcode, size, req_opcode) == (42, 129, 1, 4)
    # A heartbeat from an onboard controller is seen and counted.
    peer.send(
        dialect.MAVLink_heartbeat_message(
            dialect.MAV_TYPE_ONBOARD_CONTROLLER, dialect.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3
        )
    )
    peer.receive_for(0.3)
    out, _ = processes.stop(emulator)
    summary = last_json(out, "emulator")
    gcs = summary["gcs"]
    assert gcs["heartbeats"] == {"MAV_TYPE_ONBOARD_CONTROLLER": 1}
    assert gcs["ftp_naks"] == 1 and summary["mission"]["downloads"] == 1
    assert gcs["param_lists"] == 1
