"""The emulated glider streaming the ArduSub way (``glider-hil emulate --profile ardusub``).

ArduSub sends each message on its own stream at its own rate, stamped with its clock at the
moment it is sent: ATTITUDE and SCALED_PRESSURE2 with ``time_boot_ms``, VFR_HUD with no
stamp, and the outputs as SERVO_OUTPUT_RAW PWM with ``time_usec``, a uint32 of microseconds
that wraps every 71.6 min (``uptime`` starts the clock late so a test sees the wrap). The
plant steps at its own period; each message carries the latest step's state.

Rates: each stream's interval, changed by ``MAV_CMD_SET_MESSAGE_INTERVAL`` (per message),
``REQUEST_DATA_STREAM`` (per ArduPilot stream group) or the ``SR0_*`` parameters (Hz), as
on ArduPilot; every send is jittered by up to ``jitter`` of its interval. Ballast commands
are ``MAV_CMD_DO_SET_SERVO`` (param1 servo, param2 PWM µs) on the profile's servos.
"""

from __future__ import annotations

import math
import random
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.excitation import Excitation
from plant_emulator.gcs import Parameter
from plant_emulator.plant import GliderPlant
from protocols.mapping import WATER_TEMPERATURE_CDEG, TelemetryMapping
from protocols.mavlink_io import Link, MavMessage, dialect, message_name
from protocols.profiles import Profile
from protocols.samples import TelemetrySample
from protocols.units import InputScale

#: ArduPilot's stream groups (REQUEST_DATA_STREAM ids) and their SR0_ parameters.
STREAM_GROUPS: dict[int, tuple[str, tuple[str, ...]]] = {
    dialect.MAV_DATA_STREAM_RAW_SENSORS: ("SR0_RAW_SENS", ("SCALED_PRESSURE2",)),
    dialect.MAV_DATA_STREAM_RC_CHANNELS: ("SR0_RC_CHAN", ("SERVO_OUTPUT_RAW",)),
    dialect.MAV_DATA_STREAM_EXTRA1: ("SR0_EXTRA1", ("ATTITUDE",)),
    dialect.MAV_DATA_STREAM_EXTRA2: ("SR0_EXTRA2", ("VFR_HUD",)),
}
DEFAULT_RATES_HZ = {
    "ATTITUDE": 10.0,
    "SCALED_PRESSURE2": 4.0,
    "VFR_HUD": 4.0,
    "SERVO_OUTPUT_RAW": 4.0,
}
THRUSTER_SERVOS = range(1, 9)  # ArduSub's thrusters: neutral PWM
PWM_LIMITS = (500, 2500)  # µs a DO_SET_SERVO may ask for at all


@dataclass(frozen=True)
class StreamConfig:
    uptime: float = 0.0  # simulated seconds since boot when the emulator starts
    jitter: float = 0.1  # each interval varies by up to this fraction
    rates_hz: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_RATES_HZ))
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.uptime) and self.uptime >= 0):
            raise ValueError(f"uptime must be ≥ 0, got {self.uptime}")
        if not 0 <= self.jitter < 1:
            raise ValueError(f"jitter must be 0..1, got {self.jitter}")


class ArduSubAutopilot(Autopilot):
    """The plant behind a link that streams asynchronously, as ArduSub does."""

    def __init__(
        self,
        plant: GliderPlant,
        link: Link,
        excitations: Mapping[str, Excitation],
        profile: Profile,
        config: AutopilotConfig | None = None,
        streams: StreamConfig | None = None,
        clock: Callable[[], float] | None = None,
        on_step: Callable[[TelemetrySample], None] | None = None,
    ):
        mapping = TelemetryMapping(profile.pressure, InputScale(profile.ballast.full_scale))
        kwargs = {} if clock is None else {"clock": clock}
        self.profile = profile
        self.streams = streams or StreamConfig()
        self._rng = random.Random(self.streams.seed)
        #: message → interval in simulated s, or None when the stream is off
        self.intervals: dict[str, float | None] = {
            name: (1.0 / hz if hz > 0 else None) for name, hz in self.streams.rates_hz.items()
        }
        self._due: dict[str, float] = {}
        self.sent: dict[str, int] = dict.fromkeys(self.intervals, 0)
        self._start = 0.0
        # The vehicle's loop runs at multiples of its period since boot (as an autopilot's
        # scheduler does): the plant steps there, whatever ``uptime`` the clock starts at.
        period = plant.config.period
        self._uptime = math.ceil(self.streams.uptime / period - 1e-9) * period
        super().__init__(plant, link, excitations, config, mapping, on_step=on_step, **kwargs)
        handlers = self.manners.handlers
        handlers[dialect.MAV_CMD_DO_SET_SERVO] = self._set_servo
        handlers[dialect.MAV_CMD_SET_MESSAGE_INTERVAL] = self._set_interval
        handlers[dialect.MAV_CMD_GET_MESSAGE_INTERVAL] = self._get_interval
        for name in self.intervals:
            msg_id = getattr(dialect, f"MAVLINK_MSG_ID_{name}")
            self.manners.on_demand[msg_id] = lambda name=name: self._send_stream(name)

    # ---- settings ------------------------------------------------------------------------
    def parameters(self) -> list[Parameter]:
        params = super().parameters()
        for _group, (param, names) in sorted(STREAM_GROUPS.items()):
            params.append(
                Parameter(
                    param,
                    lambda names=names: self._group_hz(names),
                    lambda hz, names=names: self._set_group_hz(names, hz),
                )
            )
        pwm = self.profile.ballast.pwm
        for channel in ("depth", "pitch"):
            n = self.profile.ballast.output(channel)
            params += [
                Parameter(f"SERVO{n}_MIN", lambda: pwm.minimum, None, integer=True),
                Parameter(f"SERVO{n}_MAX", lambda: pwm.maximum, None, integer=True),
                Parameter(f"SERVO{n}_TRIM", lambda: pwm.neutral, None, integer=True),
            ]
        return params

    def _group_hz(self, names: tuple[str, ...]) -> float:
        interval = self.intervals.get(names[0])
        return 0.0 if interval is None else 1.0 / interval

    def _set_group_hz(self, names: tuple[str, ...], hz: float) -> None:
        if not (math.isfinite(hz) and 0 <= hz <= 50):
            raise ValueError("stream rate must be 0..50 Hz")
        for name in names:
            self._set_stream(name, 1.0 / hz if hz > 0 else None)

    def _set_stream(self, name: str, interval: float | None) -> None:
        if name not in self.intervals:
            return
        self.intervals[name] = interval
        if interval is not None:
            self._due[name] = min(self._due.get(name, math.inf), self.sim_time() + interval)

    # ---- commands ------------------------------------------------------------------------
    def handle_message(self, message: MavMessage) -> None:
        if message.get_type() == "REQUEST_DATA_STREAM":
            if message.target_system in (0, self.config.system_id):
                self._request_data_stream(message)
            return
        if not self.manners.handle(message):
            self.stats.ignored_messages += 1

    def _request_data_stream(self, message: MavMessage) -> None:
        rate = message.req_message_rate if message.start_stop else 0
        groups = (
            list(STREAM_GROUPS)
            if message.req_stream_id == dialect.MAV_DATA_STREAM_ALL
            else [message.req_stream_id]
        )
        for group in groups:
            if group in STREAM_GROUPS:
                self._set_group_hz(STREAM_GROUPS[group][1], min(float(rate), 50.0))

    def _set_servo(self, message: MavMessage) -> int:
        servo, pwm = message.param1, message.param2
        ballast = self.profile.ballast
        if not (math.isfinite(servo) and math.isfinite(pwm)):
            self.stats.commands_rejected += 1
            return dialect.MAV_RESULT_DENIED
        channel = {ballast.depth_output: "depth", ballast.pitch_output: "pitch"}.get(int(servo))
        if channel is None or not PWM_LIMITS[0] <= pwm <= PWM_LIMITS[1]:
            self.stats.commands_rejected += 1
            return dialect.MAV_RESULT_DENIED
        self._external[channel] = ballast.pwm.to_wire(pwm) * ballast.full_scale
        self._last_command_t = self.plant.t
        self.stats.commands_accepted += 1
        if not self._external_active:
            self._external_active = True
            self._status("ballast: external control")
        return dialect.MAV_RESULT_ACCEPTED

    def _set_interval(self, message: MavMessage) -> int:
        name = message_name(int(message.param1)) if math.isfinite(message.param1) else None
        if name not in self.intervals or not math.isfinite(message.param2):
            return dialect.MAV_RESULT_DENIED
        us = message.param2
        if us < 0:
            self._set_stream(name, None)
        elif us == 0:
            self._set_stream(name, 1.0 / DEFAULT_RATES_HZ[name])
        else:
            self._set_stream(name, max(us / 1e6, 0.02))
        return dialect.MAV_RESULT_ACCEPTED

    def _get_interval(self, message: MavMessage) -> int:
        name = message_name(int(message.param1)) if math.isfinite(message.param1) else None
        if name not in self.intervals:
            return dialect.MAV_RESULT_DENIED
        interval = self.intervals[name]
        us = -1 if interval is None else round(interval * 1e6)
        self._send(dialect.MAVLink_message_interval_message(int(message.param1), us))
        return dialect.MAV_RESULT_ACCEPTED

    # ---- streaming -----------------------------------------------------------------------
    def sim_time(self, now: float | None = None) -> float:
        """Simulated seconds since the vehicle booted."""
        if not self._start:
            return self._uptime + self.plant.t
        now = self.clock() if now is None else now
        wall = self._uptime + (now - self._start) * self.config.speed
        # Never ahead of the plant's next step: an emulator running behind its speed (a
        # loaded machine) stamps what it sends with the plant's time, not the wall's.
        return min(wall, self._uptime + self.plant.t)

    def step(self) -> TelemetrySample:
        sample = self.plant.step(*self._inputs_for_step())
        self.stats.steps += 1
        self.stats.last_sample = sample
        if self.on_step is not None:
            self.on_step(sample)
        return sample

    def _message(self, name: str, sim: float) -> MavMessage:
        sample = self.stats.last_sample
        assert sample is not None
        ms = int(sim * 1000) & 0xFFFFFFFF
        if name == "ATTITUDE":
            return dialect.MAVLink_attitude_message(
                ms, 0.0, sample.pitch, 0.0, 0.0, sample.pitch_rate, 0.0
            )
        if name == "SCALED_PRESSURE2":
            hpa = self.profile.pressure.pressure_hpa(sample.depth)
            return dialect.MAVLink_scaled_pressure2_message(ms, hpa, 0.0, WATER_TEMPERATURE_CDEG, 0)
        if name == "VFR_HUD":
            return dialect.MAVLink_vfr_hud_message(0.0, 0.0, 0, 0, -sample.depth, sample.climb)
        ballast = self.profile.ballast
        servos = [1500 if n in THRUSTER_SERVOS else 0 for n in range(1, 17)]
        for channel, u in (("depth", sample.u_depth), ("pitch", sample.u_pitch)):
            servos[ballast.output(channel) - 1] = ballast.pwm.from_wire(u / ballast.full_scale)
        return dialect.MAVLink_servo_output_raw_message(int(sim * 1e6) & 0xFFFFFFFF, 0, *servos)

    def _send_stream(self, name: str, sim: float | None = None) -> None:
        if self.stats.last_sample is None:
            return
        self._send(self._message(name, self.sim_time() if sim is None else sim))
        self.sent[name] += 1

    def _send_due(self, sim: float) -> float:
        """Send every stream that is due at simulated time ``sim``; the next due time."""
        next_due = math.inf
        for name, interval in self.intervals.items():
            if interval is None:
                continue
            due = self._due.setdefault(name, sim + self._rng.uniform(0, interval))
            if due <= sim:
                # Stamped at its own (jittered) send time: behind schedule on a loaded machine
                # the streams still never share a stamp by accident.
                self._send_stream(name, due)
                due += interval * (1 + self._rng.uniform(-self.streams.jitter, self.streams.jitter))
                self._due[name] = due if due > sim else sim + interval
            next_due = min(next_due, self._due[name])
        return next_due

    def run(self, stop: threading.Event | None = None):
        """Step the plant and send each stream when due until ``duration`` or ``stop``."""
        stop = stop or threading.Event()
        speed = self.config.speed
        wall_period = self.plant.config.period / speed
        start = self._start = self.clock()
        next_heartbeat = start
        total_steps = (
            None
            if self.config.duration is None
            else math.floor(self.config.duration / self.plant.config.period + 1e-9)
        )
        while not stop.is_set():
            if total_steps is not None and self.stats.steps >= total_steps:
                break
            now = self.clock()
            if now >= next_heartbeat:
                self._send(self.mapping.heartbeat(vehicle=True))
                self.stats.heartbeats += 1
                next_heartbeat += max(1, math.ceil(now - next_heartbeat))
            deadline = start + self.stats.steps * wall_period
            if now >= deadline:
                # What fell due before this step reports the state before it: a message is
                # never stamped earlier than the reading it carries.
                self._send_due(self.sim_time(now))
                self.step()
                continue
            next_due = self._send_due(self.sim_time(now))
            due_wall = start + (next_due - self._uptime) / speed
            self._receive_until(min(deadline, next_heartbeat, due_wall), stop)
        self._receive_until(self.clock(), stop)
        return self.stats
