"""Samples of a vehicle in lockstep: one per plant step, each step released once decided.

``SampleAssembler`` turns the messages stamped with one step's time into its sample;
``LockstepResponder`` releases the step when the service has finished with it (decided, or
refused as implausible), when lockstep is on (docs/lockstep.md). The companion only sends
heartbeats: the vehicle streams as it is.
"""

from __future__ import annotations

from typing import Any

from hil_service.config import ServiceConfig
from hil_service.sources.base import Send, companion_health
from hil_service.sources.companion import Companion
from hil_service.sources.companion_schedule import CompanionSchedule
from hil_service.sources.lockstep_assembler import SampleAssembler
from hil_service.sources.lockstep_responder import LockstepResponder
from protocols.mapping import MSG_ACK
from protocols.mavlink_io import MavMessage, system_of, type_of
from protocols.profiles import Profile
from protocols.samples import TelemetrySample


class LockstepSource:
    periodic = False

    def __init__(self, profile: Profile, config: ServiceConfig, send: Send | None) -> None:
        self.assembler = SampleAssembler(
            profile, config.system_ids or None, max_vehicles=config.max_vehicles
        )
        self.lockstep = LockstepResponder(config.lockstep)
        self.schedule = CompanionSchedule()
        self.companions: dict[int, Companion] = self.schedule.companions
        self._send = send

    def take(self, message: MavMessage) -> list[tuple[TelemetrySample, bool]]:
        if type_of(message) == MSG_ACK:
            return []
        self.lockstep.observe(message)
        sample = self.assembler.add(message)
        if sample is not None:
            return [(sample, False)]
        if self.assembler.refused_ms >= 0:
            refused = self.assembler.take_refused()
            send = self._send
            if send is not None:
                # Refusing a sample is finishing with it: release its step (docs/lockstep.md).
                system_id = system_of(message)
                self.lockstep.after_refused(refused, lambda released: send(released, system_id))
        return []

    def is_command_ack(self, message: MavMessage) -> bool:
        return True

    def after_sample(self, sample: TelemetrySample, commanded: bool) -> None:
        send = self._send
        if send is not None:
            system_id = sample.system_id
            self.lockstep.after_sample(sample, commanded, lambda m: send(m, system_id))

    def vehicle_seen(self, system_id: int) -> None:
        self.schedule.add(system_id, Companion(None, None, system_id))

    def due(self, now: float) -> list[tuple[int, MavMessage]]:
        return self.schedule.due(now)

    @property
    def samples(self) -> int:
        return self.assembler.counters.samples

    @property
    def unknown_system(self) -> int:
        return self.assembler.unknown_system

    def counters_for(self, system_id: int) -> dict[str, int]:
        return self.assembler.counters_for(system_id).as_dict()

    def totals(self) -> dict[str, Any]:
        return dict(self.assembler.counters.as_dict())

    def health(self, system_id: int) -> dict[str, Any]:
        sections: dict[str, Any] = {}
        if self.lockstep.active:
            sections["lockstep"] = self.lockstep.as_dict()
        sections.update(companion_health(self.companions.get(system_id)))
        return sections

    def summary(self) -> dict[str, Any]:
        return {"lockstep": self.lockstep.as_dict()}
