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

It says it is ArduPilot (``MAV_AUTOPILOT_ARDUPILOTMEGA``, C-cast parameters) and follows
ArduPilot's rule for DO_SET_SERVO (``AP_ServoRelayEvents::do_set_servo``): a servo whose
``SERVOn_FUNCTION`` is not 0 (disabled), 1 (RCPassThru) or 51..66 (RCIN1..16) has another
use, and the command is refused (``MAV_RESULT_FAILED``) with ArduPilot's STATUSTEXT
"ServoRelayEvent: Channel N is already in use". Thrusters 1..8 are motors (33..40), the
ballast servos 0; every ``SERVOn_FUNCTION`` is a parameter a ground station may change.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial

from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.excitation import Excitation
from plant_emulator.gcs import ARDUPILOT, Parameter
from plant_emulator.mission import Item, ItemRefused
from plant_emulator.plant import FamilyPlant, GliderPlant
from protocols.mapping import WATER_TEMPERATURE_CDEG, TelemetryMapping
from protocols.mavlink_io import Link, MavMessage, dialect
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
SERVOS = range(1, 17)
PWM_LIMITS = (500, 2500)  # µs a DO_SET_SERVO may ask for at all
MOTOR1_FUNCTION = 33  # SRV_Channel::k_motor1; thruster n is motor n
#: SERVOn_FUNCTION values ArduPilot lets DO_SET_SERVO drive: disabled, RCPassThru, RCIN1..16.
FREE_FUNCTIONS = frozenset({0, 1, *range(51, 67)})
#: Simulated s since boot the clock may start at: under the wrap of ``time_boot_ms``, a
#: uint32 of ms (2^32 ms ≈ 49.7 days); later starts would only wrap it, and a start far
#: beyond it leaves no float resolution for the clock to advance.
MAX_UPTIME = (1 << 32) / 1000.0


@dataclass(frozen=True)
class StreamConfig:
    uptime: float = 0.0  # simulated seconds since boot when the emulator starts
    jitter: float = 0.1  # each interval varies by up to this fraction
    rates_hz: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_RATES_HZ))
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.uptime < MAX_UPTIME:
            raise ValueError(
                f"uptime must be 0..{MAX_UPTIME:g} s (time_boot_ms is a uint32 of ms), got "
                f"{self.uptime!r}"
            )
        if not 0 <= self.jitter < 1:
            raise ValueError(f"jitter must be 0..1, got {self.jitter}")


class ArduSubAutopilot(Autopilot):
    """The plant behind a link that streams asynchronously, as ArduSub does."""

    def __init__(
        self,
        plant: GliderPlant | FamilyPlant,
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
        uptime = math.ceil(self.streams.uptime / period - 1e-9) * period
        #: SERVOn_FUNCTION of each servo (parameters): thrusters are motors, the rest free.
        self.functions = {
            n: (MOTOR1_FUNCTION + n - 1 if n in THRUSTER_SERVOS else 0) for n in SERVOS
        }
        #: PWM a DO_SET_SERVO set on a servo that is not ballast (shown in SERVO_OUTPUT_RAW).
        self._servo_pwm: dict[int, int] = {}
        super().__init__(
            plant,
            link,
            excitations,
            config,
            mapping,
            on_step=on_step,
            identity=ARDUPILOT,
            **kwargs,
        )
        self._uptime = uptime
        handlers = self.manners.handlers
        handlers[dialect.MAV_CMD_DO_SET_SERVO] = self._set_servo
        for name in self.intervals:
            msg_id = getattr(dialect, f"MAVLINK_MSG_ID_{name}")
            self.manners.on_demand[msg_id] = partial(self._send_stream, name)

    def reboot(self, boot_s: float) -> float:
        """Reboot as an autopilot does: the clock starts again so that the next step is
        ``boot_s`` (rounded up to a period) after boot, and what a companion set (its
        ballast commands, the stream rates it asked for) is forgotten. The plant goes on.
        Returns how far the clock went back (simulated s)."""
        period = self.plant.config.period
        since_boot = self._uptime + self.plant.t  # the next step's, on the old clock
        boot = math.ceil(boot_s / period - 1e-9) * period
        back = since_boot - boot
        # Every schedule is kept on the vehicle's clock: it goes back with it.
        self._uptime -= back
        for schedule in (self._gcs_due, self._due):
            for name in schedule:
                schedule[name] -= back
        self._external = {"depth": math.nan, "pitch": math.nan}
        self._external_active = False
        self._last_command_t = None
        rates = self.streams.rates_hz
        for name in self.intervals:
            hz = rates.get(name, 0.0)
            self.intervals[name] = 1.0 / hz if hz > 0 else None
        self._status("Rebooted")
        return back

    # ---- settings ------------------------------------------------------------------------
    def parameters(self) -> list[Parameter]:
        params = super().parameters()
        for _group, (param, names) in sorted(STREAM_GROUPS.items()):
            params.append(
                Parameter(
                    param,
                    partial(self._group_hz, names),
                    partial(self._set_group_hz, names),
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
        for n in SERVOS:
            params.append(
                Parameter(
                    f"SERVO{n}_FUNCTION",
                    partial(self._function, n),
                    partial(self._set_function, n),
                    integer=True,
                )
            )
        return params

    def _function(self, servo: int) -> float:
        return self.functions[servo]

    def _set_function(self, servo: int, value: float) -> None:
        if not (0 <= value <= 255):
            raise ValueError("SERVOn_FUNCTION is 0..255")
        self.functions[servo] = int(value)

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
        if not math.isfinite(servo) or int(servo) not in SERVOS:
            self.stats.commands_rejected += 1
            return dialect.MAV_RESULT_FAILED  # no such channel: ArduPilot's do_set_servo fails
        n = int(servo)
        if self.functions[n] not in FREE_FUNCTIONS:
            self.stats.commands_rejected += 1
            self._status(
                f"ServoRelayEvent: Channel {n} is already in use", dialect.MAV_SEVERITY_INFO
            )
            return dialect.MAV_RESULT_FAILED
        if not (math.isfinite(pwm) and PWM_LIMITS[0] <= pwm <= PWM_LIMITS[1]):
            self.stats.commands_rejected += 1
            return dialect.MAV_RESULT_DENIED
        channel = {ballast.depth_output: "depth", ballast.pitch_output: "pitch"}.get(n)
        if channel is None:
            self._servo_pwm[n] = round(pwm)
            return dialect.MAV_RESULT_ACCEPTED
        self._external[channel] = ballast.pwm.to_wire(pwm) * ballast.full_scale
        self._last_command_t = self.plant.t
        self.stats.commands_accepted += 1
        if not self._external_active:
            self._external_active = True
            self._status("ballast: external control")
        return dialect.MAV_RESULT_ACCEPTED

    # ---- the mission's setpoints --------------------------------------------------------
    setpoint_command = dialect.MAV_CMD_DO_SET_SERVO

    def read_setpoint(self, item: Item) -> tuple[float, float]:
        """A DO_SET_SERVO item on a ballast servo: its channel's wire value (−1..1)."""
        ballast = self.profile.ballast
        servo, pwm = item.params[0], item.params[1]
        outputs = {ballast.depth_output: 0, ballast.pitch_output: 1}
        if not math.isfinite(servo) or int(servo) != servo or int(servo) not in outputs:
            raise ItemRefused(dialect.MAV_MISSION_INVALID_PARAM1, f"servo {servo!r} is no ballast")
        if not (math.isfinite(pwm) and PWM_LIMITS[0] <= pwm <= PWM_LIMITS[1]):
            raise ItemRefused(dialect.MAV_MISSION_INVALID_PARAM2, f"PWM {pwm!r}")
        wires = [math.nan, math.nan]
        wires[outputs[int(servo)]] = ballast.pwm.to_wire(pwm)
        return wires[0], wires[1]

    # ---- message rates ------------------------------------------------------------------
    def step_message_names(self) -> tuple[str, ...]:
        return ()

    def interval_of(self, name: str) -> float | bool | None:
        if name in self.intervals:
            return self.intervals[name]
        return super().interval_of(name)

    def _set_interval(self, message: MavMessage) -> int:
        name = self._requested_stream(message)
        if name not in self.intervals or not math.isfinite(message.param2):
            return super()._set_interval(message)
        us = message.param2
        if us < 0:
            self._set_stream(name, None)
        elif us == 0:
            self._set_stream(name, 1.0 / DEFAULT_RATES_HZ[name])
        else:
            self._set_stream(name, max(us / 1e6, 0.02))
        return dialect.MAV_RESULT_ACCEPTED

    # ---- streaming -----------------------------------------------------------------------
    def step_messages(self, sample: TelemetrySample) -> list[MavMessage]:
        return []  # every message goes on its own stream

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
        servos = [1500 if n in THRUSTER_SERVOS else self._servo_pwm.get(n, 0) for n in SERVOS]
        for channel, u in (("depth", sample.u_depth), ("pitch", sample.u_pitch)):
            servos[ballast.output(channel) - 1] = ballast.pwm.from_wire(u / ballast.full_scale)
        return dialect.MAVLink_servo_output_raw_message(int(sim * 1e6) & 0xFFFFFFFF, 0, *servos)

    def _send_stream(self, name: str, sim: float | None = None) -> None:
        if self.stats.last_sample is None:
            return
        self._send(self._message(name, self.sim_time() if sim is None else sim))
        self.sent[name] += 1

    def _profile_streams_due(self, sim: float) -> float:
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
