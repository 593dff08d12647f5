"""The companion schedule polls only the companions with something due, and sends exactly
what polling every companion at every tick sends: the same messages, at the same ticks, in
the same order, through stream requests accepted, refused, unsupported and unanswered, an
outage and a reboot."""

from __future__ import annotations

from typing import Any

from hil_service.sources.companion import COMPANION_COMPONENT, Companion
from hil_service.sources.companion_schedule import CompanionSchedule
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import load_profile

PROFILE = load_profile("ardusub")
VEHICLES = range(1, 8)
TICK = 0.01  # s, as the service's COMPANION_POLL
SECONDS = 12.0


def decoded(system_id: int, message: Any) -> Any:
    frame = MavlinkCodec(system_id, 1).pack(message)
    (out,) = MavlinkCodec(0, 0).parse(frame, datagram=True)
    return out


def answer(system_id: int, request: Any) -> Any:
    """Vehicle 1 accepts, 2 denies, 3 does not support SET_MESSAGE_INTERVAL, 4 never
    answers; 5, 6 and 7 accept."""
    if request.get_type() != "COMMAND_LONG" or system_id == 4:
        return None
    result = {2: dialect.MAV_RESULT_DENIED, 3: dialect.MAV_RESULT_UNSUPPORTED}.get(
        system_id, dialect.MAV_RESULT_ACCEPTED
    )
    return decoded(
        system_id,
        dialect.MAVLink_command_ack_message(
            request.command, result, 0, 0, system_id, COMPANION_COMPONENT
        ),
    )


def telemetry(system_id: int, t: float) -> Any | None:
    """What vehicle ``system_id`` streams at tick ``t``: ATTITUDE every 0.1 s (phase by
    vehicle), none from vehicle 5 between 3 and 7 s (an outage), vehicle 6's clock back to
    zero at 5 s (a reboot), nothing at all from vehicle 7 before 2 s."""
    tick = round(t / TICK)
    if (tick + system_id) % 10 or (system_id == 5 and 3.0 <= t < 7.0):
        return None
    if system_id == 7 and t < 2.0:
        return None
    boot_ms = 60_000 + round(t * 1000)
    if system_id == 6 and t >= 5.0:
        boot_ms = round((t - 5.0) * 1000)
    return decoded(system_id, dialect.MAVLink_attitude_message(boot_ms, 0, 0, 0, 0, 0, 0))


def drive(poll_all: bool) -> tuple[list[tuple[Any, ...]], int]:
    """Every tick: each vehicle's telemetry shown to its companion, then what is due sent
    and answered. ``poll_all``: every companion polled at every tick; otherwise the
    schedule. The sent messages, and how many ``poll`` calls it took."""
    schedule = CompanionSchedule()
    polls = [0]
    for system_id in VEHICLES:
        companion = Companion(PROFILE, 0.1, system_id)
        real = companion.poll

        def counted(now: float, real: Any = real) -> list[Any]:
            polls[0] += 1
            return real(now)

        companion.poll = counted  # type: ignore[method-assign]
        schedule.add(system_id, companion)
    sent: list[tuple[Any, ...]] = []
    for tick in range(round(SECONDS / TICK)):
        t = tick * TICK
        for system_id, companion in schedule.companions.items():
            message = telemetry(system_id, t)
            if message is not None:
                companion.on_message(message, t)
                schedule.heard(system_id)
        if poll_all:
            due = [(s, m) for s, c in schedule.companions.items() for m in c.poll(t)]
        else:
            due = schedule.due(t)
        for system_id, message in due:
            sent.append((tick, system_id, message.get_type(), sorted(message.to_dict().items())))
            reply = answer(system_id, message)
            if reply is not None:
                schedule.companions[system_id].on_message(reply, t + TICK / 2)
                schedule.heard(system_id)
    return sent, polls[0]


def test_the_schedule_sends_what_polling_every_companion_sends():
    every, polled_every = drive(poll_all=True)
    scheduled, polled_scheduled = drive(poll_all=False)
    assert scheduled == every
    kinds = {kind for _, _, kind, _ in every}
    assert kinds == {"HEARTBEAT", "COMMAND_LONG", "REQUEST_DATA_STREAM"}
    # Each vehicle's heartbeats once a second, the first at once.
    for system_id in VEHICLES:
        beats = [tick for tick, s, kind, _ in every if s == system_id and kind == "HEARTBEAT"]
        assert beats == [round(n / TICK) for n in range(round(SECONDS))]
    # Polled when something may be due: after telemetry or an answer, and at wake times.
    assert polled_scheduled < polled_every / 4


def test_a_lone_heartbeat_companion_is_polled_once_a_heartbeat():
    schedule = CompanionSchedule()
    companion = Companion(None, None, 9)
    polls: list[float] = []
    real = companion.poll

    def counted(now: float) -> list[Any]:
        polls.append(now)
        return real(now)

    companion.poll = counted  # type: ignore[method-assign]
    schedule.add(9, companion)
    sent = [(tick, m.get_type()) for tick in range(300) for _, m in schedule.due(tick * TICK)]
    assert sent == [(0, "HEARTBEAT"), (100, "HEARTBEAT"), (200, "HEARTBEAT")]
    assert [round(t / TICK) for t in polls] == [0, 100, 200]
