"""MAVLink messages → one ``TelemetrySample`` per plant step and vehicle, as a lockstep
profile describes (``glider``: docs/mavlink.md).

Message fields are read through the profile only (``Profile.reader``, the loop of
``Profile.readings``). A step is complete when every message it needs
(``Profile.step_messages``: for ``glider`` ATTITUDE, SCALED_PRESSURE2 and
ACTUATOR_OUTPUT_STATUS), all stamped with the same time, has arrived; a message without a
timestamp (VFR_HUD) takes no part.
A step with a missing piece is counted when a later step supersedes it, never guessed;
a timestamp at or before the last emitted one is counted as out of order and dropped;
non-finite or physically absurd values are counted as invalid and dropped. A vehicle whose
clock starts again from a lower value and keeps advancing for ``REBOOT_STEPS`` steps has
rebooted (its ``time_boot_ms`` restarts): that is counted in ``restarts`` and assembly
starts afresh rather than dropping it forever. Everything is counted per vehicle
(``counters_for``); only ``unknown_system`` belongs to no vehicle.

Vehicle slots (``max_vehicles``): a system takes one with its first complete step (a sample,
or a complete step refused as invalid), so stray frames of other systems cannot fill them.
Until then it is a *candidate*: its partial steps are held as a vehicle's would be, for at
most ``max_vehicles`` candidates (the least recently heard is dropped for a new one). The
totals (``counters``) count what candidates counted and the partial steps a dropped
candidate held (``incomplete``). Once every slot is taken the candidates are dropped
likewise, and the messages of any other system are counted in ``unknown_system``, as are
those of a system not listed (``serve --sysid``) and those whose system id is no vehicle's
(the broadcast id 0, ``protocols.keys.is_vehicle_id``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from protocols.keys import is_vehicle_id
from protocols.mavlink_io import MavMessage, system_of, type_of
from protocols.profiles import DEFAULT_PROFILE, Profile, clock_of, load_profile
from protocols.readings import MessageReader
from protocols.samples import TelemetrySample, is_plausible, new_sample

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
        # Spelt out: dataclasses.asdict deep-copies field by field, and a fleet's health
        # asks for this hundreds of times a second.
        return {
            "samples": self.samples,
            "incomplete": self.incomplete,
            "out_of_order": self.out_of_order,
            "invalid": self.invalid,
            "restarts": self.restarts,
        }


@dataclass
class AssemblyCounters:
    """All vehicles together (``incomplete`` also the partial steps of dropped candidates),
    and the messages of systems not served (``unknown_system``)."""

    samples: int = 0
    incomplete: int = 0
    out_of_order: int = 0
    invalid: int = 0
    unknown_system: int = 0
    restarts: int = 0

    def as_dict(self) -> dict[str, int]:
        return {
            "samples": self.samples,
            "incomplete": self.incomplete,
            "out_of_order": self.out_of_order,
            "invalid": self.invalid,
            "unknown_system": self.unknown_system,
            "restarts": self.restarts,
        }


@dataclass
class _VehicleState:
    #: Per step time (ms): the step's messages so far, by type.
    pending: dict[int, dict[str, MavMessage]] = field(default_factory=dict)
    last_emitted_ms: int | None = None
    last_late_ms: int | None = None
    late_run: int = 0  # distinct, increasing late timestamps in a row
    counters: VehicleCounters = field(default_factory=VehicleCounters)
    serving: bool = False  # holds a slot (False: a candidate)


class SampleAssembler:
    """Groups telemetry by (system id, timestamp); thread-confined, no I/O."""

    def __init__(
        self,
        profile: Profile | None = None,
        system_ids: Iterable[int] | None = None,
        max_vehicles: int = 32,
    ):
        self.profile = load_profile(DEFAULT_PROFILE) if profile is None else profile
        #: Each stamped message type the profile reads → (ticks per ms, its clock field).
        self._clocks: dict[str, tuple[int, str]] = {}
        for name in self.profile.messages():
            clock = clock_of(name)
            if clock is not None:
                self._clocks[name] = (1 if clock[0] == "ms32" else 1000, clock[1])
        self._step_messages = self.profile.step_messages()
        self._reader: MessageReader = self.profile.reader
        self._full_scale = self.profile.ballast.full_scale
        self.allowed = frozenset(system_ids) if system_ids else None
        # An explicit list (serve --sysid 1-50) is served whole; the cap guards open links.
        self.max_vehicles = max(max_vehicles, len(self.allowed or ()))
        #: Messages of a system not served (not allowed, or beyond ``max_vehicles``).
        self.unknown_system = 0
        #: The timestamp of the last complete step refused as invalid, until taken
        #: (``take_refused``; -1: none): a lockstep service has finished with it too.
        self.refused_ms = -1
        #: The vehicles served: the systems that have completed a step.
        self._vehicles: dict[int, _VehicleState] = {}
        #: Systems heard, not yet served, least recently heard first (none once every
        #: slot is taken).
        self._candidates: dict[int, _VehicleState] = {}
        #: The partial steps that dropped candidates held.
        self._dropped_incomplete = 0

    @property
    def system_ids(self) -> list[int]:
        return sorted(self._vehicles)

    def counters_for(self, system_id: int) -> VehicleCounters:
        """One vehicle's counters (all zero for a vehicle not seen)."""
        vehicle = self._vehicles.get(system_id)
        return VehicleCounters() if vehicle is None else vehicle.counters

    @property
    def counters(self) -> AssemblyCounters:
        """Every vehicle's and candidate's counters summed, with the partial steps of dropped
        candidates and ``unknown_system``: the whole link's."""
        total = AssemblyCounters(
            incomplete=self._dropped_incomplete, unknown_system=self.unknown_system
        )
        for states in (self._vehicles, self._candidates):
            for vehicle in states.values():
                self._add_counts(total, vehicle.counters)
        return total

    @staticmethod
    def _add_counts(total: AssemblyCounters, counted: VehicleCounters) -> None:
        total.samples += counted.samples
        total.incomplete += counted.incomplete
        total.out_of_order += counted.out_of_order
        total.invalid += counted.invalid
        total.restarts += counted.restarts

    def add(self, message: MavMessage) -> TelemetrySample | None:
        """Take one decoded message; return the sample it completes, if any."""
        kind = type_of(message)
        clock = self._clocks.get(kind)
        if clock is None:
            return None
        stamp = int(getattr(message, clock[1])) // clock[0]
        system_id = system_of(message)
        vehicle = self._vehicle(system_id)
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
            pending = vehicle.pending[stamp] = {}
            self._evict(vehicle)
        pending[kind] = message
        if not self._complete(pending):
            return None
        del vehicle.pending[stamp]
        # Older steps still pending can no longer complete in order.
        for older in [s for s in vehicle.pending if s < stamp]:
            if vehicle.last_emitted_ms is None or older > vehicle.last_emitted_ms:
                vehicle.counters.incomplete += 1
            del vehicle.pending[older]
        vehicle.last_emitted_ms = stamp
        if not vehicle.serving:
            self._admit(system_id, vehicle)
        sample = self._build(system_id, stamp, pending)
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
        """The system's state, served or a candidate; None (counted) when not served."""
        vehicle = self._vehicles.get(system_id)
        if vehicle is not None:
            return vehicle
        return self._candidate(system_id)

    def _candidate(self, system_id: int) -> _VehicleState | None:
        """A system without a slot: its candidate state, now the most recently heard."""
        if (
            not is_vehicle_id(system_id)
            or (self.allowed is not None and system_id not in self.allowed)
            or len(self._vehicles) >= self.max_vehicles
        ):
            self.unknown_system += 1
            return None
        candidate = self._candidates.pop(system_id, None)
        if candidate is None:
            candidate = _VehicleState()
            if len(self._candidates) >= self.max_vehicles:
                self._drop(next(iter(self._candidates)))
        self._candidates[system_id] = candidate
        return candidate

    def _admit(self, system_id: int, vehicle: _VehicleState) -> None:
        """A candidate that completed its first step takes a slot (one is free: candidates
        are dropped when the last one is taken)."""
        del self._candidates[system_id]
        vehicle.serving = True
        self._vehicles[system_id] = vehicle
        if len(self._vehicles) >= self.max_vehicles:
            for other in list(self._candidates):
                self._drop(other)

    def _drop(self, system_id: int) -> None:
        dropped = self._candidates.pop(system_id)
        self._dropped_incomplete += dropped.counters.incomplete + len(dropped.pending)

    def _evict(self, vehicle: _VehicleState) -> None:
        while len(vehicle.pending) > MAX_PENDING_STEPS:
            oldest = min(vehicle.pending)
            del vehicle.pending[oldest]
            if vehicle.last_emitted_ms is None or oldest > vehicle.last_emitted_ms:
                vehicle.counters.incomplete += 1

    def _complete(self, pending: dict[str, MavMessage]) -> bool:
        if len(pending) < len(self._step_messages):
            return False
        return all(name in pending for name in self._step_messages)

    def _build(
        self, system_id: int, stamp: int, pending: dict[str, MavMessage]
    ) -> TelemetrySample | None:
        values: dict[str, tuple[int, float]] = {}  # signal → (source rank, value)
        try:
            for message in pending.values():
                for signal, rank, value in self._reader.readings(message):
                    held = values.get(signal)
                    if held is None or rank < held[0]:
                        values[signal] = (rank, value)
            sample = new_sample(
                system_id=system_id,
                time_boot_ms=stamp,
                depth=values["depth"][1],
                pitch=values["pitch"][1],
                u_depth=values["u_depth"][1],
                u_pitch=values["u_pitch"][1],
                pitch_rate=values["pitch_rate"][1] if "pitch_rate" in values else 0.0,
                climb=values["climb"][1] if "climb" in values else 0.0,
            )
        except (TypeError, ValueError, IndexError, AttributeError, KeyError):
            return None
        plausible = is_plausible(sample, self._full_scale)
        return sample if plausible else None
