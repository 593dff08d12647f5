"""The emulated USM glider autopilot: the plant behind a MAVLink 2 link.

It sends HEARTBEAT at 1 Hz (wall clock) as a submarine and, per plant step, ATTITUDE,
SCALED_PRESSURE2, VFR_HUD and ACTUATOR_OUTPUT_STATUS sharing the step's timestamp. It
accepts DO_SET_ACTUATOR commands addressed to it and answers each with COMMAND_ACK; when
commands stop for ``command_timeout`` simulated seconds it falls back to its own program (the
uploaded mission, else its excitation) or to a neutral hold, and says so in a STATUSTEXT.

For a ground station it also streams SYS_STATUS, BATTERY_STATUS, GLOBAL_POSITION_INT,
SCALED_PRESSURE and MISSION_CURRENT (``GCS_RATES_HZ``, simulated time, changed by
SET_MESSAGE_INTERVAL), answers the requests of ``plant_emulator.gcs`` and the mission protocol
(``plant_emulator.mission``), and arms and disarms: armed, the vehicle runs its own program
when no companion commands it; disarmed, it holds neutral ballast instead (a companion's
commands are obeyed either way, as ArduPilot obeys DO_SET_SERVO disarmed). It starts armed.

Steps are scheduled to absolute deadlines (start + k·period/speed), so timing error does
not accumulate over long runs. An emulator more than ``max_lag_steps`` behind its schedule (a
stalled or loaded host) does not catch up in a burst, which would run the plant on commands the
link has not yet had the time to carry: its schedule slips instead, as if the vehicle's time
had paused with the host, and ``slips``/``slipped_s`` count it. ``run`` is the one loop of
both profiles; a subclass changes what a step sends (``step_messages``) and which streams it
has (``_profile_streams_due``). One module over 500 lines: the loop, the command handling and
the ground-station streams are the base the ArduSub profile overrides piece by piece, so they
stay in one class.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import Protocol

from plant_emulator.excitation import Excitation
from plant_emulator.gcs import GENERIC, GroundStationManners, Identity, Parameter
from plant_emulator.mission import Item, ItemRefused, Mission
from plant_emulator.navigation import Navigation, NavigationConfig
from plant_emulator.plant import FamilyPlant, GliderPlant
from protocols.mapping import (
    CommandRejected,
    TelemetryMapping,
    command_target_system,
    is_ballast_command,
)
from protocols.mavlink_io import Link, MavlinkCodec, MavMessage, dialect, message_name
from protocols.samples import TelemetrySample

#: Messages that change the vehicle: never accepted unsigned when a key is set.
COMMAND_MESSAGE_IDS = frozenset(
    {
        dialect.MAVLINK_MSG_ID_COMMAND_LONG,
        dialect.MAVLINK_MSG_ID_COMMAND_INT,
        dialect.MAVLINK_MSG_ID_SETUP_SIGNING,
    }
)

FALLBACKS = ("excitation", "hold")
HEARTBEAT_PERIOD = 1.0  # s, wall clock
#: The ground-station streams of both profiles, per simulated second (0: off).
GCS_RATES_HZ = {
    "SYS_STATUS": 1.0,
    "BATTERY_STATUS": 1.0,
    "GLOBAL_POSITION_INT": 1.0,
    "SCALED_PRESSURE": 1.0,
    "MISSION_CURRENT": 1.0,
    "HOME_POSITION": 0.2,
}
#: The glider's messages of every plant step (their interval is the plant period).
STEP_MESSAGES = ("ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD", "ACTUATOR_OUTPUT_STATUS")
MIN_INTERVAL = 0.02  # s: the fastest a stream may be asked for (50 Hz)


class MessageGate(Protocol):
    """Something that sees every received message first (lockstep: the step releases)."""

    def offer(self, message: MavMessage) -> bool:
        """True when it took the message (the autopilot does not handle it)."""
        ...


def run_steps(duration: float | None, period: float) -> int | None:
    """The plant steps a run of ``duration`` simulated s takes (None: no end); a duration
    a rounding error short of a whole number of periods still counts the last one."""
    return None if duration is None else math.floor(duration / period + 1e-9)


@dataclass(frozen=True)
class AutopilotConfig:
    system_id: int = 1
    speed: float = 1.0  # simulated seconds per wall-clock second
    duration: float | None = None  # simulated seconds; None runs until stopped
    command_timeout: float = 10.0  # simulated seconds without a command → fallback
    fallback: str = "excitation"
    #: MAVLink 2 signing key: sign everything sent, accept only correctly signed frames.
    signing_key: bytes | None = field(default=None, repr=False)
    #: With a key: still accept unsigned frames that are not commands (a GCS heartbeat).
    accept_unsigned_non_commands: bool = False
    navigation: NavigationConfig = field(default_factory=NavigationConfig)
    #: Plant steps the emulator may fall behind its schedule and still catch up; beyond
    #: them the schedule slips.
    max_lag_steps: int = 3

    def __post_init__(self) -> None:
        if not (self.speed > 0 and math.isfinite(self.speed)):
            raise ValueError(f"speed must be positive, got {self.speed}")
        if self.max_lag_steps < 1:
            raise ValueError(f"max_lag_steps must be at least 1, got {self.max_lag_steps}")
        if self.fallback not in FALLBACKS:
            raise ValueError(f"fallback must be one of {FALLBACKS}, got {self.fallback!r}")
        if not 1 <= self.system_id <= 255:
            raise ValueError(f"system id must be 1..255, got {self.system_id}")
        if self.accept_unsigned_non_commands and self.signing_key is None:
            raise ValueError("accepting unsigned non-commands needs a signing key")


@dataclass
class AutopilotStats:
    steps: int = 0
    frames_sent: int = 0
    heartbeats: int = 0
    commands_accepted: int = 0
    commands_rejected: int = 0
    commands_for_other_systems: int = 0
    ignored_messages: int = 0
    fallbacks: int = 0
    arms: int = 0
    disarms: int = 0
    arms_refused: int = 0
    slips: int = 0  # times the schedule slipped rather than catch up in a burst
    slipped_s: float = 0.0  # simulated seconds the slips paused the vehicle for
    last_sample: TelemetrySample | None = field(default=None, repr=False)

    def as_dict(self, codec: MavlinkCodec) -> dict[str, object]:
        summary: dict[str, object] = {
            key: value for key, value in self.__dict__.items() if key != "last_sample"
        }
        summary["slipped_s"] = round(self.slipped_s, 3)
        summary.update({f"rx_{k}": v for k, v in codec.counters.as_dict().items()})
        if codec.verifier is not None:
            summary.update({f"rx_{k}": v for k, v in codec.verifier.counters.as_dict().items()})
        if self.last_sample is not None:
            summary["last_sample"] = self.last_sample.to_payload()
        return summary


class Autopilot:
    """Runs the plant in (scaled) real time behind a MAVLink link."""

    def __init__(
        self,
        plant: GliderPlant | FamilyPlant,
        link: Link,
        excitations: Mapping[str, Excitation],
        config: AutopilotConfig | None = None,
        mapping: TelemetryMapping | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_step: Callable[[TelemetrySample], None] | None = None,
        identity: Identity = GENERIC,
    ):
        self.plant = plant
        self.link = link
        self.excitations = excitations
        self.config = config or AutopilotConfig()
        self.mapping = mapping or TelemetryMapping()
        self.clock = clock
        self.on_step = on_step
        self.codec = MavlinkCodec.for_link(
            self.config.system_id,
            dialect.MAV_COMP_ID_AUTOPILOT1,
            self.config.signing_key,
            accept_unsigned=self.config.accept_unsigned_non_commands,
            always_signed=COMMAND_MESSAGE_IDS,
        )
        self.stats = AutopilotStats()
        #: Set by ``plant_emulator.lockstep.LockstepRunner``: it takes the releases.
        self.lockstep: MessageGate | None = None
        #: HEARTBEAT base_mode bits a runner adds (lockstep: MAV_MODE_FLAG_HIL_ENABLED).
        self.heartbeat_flags = 0
        self.identity = identity
        self.armed = True
        self._armed_at_utc_us = 0
        self.navigation = Navigation(self.config.navigation)
        self._start = 0.0
        self._uptime = 0.0
        self._next_heartbeat: float | None = None
        #: ground-station stream → interval in simulated s, or None when off
        self.gcs_intervals: dict[str, float | None] = {
            name: (1.0 / hz if hz > 0 else None) for name, hz in GCS_RATES_HZ.items()
        }
        self._gcs_due: dict[str, float] = {}
        self._external = {"depth": math.nan, "pitch": math.nan}
        self._last_command_t: float | None = None  # simulated time of the last command
        self._external_active = False
        # Settings a ground station may change (parameters); they start from the config.
        self.command_timeout = self.config.command_timeout
        self.fallback = self.config.fallback
        self.manners = GroundStationManners(self.config.system_id, self.send, identity=identity)
        for parameter in self.parameters():
            self.manners.add_parameter(parameter)
        self.mission = Mission(
            self.send,
            self.setpoint_command,
            self.read_setpoint,
            self.clock,
            self.navigation.home_e7,
            home_item=identity.autopilot == dialect.MAV_AUTOPILOT_ARDUPILOTMEGA,
        )
        self.manners.message_handlers.update(self.mission.handlers())
        handlers = self.manners.handlers
        handlers[dialect.MAV_CMD_COMPONENT_ARM_DISARM] = self._arm_disarm
        handlers[dialect.MAV_CMD_GET_HOME_POSITION] = self._home
        handlers[dialect.MAV_CMD_DO_SET_MISSION_CURRENT] = self._set_mission_current
        handlers[dialect.MAV_CMD_SET_MESSAGE_INTERVAL] = self._set_interval
        handlers[dialect.MAV_CMD_GET_MESSAGE_INTERVAL] = self._get_interval
        on_demand = self.manners.on_demand
        on_demand[dialect.MAVLINK_MSG_ID_HEARTBEAT] = self.send_heartbeat
        on_demand[dialect.MAVLINK_MSG_ID_FLIGHT_INFORMATION] = self._send_flight_information
        for name in GCS_RATES_HZ:
            msg_id = getattr(dialect, f"MAVLINK_MSG_ID_{name}")
            on_demand[msg_id] = partial(self._send_gcs_stream, name)
        for name in self.step_message_names():
            msg_id = getattr(dialect, f"MAVLINK_MSG_ID_{name}")
            on_demand[msg_id] = partial(self._send_latest, name)

    def parameters(self) -> list[Parameter]:
        """The emulator's real settings as MAVLink parameters (a change takes effect)."""

        def set_timeout(value: float) -> None:
            if not value > 0:
                raise ValueError("command timeout must be positive")
            self.command_timeout = value

        def set_fallback(value: float) -> None:
            if int(value) not in (0, 1):
                raise ValueError("fallback is 0 (excitation) or 1 (hold)")
            self.fallback = FALLBACKS[int(value)]

        return [
            Parameter("SYSID_THISMAV", lambda: self.config.system_id, None, integer=True),
            Parameter("CMD_TIMEOUT", lambda: self.command_timeout, set_timeout),
            Parameter(
                "CMD_FALLBACK", lambda: FALLBACKS.index(self.fallback), set_fallback, integer=True
            ),
        ]

    # ---- sending ------------------------------------------------------------------
    def send(self, message: MavMessage) -> None:
        """Frame ``message`` as this vehicle and put it on the link."""
        self.link.send(self.codec.pack(message))
        self.stats.frames_sent += 1

    _send = send

    def _status(self, text: str, severity: int = dialect.MAV_SEVERITY_NOTICE) -> None:
        self._send(self.mapping.status_text(text, severity))

    def heartbeat(self) -> MavMessage:
        armed = dialect.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
        return self.mapping.heartbeat(
            vehicle=True,
            autopilot=self.identity.autopilot,
            base_mode=self.identity.base_mode | armed | self.heartbeat_flags,
        )

    def send_heartbeat(self) -> None:
        self._send(self.heartbeat())
        self.stats.heartbeats += 1

    def heartbeat_if_due(self, now: float) -> bool:
        """Send the 1 Hz (wall clock) HEARTBEAT if it is due; True if it was."""
        if self._next_heartbeat is None:
            self._next_heartbeat = now
        if now < self._next_heartbeat:
            return False
        self.send_heartbeat()
        self._next_heartbeat += HEARTBEAT_PERIOD * max(
            1, math.ceil((now - self._next_heartbeat) / HEARTBEAT_PERIOD)
        )
        return True

    # ---- what a ground station asks for ---------------------------------------------
    def _home(self, message: MavMessage) -> int:
        self._send_home()
        return dialect.MAV_RESULT_ACCEPTED

    def _send_home(self) -> None:
        self._send(self.navigation.home_position())

    def _send_flight_information(self) -> None:
        ms = int(self.sim_time() * 1000) & 0xFFFFFFFF
        at = self._armed_at_utc_us
        uuid = 0x676C6964 << 16 | self.config.system_id
        self._send(dialect.MAVLink_flight_information_message(ms, at, at, uuid))

    def _arm_disarm(self, message: MavMessage) -> int:
        if not math.isfinite(message.param1) or message.param1 not in (0.0, 1.0):
            return dialect.MAV_RESULT_DENIED
        if message.param1 == 0.0:
            if self.armed:
                self.stats.disarms += 1
                self._status("Disarmed: holding neutral ballast")
            self.armed = False
            return dialect.MAV_RESULT_ACCEPTED
        if self.mission.uploading:
            self.stats.arms_refused += 1
            self._status("PreArm: mission upload in progress", dialect.MAV_SEVERITY_CRITICAL)
            return dialect.MAV_RESULT_FAILED
        if not self.armed:
            self.stats.arms += 1
            self._armed_at_utc_us = time.time_ns() // 1000
            self._status("Armed")
        self.armed = True
        return dialect.MAV_RESULT_ACCEPTED

    def _set_mission_current(self, message: MavMessage) -> int:
        seq = message.param1
        if not math.isfinite(seq) or not self.mission.set_current(int(seq)):
            return dialect.MAV_RESULT_DENIED
        return dialect.MAV_RESULT_ACCEPTED

    # ---- the mission's setpoints (the profile's ballast command) ---------------------
    setpoint_command = dialect.MAV_CMD_DO_SET_ACTUATOR

    def read_setpoint(self, item: Item) -> tuple[float, float]:
        """A DO_SET_ACTUATOR item's (depth, pitch) wire values; ItemRefused when bad."""
        values = []
        for index, result in (
            (0, dialect.MAV_MISSION_INVALID_PARAM1),
            (1, dialect.MAV_MISSION_INVALID_PARAM2),
        ):
            wire = item.params[index]
            if not math.isnan(wire) and not (math.isfinite(wire) and abs(wire) <= 1.0):
                raise ItemRefused(result, f"actuator {index + 1} value {wire!r} outside -1..1")
            values.append(wire)
        return values[0], values[1]

    # ---- message rates --------------------------------------------------------------
    def step_message_names(self) -> tuple[str, ...]:
        return STEP_MESSAGES

    def _requested_stream(self, message: MavMessage) -> str | None:
        wanted = message.param1
        return message_name(int(wanted)) if math.isfinite(wanted) and wanted >= 0 else None

    def _set_interval(self, message: MavMessage) -> int:
        name = self._requested_stream(message)
        us = message.param2
        if name is None or not math.isfinite(us):
            return dialect.MAV_RESULT_DENIED
        if name in self.gcs_intervals:
            if us < 0:
                interval = None
            elif us == 0:
                interval = 1.0 / GCS_RATES_HZ[name]
            else:
                interval = max(us / 1e6, MIN_INTERVAL)
            self.gcs_intervals[name] = interval
            if interval is not None:
                due = self._gcs_due.get(name, math.inf)
                self._gcs_due[name] = min(due, self.sim_time() + interval)
            return dialect.MAV_RESULT_ACCEPTED
        if name in self.step_message_names():
            # The lockstep contract: every step's messages go with the step, no more often.
            period = self.plant.config.period
            if us == 0 or us / 1e6 >= period - 1e-9:
                return dialect.MAV_RESULT_ACCEPTED
            self._status(f"{name} goes with each plant step ({period:g}s)")
            return dialect.MAV_RESULT_DENIED
        return dialect.MAV_RESULT_DENIED

    def interval_of(self, name: str) -> float | bool | None:
        """A stream's interval (s; None when off), False for a message that is no stream."""
        if name in self.gcs_intervals:
            return self.gcs_intervals[name]
        if name in self.step_message_names():
            return self.plant.config.period
        if name == "HEARTBEAT":
            return HEARTBEAT_PERIOD
        return False

    def _get_interval(self, message: MavMessage) -> int:
        name = self._requested_stream(message)
        interval = False if name is None else self.interval_of(name)
        if interval is False:
            return dialect.MAV_RESULT_DENIED
        us = -1 if interval is None else round(float(interval) * 1e6)
        self._send(dialect.MAVLink_message_interval_message(int(message.param1), us))
        return dialect.MAV_RESULT_ACCEPTED

    def _gcs_message(self, name: str, sim: float) -> MavMessage:
        ms = int(sim * 1000)
        navigation = self.navigation
        if name == "SYS_STATUS":
            return navigation.sys_status()
        if name == "BATTERY_STATUS":
            return navigation.battery_status()
        if name == "GLOBAL_POSITION_INT":
            return navigation.global_position(ms)
        if name == "SCALED_PRESSURE":
            return navigation.hull_pressure(ms, self.mapping.pressure.surface_hpa)
        if name == "HOME_POSITION":
            return navigation.home_position()
        return self.mission.current_message()

    def _send_gcs_stream(self, name: str) -> None:
        self._send(self._gcs_message(name, self.sim_time()))

    def _send_latest(self, name: str) -> None:
        """REQUEST_MESSAGE for a per-step message: the last step's again."""
        sample = self.stats.last_sample
        if sample is None:
            return
        for message in self.step_messages(sample):
            if message.get_type() == name:
                self._send(message)

    def send_gcs_streams(self, sim: float) -> float:
        """Send every ground-station stream due at simulated time ``sim``; the next due."""
        next_due = math.inf
        for name, interval in self.gcs_intervals.items():
            if interval is None:
                continue
            due = self._gcs_due.setdefault(name, sim)
            if due <= sim:
                self._send(self._gcs_message(name, sim))
                due += interval
                self._gcs_due[name] = due if due > sim else sim + interval
            next_due = min(next_due, self._gcs_due[name])
        return next_due

    def send_periodic(self, now: float) -> None:
        """For a runner with a loop of its own (lockstep): the heartbeat when due, and with
        it one of each ground-station stream (1 Hz wall clock, whatever their rates)."""
        if self.heartbeat_if_due(now):
            for name, interval in self.gcs_intervals.items():
                if interval is not None:
                    self._send_gcs_stream(name)

    # ---- receiving ----------------------------------------------------------------
    def handle_bytes(self, data: bytes) -> None:
        for message in self.codec.parse(data, datagram=self.link.datagram):
            self.handle_message(message)

    def handle_message(self, message: MavMessage) -> None:
        if self.lockstep is not None and self.lockstep.offer(message):
            return
        if not is_ballast_command(message):
            if not self.manners.handle(message):
                self.stats.ignored_messages += 1
            return
        if command_target_system(message) not in (0, self.config.system_id):
            self.stats.commands_for_other_systems += 1
            return
        try:
            command = self.mapping.parse_ballast_command(message)
        except CommandRejected:
            self.stats.commands_rejected += 1
            self._send(self.mapping.command_ack(message, accepted=False))
            return
        for channel, value in (("depth", command.u_depth), ("pitch", command.u_pitch)):
            if not math.isnan(value):
                self._external[channel] = value
        self._last_command_t = self.plant.t
        self.stats.commands_accepted += 1
        self._send(self.mapping.command_ack(message, accepted=True))
        if not self._external_active:
            self._external_active = True
            self._status("ballast: external control")

    # ---- stepping -----------------------------------------------------------------
    def _inputs_for_step(self) -> tuple[float, float]:
        t = self.plant.t
        timed_out = (
            self._last_command_t is not None and t - self._last_command_t > self.command_timeout
        )
        if self._external_active and timed_out:
            self._external_active = False
            self._external = {"depth": math.nan, "pitch": math.nan}
            self.stats.fallbacks += 1
            self._status(
                f"ballast: no command for {self.command_timeout:g}s, {self.fallback}",
                dialect.MAV_SEVERITY_WARNING,
            )
        if self._external_active:
            depth, pitch = self._external["depth"], self._external["pitch"]
            if math.isnan(depth) or math.isnan(pitch):
                held = self.plant.applied_inputs()
                depth = held[0] if math.isnan(depth) else depth
                pitch = held[1] if math.isnan(pitch) else pitch
            return depth, pitch
        if self.fallback == "hold" and self._last_command_t is not None:
            return 0.0, 0.0
        if not self.armed:
            return 0.0, 0.0
        if self.mission.playable:
            depth, pitch = self.mission.setpoints(self.plant.t)
            scale = self.mapping.inputs
            return (
                0.0 if math.isnan(depth) else scale.to_model(depth),
                0.0 if math.isnan(pitch) else scale.to_model(pitch),
            )
        k = self.plant.k
        return self.excitations["depth"].value(k), self.excitations["pitch"].value(k)

    def step_messages(self, sample: TelemetrySample) -> list[MavMessage]:
        """What is sent with every plant step (the glider: its four stamped messages)."""
        return self.mapping.encode_telemetry(sample)

    def step(self) -> TelemetrySample:
        sample = self.plant.step(*self._inputs_for_step())
        # As ``send`` does for each message, with the lookups made once per step.
        messages = self.step_messages(sample)
        pack, send = self.codec.pack, self.link.send
        for message in messages:
            send(pack(message))
        self.stats.frames_sent += len(messages)
        self.navigation.advance(sample, self.plant.config.period)
        self.stats.steps += 1
        self.stats.last_sample = sample
        if self.on_step is not None:
            self.on_step(sample)
        return sample

    # ---- the loop ---------------------------------------------------------------------
    def sim_time(self, now: float | None = None) -> float:
        """Simulated seconds since the vehicle booted."""
        if not self._start:
            return self._uptime + self.plant.t
        now = self.clock() if now is None else now
        wall = self._uptime + (now - self._start) * self.config.speed
        # Never ahead of the plant's next step: an emulator running behind its speed (a
        # loaded machine) stamps what it sends with the plant's time, not the wall's.
        return min(wall, self._uptime + self.plant.t)

    def _profile_streams_due(self, sim: float) -> float:
        """Send the profile's own streams due at ``sim`` (the glider has none: its telemetry
        goes with each step); the next due time."""
        return math.inf

    def send_streams_due(self, sim: float) -> float:
        """Send every stream (the profile's and the ground station's) due at simulated time
        ``sim``; the next due time."""
        return min(self._profile_streams_due(sim), self.send_gcs_streams(sim))

    def run(self, stop: threading.Event | None = None) -> AutopilotStats:
        """Step until ``duration`` simulated seconds have passed or ``stop`` is set."""
        stop = stop or threading.Event()
        speed = self.config.speed
        wall_period = self.plant.config.period / speed
        start = self._start = self.clock()
        self._next_heartbeat = start
        total_steps = run_steps(self.config.duration, self.plant.config.period)
        while not stop.is_set():
            if total_steps is not None and self.stats.steps >= total_steps:
                break
            now = self.clock()
            self.heartbeat_if_due(now)
            deadline = start + self.stats.steps * wall_period
            behind = now - deadline
            if behind > self.config.max_lag_steps * wall_period:
                start = self._start = start + behind
                deadline = now
                self.stats.slips += 1
                self.stats.slipped_s += behind * speed
            if now >= deadline:
                # What fell due before this step reports the state before it: a message is
                # never stamped earlier than the reading it carries.
                self.send_streams_due(self.sim_time(now))
                self.step()
                continue
            next_due = self.send_streams_due(self.sim_time(now))
            due_wall = start + (next_due - self._uptime) / speed
            assert self._next_heartbeat is not None
            self._receive_until(min(deadline, self._next_heartbeat, due_wall), stop)
        self._receive_until(self.clock(), stop)
        return self.stats

    def _receive_until(self, deadline: float, stop: threading.Event) -> None:
        while not stop.is_set():
            remaining = deadline - self.clock()
            if not self.link.wait(min(max(remaining, 0.0), 0.2)):
                if remaining <= 0:
                    return
                continue
            data = self.link.recv()
            if data:
                self.handle_bytes(data)
            elif remaining <= 0:
                return
