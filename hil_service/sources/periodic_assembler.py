"""Telemetry samples from a vehicle that streams asynchronously, as its profile describes.

The periodic counterpart of ``lockstep_assembler.SampleAssembler`` (lockstep): one
``StreamSampler`` per vehicle (system id) fed with the profile's readings and clock stamps,
each complete tick turned into a ``TelemetrySample`` (``time_boot_ms``: the tick's time,
increasing across reboots and clock wraps). Its counters carry the lockstep assembler's
names (``samples``, ``incomplete``, ``out_of_order``, ``invalid``, ``unknown_system``,
``restarts``) so that ``health`` reads either, plus the reasons for incomplete samples.

One message may complete several ticks (after a gap), so ``add_all`` returns a list.

A reboot (the sampler's segment started by the vehicle's clock stepping back) marks the
vehicle's next complete sample ``restarted``: its time does not step back, so the pipeline
learns of the reboot from the mark (``VehiclePipeline.observe``).

Vehicle slots (``max_vehicles``) as in the lockstep assembler: a system takes one with its
first complete tick (a sample, or one refused as implausible), so stray frames of other
systems cannot fill them. Until then it is a *candidate* with a sampler of its own, for at
most ``max_vehicles`` candidates (the least recently heard is dropped for a new one). The
totals (``counters``) count what candidates counted; a dropped candidate's counts stay in
them, with one incomplete sample more (reason ``DROPPED_REASON``) for the readings it held.
Once every slot is taken the candidates are dropped likewise, and the messages of any other
system are counted in ``unknown_system``, as are those of a system not listed (``serve
--sysid``) and those whose system id is no vehicle's (the broadcast id 0,
``protocols.keys.is_vehicle_id``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from hil_service.sources.sampler import SamplerConfig, StreamSampler, Tick
from protocols.keys import is_vehicle_id
from protocols.mavlink_io import MavMessage
from protocols.profiles import Profile, message_clock
from protocols.samples import TelemetrySample, is_plausible

INPUT_SIGNALS = ("u_depth", "u_pitch")
#: The incomplete reason of the readings a candidate held when it was dropped.
DROPPED_REASON = "candidate dropped"


@dataclass
class ProfileAssemblyCounters:
    samples: int = 0
    incomplete: int = 0
    out_of_order: int = 0  # stamps discarded as jumps nobody confirmed
    invalid: int = 0
    unknown_system: int = 0
    restarts: int = 0  # clock segments: reboots and outages
    reboots: int = 0  # of those, the clock stepping back
    reasons: dict[str, int] = field(default_factory=dict)
    fallbacks: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return {
            "samples": self.samples,
            "incomplete": self.incomplete,
            "out_of_order": self.out_of_order,
            "invalid": self.invalid,
            "unknown_system": self.unknown_system,
            "restarts": self.restarts,
            "reboots": self.reboots,
            "incomplete_reasons": dict(self.reasons),
            "fallbacks": dict(self.fallbacks),
        }


class ProfileAssembler:
    """Groups telemetry by system id and samples it periodically; no I/O."""

    def __init__(
        self,
        profile: Profile,
        sample_period: float | None = None,
        system_ids: Iterable[int] | None = None,
        max_vehicles: int = 32,
    ):
        period = sample_period if sample_period is not None else profile.sampling.period
        if period is None:
            raise ValueError(f"profile {profile.name!r} has no sample period: give one")
        self.profile = profile
        self.config = SamplerConfig(
            period=period,
            staleness=profile.staleness(period),
            optional=profile.optional_signals(),
            delay=profile.sampling.delay,
        )
        self.allowed = frozenset(system_ids) if system_ids else None
        # An explicit list (serve --sysid 1-50) is served whole; the cap guards open links.
        self.max_vehicles = max(max_vehicles, len(self.allowed or ()))
        #: The vehicles served: the systems that have completed a tick.
        self._samplers: dict[int, StreamSampler] = {}
        #: Systems heard, not yet served, least recently heard first (none once every
        #: slot is taken).
        self._candidates: dict[int, StreamSampler] = {}
        self._readable = frozenset(profile.messages())
        #: What belongs to no vehicle served: ``unknown_system``, and what dropped
        #: candidates counted.
        self._counters = ProfileAssemblyCounters()
        self._samples: dict[int, int] = {}  # per system id
        self._invalid: dict[int, int] = {}  # per system id
        # per system id: the last tick's reading stamps (None after an incomplete tick)
        self._input_stamps: dict[int, dict[str, float] | None] = {}
        self._rebooted: set[int] = set()  # a reboot not yet marked on a sample

    @property
    def system_ids(self) -> list[int]:
        return sorted(self._samplers)

    @property
    def counters(self) -> ProfileAssemblyCounters:
        """Totals over all vehicles and candidates, with what dropped candidates counted and
        the messages of systems not served."""
        total = ProfileAssemblyCounters()
        _accumulate(total, self._counters)
        for samplers in (self._samplers, self._candidates):
            for system_id, sampler in samplers.items():
                _accumulate(total, self._counted(system_id, sampler))
        return total

    def counters_for(self, system_id: int) -> ProfileAssemblyCounters:
        """One vehicle's counters (all zero for a vehicle not seen)."""
        sampler = self._samplers.get(system_id)
        if sampler is None:
            return ProfileAssemblyCounters()
        return self._counted(system_id, sampler)

    def _counted(self, system_id: int, sampler: StreamSampler) -> ProfileAssemblyCounters:
        c = sampler.counters
        return ProfileAssemblyCounters(
            samples=self._samples.get(system_id, 0),
            incomplete=c.incomplete,
            out_of_order=c.discarded,
            invalid=self._invalid.get(system_id, 0) + c.invalid,
            restarts=c.segments,
            reboots=c.reboots,
            reasons=dict(c.reasons),
            fallbacks=dict(c.fallbacks),
        )

    def add_all(self, message: MavMessage) -> list[TelemetrySample]:
        """Take one decoded message; the samples that became due."""
        return [sample for sample, _ in self.add_all_flagged(message)]

    def add_all_flagged(self, message: MavMessage) -> list[tuple[TelemetrySample, bool]]:
        """Like ``add_all``, each sample with ``inputs_reused``: an input reading (the servo
        readback) is the one the previous sample of that vehicle took (no newer one was
        stamped by this tick), so it may hold the previous step's input. The identifier
        must not pair outputs with it (``VehiclePipeline.observe``)."""
        if message.get_type() not in self._readable:
            return []
        system_id = int(message.get_srcSystem())
        sampler = self._samplers.get(system_id)
        serving = sampler is not None
        if sampler is None:
            sampler = self._candidate(system_id)
            if sampler is None:
                return []
        try:
            readings = self.profile.readings(message)
        except (TypeError, ValueError, IndexError, AttributeError):
            self._invalid[system_id] = self._invalid.get(system_id, 0) + 1
            return []
        samples: list[tuple[TelemetrySample, bool]] = []
        reboots = sampler.counters.reboots
        ticks = sampler.observe(readings, message_clock(message))
        if sampler.counters.reboots != reboots:
            self._rebooted.add(system_id)  # every tick of this call is after the reboot
        if not serving and any(tick.values is not None for tick in ticks):
            self._admit(system_id, sampler)
        for tick in ticks:
            sample = self._build(system_id, tick)
            stamps = tick.stamps if sample is not None else None
            previous = self._input_stamps.get(system_id)
            reused = (
                stamps is not None
                and previous is not None
                and any(stamps.get(name) == previous.get(name) for name in INPUT_SIGNALS)
            )
            self._input_stamps[system_id] = stamps
            if sample is not None:
                samples.append((sample, reused))
        return samples

    def _candidate(self, system_id: int) -> StreamSampler | None:
        """A system without a slot: its candidate sampler, now the most recently heard;
        None (counted) when the system is not served."""
        if (
            not is_vehicle_id(system_id)
            or (self.allowed is not None and system_id not in self.allowed)
            or len(self._samplers) >= self.max_vehicles
        ):
            self._counters.unknown_system += 1
            return None
        candidate = self._candidates.pop(system_id, None)
        if candidate is None:
            candidate = StreamSampler(self.config)
            if len(self._candidates) >= self.max_vehicles:
                self._drop(next(iter(self._candidates)))
        self._candidates[system_id] = candidate
        return candidate

    def _admit(self, system_id: int, sampler: StreamSampler) -> None:
        """A candidate that completed its first tick takes a slot (one is free: candidates
        are dropped when the last one is taken)."""
        del self._candidates[system_id]
        self._samplers[system_id] = sampler
        if len(self._samplers) >= self.max_vehicles:
            for other in list(self._candidates):
                self._drop(other)

    def _drop(self, system_id: int) -> None:
        dropped = self._counted(system_id, self._candidates.pop(system_id))
        dropped.incomplete += 1
        dropped.reasons[DROPPED_REASON] = dropped.reasons.get(DROPPED_REASON, 0) + 1
        _accumulate(self._counters, dropped)
        self._invalid.pop(system_id, None)
        self._input_stamps.pop(system_id, None)
        self._rebooted.discard(system_id)

    def _build(self, system_id: int, tick: Tick) -> TelemetrySample | None:
        values = tick.values
        if values is None:
            return None
        sample = TelemetrySample(
            system_id=system_id,
            time_boot_ms=round(tick.t * 1000),
            depth=values["depth"],
            pitch=values["pitch"],
            u_depth=values["u_depth"],
            u_pitch=values["u_pitch"],
            pitch_rate=values.get("pitch_rate", 0.0),
            climb=values.get("climb", 0.0),
            restarted=system_id in self._rebooted,
        )
        plausible = is_plausible(sample, self.profile.ballast.full_scale)
        if not plausible:
            self._invalid[system_id] = self._invalid.get(system_id, 0) + 1
            return None
        self._samples[system_id] = self._samples.get(system_id, 0) + 1
        self._rebooted.discard(system_id)
        return sample


def _accumulate(total: ProfileAssemblyCounters, one: ProfileAssemblyCounters) -> None:
    """Add ``one``'s counts to ``total``."""
    total.samples += one.samples
    total.incomplete += one.incomplete
    total.out_of_order += one.out_of_order
    total.invalid += one.invalid
    total.unknown_system += one.unknown_system
    total.restarts += one.restarts
    total.reboots += one.reboots
    for key, n in one.reasons.items():
        total.reasons[key] = total.reasons.get(key, 0) + n
    for key, n in one.fallbacks.items():
        total.fallbacks[key] = total.fallbacks.get(key, 0) + n
