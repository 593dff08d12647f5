"""The companion's manners: heartbeat at 1 Hz as an onboard controller, and stream requests
that fall back to REQUEST_DATA_STREAM and are made again after a reboot or an outage."""

from __future__ import annotations

import pytest

from hil_service.sources.companion import COMPANION_COMPONENT, Companion, CompanionConfig
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


def _stream(name: str, ms: int):
    if name == "ATTITUDE":
        return attitude(ms)
    if name == "SCALED_PRESSURE2":
        message = dialect.MAVLink_scaled_pressure2_message(ms, 1163.0, 0, 1500, 0)
    elif name == "SERVO_OUTPUT_RAW":
        message = dialect.MAVLink_servo_output_raw_message(ms * 1000, 0, *([1500] * 16))
    else:
        message = dialect.MAVLink_vfr_hud_message(0, 0, 0, 0, -15.0, 0)
    return wire(VEHICLE, message)


class StreamingVehicle:
    """Streams each message at its rate (Hz on its own clock, None: never), accepts
    SET_MESSAGE_INTERVAL up to ``max_hz``; a ground station may lower rates with ``lower``."""

    def __init__(self, rates: dict[str, float | None], max_hz: float = 50.0):
        self.rates = dict(rates)
        self.max_hz = max_hz
        self.due = dict.fromkeys(rates, 0.0)

    def answer(self, message):
        if message.get_type() != "COMMAND_LONG":
            return None
        name = {
            dialect.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
            dialect.MAVLINK_MSG_ID_SCALED_PRESSURE2: "SCALED_PRESSURE2",
            dialect.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: "SERVO_OUTPUT_RAW",
            dialect.MAVLINK_MSG_ID_VFR_HUD: "VFR_HUD",
        }[int(message.param1)]
        if self.rates[name] is not None:
            self.rates[name] = min(1e6 / message.param2, self.max_hz)
        return ack(dialect.MAV_RESULT_ACCEPTED)

    def lower(self, hz: float) -> None:
        self.rates = {k: (None if v is None else hz) for k, v in self.rates.items()}

    def run(self, companion, start: float, seconds: float, step: float = 0.01) -> None:
        """Vehicle time = ``now`` here (boot at 0); the companion polled every ``step``."""
        for i in range(round(seconds / step)):
            t = start + i * step
            for name, hz in self.rates.items():
                if hz is not None and t >= self.due[name]:
                    companion.on_message(_stream(name, int(t * 1000)), t)
                    self.due[name] = max(self.due[name] + 1 / hz, t)
            for message in companion.poll(t):
                reply = self.answer(wire(US, message))
                if reply is not None:
                    companion.on_message(reply, t + 0.001)


def test_a_stream_lowered_by_a_ground_station_is_asked_for_again():
    companion = Companion(PROFILE, 0.1, 1)
    # Default ArduSub-like rates; the vehicle has no Bar30 (SCALED_PRESSURE2 never comes).
    vehicle = StreamingVehicle(
        {"ATTITUDE": 4.0, "SCALED_PRESSURE2": None, "VFR_HUD": 4.0, "SERVO_OUTPUT_RAW": 4.0}
    )
    vehicle.run(companion, 1.0, 5.0)
    assert set(companion.states.values()) == {"accepted"}
    assert vehicle.rates["ATTITUDE"] == pytest.approx(10.0)
    assert companion.counters.rerequests == {}  # at the requested rate: nothing to ask
    vehicle.lower(4.0)  # MAVProxy's REQUEST_DATA_STREAM at its streamrate
    vehicle.run(companion, 6.0, 3.5)
    # After two slow windows (1 s each of the vehicle's clock) every lowered stream is asked
    # again; the one never heard is left to the profile's fallback.
    assert companion.counters.rerequests == {"rate": 3}
    assert companion.counters.slow_streams == {"ATTITUDE": 1, "VFR_HUD": 1, "SERVO_OUTPUT_RAW": 1}
    assert all(hz == pytest.approx(10.0) for hz in vehicle.rates.values() if hz is not None)
    vehicle.run(companion, 9.5, 10.0)
    assert companion.counters.rerequests == {"rate": 3}  # back at the rate: not asked again
    assert companion.counters.as_dict()["slow_streams"]["ATTITUDE"] == 1


def test_a_vehicle_that_cannot_go_faster_is_asked_ever_less_often():
    companion = Companion(PROFILE, 0.1, 1)
    vehicle = StreamingVehicle(dict.fromkeys(PROFILE.intervals(0.1), 4.0), max_hz=5.0)
    vehicle.run(companion, 1.0, 40.0)
    # Two slow windows of 1, then 2, 4, 8 s: 4 requests per stream in 40 s, not 20.
    assert 3 <= companion.counters.slow_streams["ATTITUDE"] <= 6, companion.counters.slow_streams
    assert companion.counters.interval_requests <= 4 * 7
