"""The emulated USM glider autopilot: the plant behind a MAVLink 2 link.

It sends HEARTBEAT at 1 Hz (wall clock) as a submarine and, per plant step, ATTITUDE,
SCALED_PRESSURE2, VFR_HUD and ACTUATOR_OUTPUT_STATUS sharing the step's timestamp. It
accepts DO_SET_ACTUATOR commands addressed to it and answers each with COMMAND_ACK; when
commands stop for ``command_timeout`` simulated seconds it falls back to its own excitation
or to a neutral hold, and says so in a STATUSTEXT.

Steps are scheduled to absolute deadlines (start + k·period/speed), so timing error does
not accumulate over long runs.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from plant_emulator.excitation import Excitation
from plant_emulator.gcs import GroundStationManners, Parameter
from plant_emulator.plant import GliderPlant
from protocols.mapping import (
    CommandRejected,
    TelemetryMapping,
    command_target_system,
    is_ballast_command,
)
from protocols.mavlink_io import Link, MavlinkCodec, MavMessage, dialect
from protocols.samples import TelemetrySample

if TYPE_CHECKING:
    from plant_emulator.lockstep import LockstepRunner

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

    def __post_init__(self) -> None:
        if not (self.speed > 0 and math.isfinite(self.speed)):
            raise ValueError(f"speed must be positive, got {self.speed}")
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
    last_sample: TelemetrySample | None = field(default=None, repr=False)

    def as_dict(self, codec: MavlinkCodec) -> dict[str, object]:
        summary: dict[str, object] = {
            key: value for key, value in self.__dict__.items() if key != "last_sample"
        }
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
        plant: GliderPlant,
        link: Link,
        excitations: Mapping[str, Excitation],
        config: AutopilotConfig | None = None,
        mapping: TelemetryMapping | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_step: Callable[[TelemetrySample], None] | None = None,
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
        self.lockstep: LockstepRunner | None = None
        self._external = {"depth": math.nan, "pitch": math.nan}
        self._last_command_t: float | None = None  # simulated time of the last command
        self._external_active = False
        # Settings a ground station may change (parameters); they start from the config.
        self.command_timeout = self.config.command_timeout
        self.fallback = self.config.fallback
        self.manners = GroundStationManners(self.config.system_id, self._send)
        for parameter in self.parameters():
            self.manners.add_parameter(parameter)

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
    def _send(self, message: MavMessage) -> None:
        self.link.send(self.codec.pack(message))
        self.stats.frames_sent += 1

    def _status(self, text: str, severity: int = dialect.MAV_SEVERITY_NOTICE) -> None:
        self._send(self.mapping.status_text(text, severity))

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
            self._last_command_t is not None
            and t - self._last_command_t > self.command_timeout
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
            held = self.plant.applied_inputs()
            return (
                held[0] if math.isnan(self._external["depth"]) else self._external["depth"],
                held[1] if math.isnan(self._external["pitch"]) else self._external["pitch"],
            )
        if self.fallback == "hold" and self._last_command_t is not None:
            return 0.0, 0.0
        k = self.plant.k
        return self.excitations["depth"].value(k), self.excitations["pitch"].value(k)

    def step(self) -> TelemetrySample:
        sample = self.plant.step(*self._inputs_for_step())
        for message in self.mapping.encode_telemetry(sample):
            self._send(message)
        self.stats.steps += 1
        self.stats.last_sample = sample
        if self.on_step is not None:
            self.on_step(sample)
        return sample

    def run(self, stop: threading.Event | None = None) -> AutopilotStats:
        """Step until ``duration`` simulated seconds have passed or ``stop`` is set."""
        stop = stop or threading.Event()
        wall_period = self.plant.config.period / self.config.speed
        start = self.clock()
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
                next_heartbeat += HEARTBEAT_PERIOD * max(
                    1, math.ceil((now - next_heartbeat) / HEARTBEAT_PERIOD)
                )
            deadline = start + self.stats.steps * wall_period
            if now >= deadline:
                self.step()
                continue
            self._receive_until(min(deadline, next_heartbeat), stop)
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
