"""A companion computer's manners towards its autopilot: heartbeat and stream requests.

MAVLink asks an onboard computer to send HEARTBEAT at 1 Hz as ``MAV_TYPE_ONBOARD_CONTROLLER``
/ ``MAV_AUTOPILOT_INVALID`` from the vehicle's system id and ``MAV_COMP_ID_ONBOARD_COMPUTER``
(191): routers (mavlink-router, MAVProxy) learn routes from heartbeats. And companion
software asks for what it needs rather than hoping for it: ``MAV_CMD_SET_MESSAGE_INTERVAL``
for each message of the profile at the sample rate, one request at a time (a COMMAND_ACK
does not say which message it is for); ``REQUEST_DATA_STREAM`` for a message whose request
the vehicle refuses or leaves unanswered; everything again after a reboot (the vehicle's
``time_boot_ms`` goes back) or an outage (nothing heard for ``outage`` s); and a stream again
when its measured rate stays below ``rate_fraction`` of the one requested for
``slow_windows`` windows of ``rate_window`` s of the vehicle's clock (so an emulator at any
speed is measured alike; one window by default: each window of delay costs a second of
samples, and asking a vehicle that only dropped a few messages again is harmless): a
ground station such as MAVProxy lowers every stream with its own ``REQUEST_DATA_STREAM``
(MAVProxy: at its ``streamrate``, every 15 s). A stream not heard at all in a window is
left alone (a vehicle without that sensor: the profile's fallback serves); one that stays
slow after being asked again is watched over windows twice as long each time (up to 32),
so a vehicle that cannot go faster is not asked every second.

The companion reads only what is addressed to it: a ``COMMAND_ACK`` counts (and settles a
request) only when its ``target_system``/``target_component`` are the companion's (the
vehicle's system id, component 191) and its ``command`` the one in flight; every other
targeted message (the vehicle's acknowledgements and mission or parameter answers to a
ground station) is counted as ``not_ours`` and left alone (``addressed_to_companion``).

Every profile gets the heartbeat; a lockstep one (``glider``: the vehicle streams as it is,
``profile=None`` here) no stream requests.

Pure: no sockets, no clock of its own. The caller passes ``now`` (monotonic s), sends what
``poll`` returns through a codec with the identity above, and shows every received message
to ``on_message``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from protocols.mavlink_io import MavMessage, dialect, message_id
from protocols.profiles import AUTOPILOT_COMPONENT, Profile, message_clock

COMPANION_COMPONENT = dialect.MAV_COMP_ID_ONBOARD_COMPUTER
#: ArduPilot's REQUEST_DATA_STREAM group of each message (the fallback request).
DATA_STREAM_GROUP = {
    "ATTITUDE": dialect.MAV_DATA_STREAM_EXTRA1,
    "VFR_HUD": dialect.MAV_DATA_STREAM_EXTRA2,
    "SCALED_PRESSURE": dialect.MAV_DATA_STREAM_RAW_SENSORS,
    "SCALED_PRESSURE2": dialect.MAV_DATA_STREAM_RAW_SENSORS,
    "SERVO_OUTPUT_RAW": dialect.MAV_DATA_STREAM_RC_CHANNELS,
    "ACTUATOR_OUTPUT_STATUS": dialect.MAV_DATA_STREAM_EXTRA3,
}
#: The commands the service sends a vehicle whose COMMAND_ACK it counts (the ballast).
BALLAST_COMMANDS = frozenset({dialect.MAV_CMD_DO_SET_ACTUATOR, dialect.MAV_CMD_DO_SET_SERVO})
REFUSALS = frozenset(
    {
        dialect.MAV_RESULT_DENIED,
        dialect.MAV_RESULT_UNSUPPORTED,
        dialect.MAV_RESULT_FAILED,
    }
)


def addressed_to_companion(message: MavMessage) -> bool:
    """Whether a targeted message is for its sender's companion: target system = the
    sender's (a companion speaks from its vehicle's id), target component 191."""
    return (
        getattr(message, "target_system", None) == message.get_srcSystem()
        and getattr(message, "target_component", None) == COMPANION_COMPONENT
    )


def is_targeted(message: MavMessage) -> bool:
    """A message with a (non-broadcast) target system."""
    return bool(getattr(message, "target_system", 0))


def ack_is_ours(message: MavMessage, commands: frozenset[int] = BALLAST_COMMANDS) -> bool:
    """A COMMAND_ACK for the companion, of one of ``commands``."""
    return addressed_to_companion(message) and message.command in commands


@dataclass(frozen=True)
class CompanionConfig:
    heartbeat_period: float = 1.0  # s
    ack_timeout: float = 1.0  # s for a COMMAND_ACK before asking again
    attempts: int = 2  # SET_MESSAGE_INTERVAL sends before falling back
    outage: float = 3.0  # s of silence after which the streams are asked for again
    reboot_step: float = 2.0  # s: time_boot_ms going back this much is a reboot
    rate_window: float = 1.0  # s of the vehicle's clock over which stream rates are measured
    rate_fraction: float = 0.6  # of the requested rate: below it a window is slow
    slow_windows: int = 1  # consecutive slow windows before the stream is asked again


@dataclass
class CompanionCounters:
    heartbeats: int = 0
    interval_requests: int = 0
    data_stream_requests: int = 0
    unanswered: int = 0  # SET_MESSAGE_INTERVAL requests that timed out
    not_ours: int = 0  # targeted messages seen for someone else (a ground station)
    acks: dict[str, int] = field(default_factory=dict)  # result name → count
    rerequests: dict[str, int] = field(default_factory=dict)  # reboot/outage/rate → count
    slow_streams: dict[str, int] = field(default_factory=dict)  # message → times found slow

    def as_dict(self) -> dict[str, object]:
        return {
            "heartbeats": self.heartbeats,
            "interval_requests": self.interval_requests,
            "data_stream_requests": self.data_stream_requests,
            "unanswered": self.unanswered,
            "not_ours": self.not_ours,
            "acks": dict(self.acks),
            "rerequests": dict(self.rerequests),
            "slow_streams": dict(self.slow_streams),
        }


@dataclass
class _Request:
    name: str
    state: str = "pending"  # pending → sent → accepted | refused → data_stream
    sent_at: float = 0.0
    attempts: int = 0
    # Rate watch, on the vehicle's clock, once the request is accepted (or sent as a
    # REQUEST_DATA_STREAM): where the current window started, and arrivals since.
    watch_from: float | None = None
    count: int = 0
    backoff: float = 1.0  # window length in rate_windows
    slow: int = 0  # consecutive slow windows


SETTLED = ("accepted", "data_stream")


class Companion:
    """Heartbeat and stream requests for one vehicle (heartbeat only without a profile)."""

    def __init__(
        self,
        profile: Profile | None,
        sample_period: float | None,
        target_system: int,
        config: CompanionConfig | None = None,
    ):
        if profile is not None and not (
            sample_period is not None and math.isfinite(sample_period) and sample_period > 0
        ):
            raise ValueError(f"sample period must be positive, got {sample_period}")
        self.profile = profile
        self.target_system = target_system
        self.config = config or CompanionConfig()
        self.intervals: dict[str, float] = (
            {} if profile is None or sample_period is None else profile.intervals(sample_period)
        )
        self.counters = CompanionCounters()
        self.requests = [_Request(name) for name in self.intervals]
        self._by_name = {r.name: r for r in self.requests}
        self._next_heartbeat: float | None = None
        self._last_heard: float | None = None
        self._last_boot_s: float | None = None
        self._refused_command = False  # SET_MESSAGE_INTERVAL unsupported altogether

    @property
    def states(self) -> dict[str, str]:
        return {r.name: r.state for r in self.requests}

    # ---- sending ------------------------------------------------------------------------
    def heartbeat(self) -> MavMessage:
        return dialect.MAVLink_heartbeat_message(
            dialect.MAV_TYPE_ONBOARD_CONTROLLER,
            dialect.MAV_AUTOPILOT_INVALID,
            0,
            0,
            dialect.MAV_STATE_ACTIVE,
            3,
        )

    def poll(self, now: float) -> list[MavMessage]:
        """What to send now: a heartbeat when due, and the next stream request."""
        out = []
        if self._next_heartbeat is None or now >= self._next_heartbeat:
            out.append(self.heartbeat())
            self.counters.heartbeats += 1
            period = self.config.heartbeat_period
            base = now if self._next_heartbeat is None else self._next_heartbeat
            self._next_heartbeat = base + period * max(1, math.ceil((now - base) / period))
        if self._last_heard is None:
            return out  # nobody to ask yet
        refused = next((r for r in self.requests if r.state == "refused"), None)
        if refused is not None:
            out.append(self._data_stream(refused))
            return out
        in_flight = next((r for r in self.requests if r.state == "sent"), None)
        if in_flight is not None:
            if now - in_flight.sent_at < self.config.ack_timeout:
                return out
            self.counters.unanswered += 1
            if in_flight.attempts >= self.config.attempts:
                out.append(self._data_stream(in_flight))
                return out
            out.append(self._interval(in_flight, now))
            return out
        pending = next((r for r in self.requests if r.state == "pending"), None)
        if pending is not None:
            if self._refused_command:
                out.append(self._data_stream(pending))
            else:
                out.append(self._interval(pending, now))
        return out

    def next_poll(self, now: float) -> float:
        """The earliest time ``poll`` may send something, as the companion stands at ``now``
        (``now`` itself: at once). Before that, ``poll`` sends nothing and changes nothing,
        unless ``on_message`` changes the companion first."""
        heartbeat = self._next_heartbeat
        if heartbeat is None:
            return now
        if self._last_heard is None:
            return heartbeat
        if any(r.state == "refused" for r in self.requests):
            return now
        in_flight = next((r for r in self.requests if r.state == "sent"), None)
        if in_flight is not None:
            return min(heartbeat, in_flight.sent_at + self.config.ack_timeout)
        if any(r.state == "pending" for r in self.requests):
            return now
        return heartbeat

    def _interval(self, request: _Request, now: float) -> MavMessage:
        request.state = "sent"
        request.sent_at = now
        request.attempts += 1
        self.counters.interval_requests += 1
        interval_us = round(self.intervals[request.name] * 1e6)
        return dialect.MAVLink_command_long_message(
            self.target_system,
            AUTOPILOT_COMPONENT,
            dialect.MAV_CMD_SET_MESSAGE_INTERVAL,
            0,
            float(message_id(request.name)),
            float(interval_us),
            0,
            0,
            0,
            0,
            0,
        )

    def _data_stream(self, request: _Request) -> MavMessage:
        self._settle(request, "data_stream")
        self.counters.data_stream_requests += 1
        group = DATA_STREAM_GROUP.get(request.name, dialect.MAV_DATA_STREAM_ALL)
        hz = max(1, round(1.0 / self.intervals[request.name]))
        return dialect.MAVLink_request_data_stream_message(
            self.target_system, AUTOPILOT_COMPONENT, group, hz, 1
        )

    # ---- receiving ----------------------------------------------------------------------
    def on_message(self, message: MavMessage, now: float) -> None:
        if message.get_srcSystem() != self.target_system:
            return
        if message.get_srcComponent() == COMPANION_COMPONENT:
            return  # our own kind, not the autopilot
        if self._last_heard is not None and now - self._last_heard > self.config.outage:
            self._ask_again("outage")
        self._last_heard = now
        kind = message.get_type()
        request = self._by_name.get(kind)
        if request is not None and request.watch_from is not None:
            request.count += 1
        clock = message_clock(message)
        if clock is not None and clock[0] == "ms32":
            boot_s = clock[1] / 1000
            back = (
                self._last_boot_s is not None
                and boot_s < self._last_boot_s - self.config.reboot_step
            )
            if back:
                self._ask_again("reboot")
            self._last_boot_s = boot_s
            self._watch_rates(boot_s)
        if is_targeted(message) and not addressed_to_companion(message):
            self.counters.not_ours += 1
            return
        if kind == "COMMAND_ACK":
            self._ack(message)

    def _watch_rates(self, t: float) -> None:
        """Ask again for a settled stream arriving below ``rate_fraction`` of its rate."""
        config = self.config
        for request in self.requests:
            if request.state not in SETTLED:
                continue
            start = request.watch_from
            if start is None or t < start:  # newly settled, or the clock went back
                request.watch_from, request.count = t, 0
                continue
            span = t - start
            if span < config.rate_window * request.backoff:
                continue
            expected = span / self.intervals[request.name]
            slow = 0 < request.count < config.rate_fraction * expected
            request.slow = request.slow + 1 if slow else 0
            if request.slow >= config.slow_windows:
                self.counters.slow_streams[request.name] = (
                    self.counters.slow_streams.get(request.name, 0) + 1
                )
                self.counters.rerequests["rate"] = self.counters.rerequests.get("rate", 0) + 1
                request.backoff = min(request.backoff * 2, 32.0)
                self._reset(request)
                continue
            if request.count > 0 and not slow:
                request.backoff = 1.0
            request.watch_from, request.count = t, 0

    def _settle(self, request: _Request, state: str) -> None:
        request.state = state
        request.watch_from, request.count = None, 0

    def _reset(self, request: _Request) -> None:
        request.state = "pending"
        request.attempts = 0
        request.watch_from, request.count, request.slow = None, 0, 0

    def _ack(self, message: MavMessage) -> None:
        if message.command != dialect.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        result = dialect.enums["MAV_RESULT"].get(message.result)
        name = result.name if result is not None else str(message.result)
        self.counters.acks[name] = self.counters.acks.get(name, 0) + 1
        in_flight = next((r for r in self.requests if r.state == "sent"), None)
        if in_flight is None:
            return
        if message.result == dialect.MAV_RESULT_ACCEPTED:
            self._settle(in_flight, "accepted")
        elif message.result in REFUSALS:
            if message.result == dialect.MAV_RESULT_UNSUPPORTED:
                self._refused_command = True  # the others go by REQUEST_DATA_STREAM too
            in_flight.state = "refused"

    def _ask_again(self, why: str) -> None:
        self.counters.rerequests[why] = self.counters.rerequests.get(why, 0) + 1
        self._refused_command = False
        for request in self.requests:
            request.backoff = 1.0
            self._reset(request)
