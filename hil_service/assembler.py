"""MAVLink messages → one ``TelemetrySample`` per plant step and vehicle.

Message fields are read through ``protocols.mapping`` only (docs/mavlink.md). A step is
complete when its ATTITUDE, SCALED_PRESSURE2 and ACTUATOR_OUTPUT_STATUS, all stamped with
the same time, have arrived (VFR_HUD carries no timestamp and is not needed).
A step with a missing piece is counted when a later step supersedes it, never guessed;
a timestamp at or before the last emitted one is counted as out of order and dropped;
non-finite or physically absurd values are counted as invalid and dropped. A vehicle whose
clock starts again from a lower value and keeps advancing for ``REBOOT_STEPS`` steps has
rebooted (its ``time_boot_ms`` restarts): that is counted in ``restarts`` and assembly
starts afresh rather than dropping it forever. Everything is counted per vehicle
(``counters_for``); only ``unknown_system`` belongs to no vehicle.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

from protocols.mapping import (
    MSG_ATTITUDE,
    MSG_PRESSURE,
    TelemetryMapping,
    pitch_from_attitude,
    pitch_rate_from_attitude,
    step_time_ms,
)
from protocols.mavlink_io import MavMessage
from protocols.samples import TelemetrySample, is_plausible

MAX_PENDING_STEPS = 4
REBOOT_STEPS = 3


@dataclass
class VehicleCounters:
    """What assembly counted for one vehicle (system id)."""

    samples: int = 0
    incomplete: int = 0
    out_of_order: int = 0
    invalid: int = 0
    restarts: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class AssemblyCounters:
    """All vehicles together, and the messages of systems not served (``unknown_system``)."""

    samples: int = 0
    incomplete: int = 0
    out_of_order: int = 0
    invalid: int = 0
    unknown_system: int = 0
    restarts: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass
class _Pending:
    attitude: MavMessage | None = None
    pressure: MavMessage | None = None
    actuators: MavMessage | None = None

    def complete(self) -> bool:
        return None not in (self.attitude, self.pressure, self.actuators)


@dataclass
class _VehicleState:
    pending: dict[int, _Pending] = field(default_factory=dict)
    last_emitted_ms: int | None = None
    last_late_ms: int | None = None
    late_run: int = 0  # distinct, increasing late timestamps in a row
    counters: VehicleCounters = field(default_factory=VehicleCounters)


class SampleAssembler:
    """Groups telemetry by (system id, timestamp); thread-confined, no I/O."""

    def __init__(
        self,
        mapping: TelemetryMapping | None = None,
        system_ids: Iterable[int] | None = None,
        max_vehicles: int = 32,
    ):
        self.mapping = mapping or TelemetryMapping()
        self.allowed = frozenset(system_ids) if system_ids else None
        # An explicit list (serve --sysid 1-50) is served whole; the cap guards open links.
        self.max_vehicles = max(max_vehicles, len(self.allowed or ()))
        #: Messages of a system not served (not allowed, or beyond ``max_vehicles``).
        self.unknown_system = 0
        #: The timestamp of the last complete step refused as invalid, until taken
        #: (``take_refused``; -1: none): a lockstep service has finished with it too.
        self.refused_ms = -1
        self._vehicles: dict[int, _VehicleState] = {}

    @property
    def system_ids(self) -> list[int]:
        return sorted(self._vehicles)

    def counters_for(self, system_id: int) -> VehicleCounters:
        """One vehicle's counters (all zero for a vehicle not seen)."""
        vehicle = self._vehicles.get(system_id)
        return VehicleCounters() if vehicle is None else vehicle.counters

    @property
    def counters(self) -> AssemblyCounters:
        """Every vehicle's counters summed, with ``unknown_system``: the whole link's."""
        total = AssemblyCounters(unknown_system=self.unknown_system)
        for vehicle in self._vehicles.values():
            counted = vehicle.counters
            total.samples += counted.samples
            total.incomplete += counted.incomplete
            total.out_of_order += counted.out_of_order
            total.invalid += counted.invalid
            total.restarts += counted.restarts
        return total

    def add(self, message: MavMessage) -> TelemetrySample | None:
        """Take one decoded message; return the sample it completes, if any."""
        kind = message.get_type()
        stamp = step_time_ms(message, kind)
        if stamp < 0:
            return None
        vehicle = self._vehicle(message.get_srcSystem())
        if vehicle is None:
            return None
        if vehicle.last_emitted_ms is not None and stamp <= vehicle.last_emitted_ms:
            if stamp != vehicle.last_late_ms:  # count a late step once, not per message
                advancing = vehicle.last_late_ms is not None and stamp > vehicle.last_late_ms
                vehicle.late_run = vehicle.late_run + 1 if advancing else 1
                vehicle.last_late_ms = stamp
                if vehicle.late_run >= REBOOT_STEPS:
                    vehicle.counters.restarts += 1
                    vehicle.pending.clear()
                    vehicle.last_emitted_ms = None
                    vehicle.last_late_ms = None
                    vehicle.late_run = 0
                    return self.add(message)
                vehicle.counters.out_of_order += 1
            return None
        vehicle.late_run = 0
        pending = vehicle.pending.get(stamp)
        if pending is None:
            pending = vehicle.pending[stamp] = _Pending()
            self._evict(vehicle)
        if kind == MSG_ATTITUDE:
            pending.attitude = message
        elif kind == MSG_PRESSURE:
            pending.pressure = message
        else:
            pending.actuators = message
        if not pending.complete():
            return None
        del vehicle.pending[stamp]
        # Older steps still pending can no longer complete in order.
        for older in [s for s in vehicle.pending if s < stamp]:
            if vehicle.last_emitted_ms is None or older > vehicle.last_emitted_ms:
                vehicle.counters.incomplete += 1
            del vehicle.pending[older]
        vehicle.last_emitted_ms = stamp
        sample = self._build(message.get_srcSystem(), stamp, pending)
        if sample is None:
            vehicle.counters.invalid += 1
            self.refused_ms = stamp
            return None
        vehicle.counters.samples += 1
        return sample

    def take_refused(self) -> int:
        """The timestamp of the complete step last refused as invalid (-1: none since the
        last call), once."""
        refused = self.refused_ms
        self.refused_ms = -1
        return refused

    def _vehicle(self, system_id: int) -> _VehicleState | None:
        if self.allowed is not None and system_id not in self.allowed:
            self.unknown_system += 1
            return None
        vehicle = self._vehicles.get(system_id)
        if vehicle is None:
            if len(self._vehicles) >= self.max_vehicles:
                self.unknown_system += 1
                return None
            vehicle = self._vehicles[system_id] = _VehicleState()
        return vehicle

    def _evict(self, vehicle: _VehicleState) -> None:
        while len(vehicle.pending) > MAX_PENDING_STEPS:
            oldest = min(vehicle.pending)
            del vehicle.pending[oldest]
            if vehicle.last_emitted_ms is None or oldest > vehicle.last_emitted_ms:
                vehicle.counters.incomplete += 1

    def _build(self, system_id: int, stamp: int, pending: _Pending) -> TelemetrySample | None:
        attitude = pending.attitude
        if attitude is None:
            return None
        try:
            depth = self.mapping.depth_from_pressure(pending.pressure)
            u_depth, u_pitch = self.mapping.inputs_from_actuators(pending.actuators)
            sample = TelemetrySample(
                system_id=system_id,
                time_boot_ms=stamp,
                depth=depth,
                pitch=pitch_from_attitude(attitude),
                u_depth=u_depth,
                u_pitch=u_pitch,
                pitch_rate=pitch_rate_from_attitude(attitude),
            )
        except (TypeError, ValueError, IndexError, AttributeError):
            return None
        plausible = is_plausible(sample, self.mapping.inputs.full_scale)
        return sample if plausible else None
