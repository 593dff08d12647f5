"""The companion's manners: heartbeat at 1 Hz as an onboard controller, and stream requests
that fall back to REQUEST_DATA_STREAM and are made again after a reboot or an outage."""

from __future__ import annotations

import pytest

from hil_service.companion import COMPANION_COMPONENT, Companion, CompanionConfig
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import load_profile

PROFILE = load_profile("ardusub")
VEHICLE = MavlinkCodec(1, 1)
US = MavlinkCodec(1, COMPANION_COMPONENT)


def wire(codec, message):
    (decoded,) = MavlinkCodec(0, 0).parse(codec.pack(message), datagram=True)
    return decoded


def attitude(ms: int):
    return wire(VEHICLE, dialect.MAVLink_attitude_message(ms, 0, 0, 0, 0, 0, 0))


def ack(result: int):
    return wire(
        VEHICLE,
        dialect.MAVLink_command_ack_message(
            dialect.MAV_CMD_SET_MESSAGE_INTERVAL, result, 0, 0, 1, COMPANION_COMPONENT
        ),
    )


def run(companion, vehicle_answer, seconds, start=0.0, boot_ms=10_000, step=0.05):
    """Poll every ``step`` s; ``vehicle_answer(request)`` gives the vehicle's reply or None."""
    sent = []
    for i in range(round(seconds / step)):
        t = start + i * step
        companion.on_message(attitude(boot_ms + int((t - start) * 1000)), t)
        for message in companion.poll(t):
            sent.append((t, wire(US, message)))
            reply = vehicle_answer(sent[-1][1])
            if reply is not None:
                companion.on_message(reply, t + 0.01)
    return sent


def test_heartbeat_once_a_second_as_an_onboard_controller():
    companion = Companion(PROFILE, 0.1, 1)
    sent = run(companion, lambda m: None, 5.0)
    beats = [(t, m) for t, m in sent if m.get_type() == "HEARTBEAT"]
    assert len(beats) == 5
    assert [round(t, 2) for t, _ in beats] == [0.0, 1.0, 2.0, 3.0, 4.0]
    _, beat = beats[0]
    assert beat.type == dialect.MAV_TYPE_ONBOARD_CONTROLLER
    assert beat.autopilot == dialect.MAV_AUTOPILOT_INVALID
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 191)


def test_intervals_requested_one_at_a_time_at_the_sample_rate():
    companion = Companion(PROFILE, 0.1, 1)
    sent = run(
        companion,
        lambda m: ack(dialect.MAV_RESULT_ACCEPTED) if m.get_type() == "COMMAND_LONG" else None,
        2.0,
    )
    requests = [m for _, m in sent if m.get_type() == "COMMAND_LONG"]
    assert [int(m.param1) for m in requests] == [
        dialect.MAVLINK_MSG_ID_SCALED_PRESSURE2,
        dialect.MAVLINK_MSG_ID_VFR_HUD,
        dialect.MAVLINK_MSG_ID_ATTITUDE,
        dialect.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
    ]
    assert all(m.command == dialect.MAV_CMD_SET_MESSAGE_INTERVAL for m in requests)
    assert all(m.param2 == 100_000 for m in requests)  # µs
    assert set(companion.states.values()) == {"accepted"}
    assert companion.counters.acks == {"MAV_RESULT_ACCEPTED": 4}


@pytest.mark.parametrize("answer", ["unsupported", "silent"])
def test_refused_or_unanswered_requests_fall_back_to_request_data_stream(answer):
    companion = Companion(PROFILE, 0.1, 1, CompanionConfig(ack_timeout=0.5))

    def vehicle(message):
        if answer == "unsupported" and message.get_type() == "COMMAND_LONG":
            return ack(dialect.MAV_RESULT_UNSUPPORTED)
        return None

    sent = run(companion, vehicle, 8.0)
    streams = [m for _, m in sent if m.get_type() == "REQUEST_DATA_STREAM"]
    assert {m.req_stream_id for m in streams} == {
        dialect.MAV_DATA_STREAM_RAW_SENSORS,
        dialect.MAV_DATA_STREAM_EXTRA2,
        dialect.MAV_DATA_STREAM_EXTRA1,
        dialect.MAV_DATA_STREAM_RC_CHANNELS,
    }
    assert all(m.req_message_rate == 10 and m.start_stop == 1 for m in streams)
    assert set(companion.states.values()) == {"data_stream"}
    if answer == "unsupported":  # refused once: the others go straight to the fallback
        assert companion.counters.interval_requests == 1
        assert companion.counters.unanswered == 0
    else:
        assert companion.counters.interval_requests == 8  # two tries each
        assert companion.counters.unanswered == 8


def test_asked_again_after_a_reboot_and_after_an_outage():
    companion = Companion(PROFILE, 0.1, 1)

    def accept(m):
        return ack(dialect.MAV_RESULT_ACCEPTED) if m.get_type() == "COMMAND_LONG" else None

    run(companion, accept, 2.0, boot_ms=60_000)
    assert companion.counters.interval_requests == 4
    run(companion, accept, 2.0, start=2.0, boot_ms=1_000)  # time_boot_ms restarted
    assert companion.counters.rerequests == {"reboot": 1}
    assert companion.counters.interval_requests == 8
    run(companion, accept, 2.0, start=10.0, boot_ms=11_000)  # 6 s of silence before
    assert companion.counters.rerequests == {"reboot": 1, "outage": 1}
    assert companion.counters.interval_requests == 12
    assert set(companion.states.values()) == {"accepted"}
    # Our own component's messages (another companion's echo) are not the autopilot.
    echo = wire(US, dialect.MAVLink_attitude_message(5, 0, 0, 0, 0, 0, 0))
    companion.on_message(echo, 100.0)
    assert companion.counters.rerequests == {"reboot": 1, "outage": 1}
