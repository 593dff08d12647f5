"""Samples of a vehicle in lockstep: one per plant step, each step released once decided.

``SampleAssembler`` turns the messages stamped with one step's time into its sample; a
``LockstepResponder`` per vehicle in lockstep releases the step when the service has
finished with it (decided, or refused as implausible), docs/lockstep.md. A vehicle is in
lockstep once its own heartbeat announced it, or from the start with ``serve --lockstep``;
an announcement from a system the service does not serve is ignored and counted
(``lockstep_announcements_ignored``). The companion only sends heartbeats: the vehicle
streams as it is.
"""

from __future__ import annotations

from typing import Any

from hil_service.config import ServiceConfig
from hil_service.sources.base import Send, companion_health
from hil_service.sources.companion import Companion
from hil_service.sources.companion_schedule import CompanionSchedule
from hil_service.sources.lockstep_assembler import SampleAssembler
from hil_service.sources.lockstep_responder import LockstepResponder, combined
from protocols.keys import is_vehicle_id
from protocols.lockstep import announces_lockstep
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
        #: ``serve --lockstep``: every served vehicle is in lockstep from the start.
        self.forced = config.lockstep
        #: Each vehicle in lockstep, by system id: its releases. A vehicle without one gets
        #: no release. Besides served vehicles it may hold systems that announced while a
        #: slot was free and have no sample yet (at most ``max_vehicles`` in all).
        self.responders: dict[int, LockstepResponder] = {}
        #: Lockstep announcements from systems the service does not serve: ignored.
        self.announcements_ignored = 0
        self.schedule = CompanionSchedule()
        self.companions: dict[int, Companion] = self.schedule.companions
        self._send = send

    def take(self, message: MavMessage) -> list[tuple[TelemetrySample, bool]]:
        kind = type_of(message)
        if kind == MSG_ACK:
            return []
        if kind == "HEARTBEAT" and announces_lockstep(message):
            self._announced(system_of(message))
        sample = self.assembler.add(message)
        if sample is not None:
            return [(sample, False)]
        if self.assembler.refused_ms >= 0:
            refused = self.assembler.take_refused()
            send = self._send
            if send is not None:
                system_id = system_of(message)
                responder = self._responder(system_id)
                if responder is not None:
                    # Refusing a sample is finishing with it: release its step
                    # (docs/lockstep.md).
                    responder.after_refused(refused, lambda released: send(released, system_id))
        return []

    def _announced(self, system_id: int) -> None:
        """``system_id``'s heartbeat announced lockstep: its steps are released from now on
        if the service serves it; otherwise the announcement is counted and ignored."""
        responder = self.responders.get(system_id)
        if responder is None:
            if not self._serves(system_id):
                self.announcements_ignored += 1
                return
            responder = self._add_responder(system_id)
        responder.announce()

    def _serves(self, system_id: int) -> bool:
        """Whether the assembler serves ``system_id``, or will once its telemetry arrives (a
        heartbeat comes first): a vehicle id, in the ``--sysid`` list if there is one, with
        a slot or a free one (``--max-vehicles``)."""
        assembler = self.assembler
        if not is_vehicle_id(system_id):
            return False
        if assembler.allowed is not None and system_id not in assembler.allowed:
            return False
        served = assembler.system_ids
        return system_id in served or len(served) < assembler.max_vehicles

    def _responder(self, system_id: int) -> LockstepResponder | None:
        """The lockstep of served vehicle ``system_id`` (None: not in lockstep)."""
        responder = self.responders.get(system_id)
        if responder is None and self.forced:
            responder = self._add_responder(system_id)
        return responder

    def _add_responder(self, system_id: int) -> LockstepResponder:
        if len(self.responders) >= self.assembler.max_vehicles:
            # Systems that announced while a slot was free but took none (their telemetry
            # never came, or others took the slots first) make room; one that takes a slot
            # later announces again with its next heartbeat.
            self.responders = self._counted()
        responder = self.responders[system_id] = LockstepResponder(self.forced)
        return responder

    def _counted(self) -> dict[int, LockstepResponder]:
        """The responders of vehicles: systems the assembler serves, or that it served when
        one of their steps was released."""
        served = set(self.assembler.system_ids)
        return {
            system_id: responder
            for system_id, responder in self.responders.items()
            if system_id in served or responder.has_released
        }

    def is_command_ack(self, message: MavMessage) -> bool:
        return True

    def after_sample(self, sample: TelemetrySample, commanded: bool) -> None:
        send = self._send
        if send is not None:
            system_id = sample.system_id
            responder = self._responder(system_id)
            if responder is not None:
                responder.after_sample(sample, commanded, lambda m: send(m, system_id))

    def vehicle_seen(self, system_id: int) -> None:
        self.schedule.add(system_id, Companion(None, None, system_id))

    def due(self, now: float) -> list[tuple[int, MavMessage]]:
        return self.schedule.due(now)

    @property
    def samples(self) -> int:
        return self.assembler.counters.samples

    def link_counters(self) -> dict[str, int]:
        return {
            "unknown_system": self.assembler.unknown_system,
            "lockstep_announcements_ignored": self.announcements_ignored,
        }

    def counters_for(self, system_id: int) -> dict[str, int]:
        return self.assembler.counters_for(system_id).as_dict()

    def totals(self) -> dict[str, Any]:
        return {
            **self.assembler.counters.as_dict(),
            "lockstep_announcements_ignored": self.announcements_ignored,
        }

    def health(self, system_id: int) -> dict[str, Any]:
        sections: dict[str, Any] = {}
        responder = self._responder(system_id)
        if responder is not None and responder.active:
            sections["lockstep"] = responder.as_dict()
        sections.update(companion_health(self.companions.get(system_id)))
        return sections

    def summary(self) -> dict[str, Any]:
        return {"lockstep": combined(self._counted().values(), self.forced)}
