"""Samples of a vehicle that streams asynchronously: one every period of its clock.

``ProfileAssembler`` samples each vehicle's streams as its profile says; each vehicle's
``Companion`` asks for those streams at the sample rate and sees every message first (its
answers to the stream requests, the rates, reboots and outages; docs/profiles.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hil_service.config import ServiceConfig
from hil_service.sources.base import companion_health
from hil_service.sources.companion import Companion
from hil_service.sources.companion_schedule import CompanionSchedule
from hil_service.sources.periodic_assembler import ProfileAssembler
from protocols.mapping import MSG_ACK
from protocols.mavlink_io import MavMessage, dialect
from protocols.profiles import Profile
from protocols.samples import TelemetrySample


class PeriodicSource:
    periodic = True

    def __init__(self, profile: Profile, config: ServiceConfig, clock: Callable[[], float]) -> None:
        self.profile = profile
        self.assembler = ProfileAssembler(
            profile,
            config.sample_period,
            config.system_ids or None,
            max_vehicles=config.max_vehicles,
        )
        self.schedule = CompanionSchedule()
        self.companions: dict[int, Companion] = self.schedule.companions
        self._clock = clock

    def take(self, message: MavMessage) -> list[tuple[TelemetrySample, bool]]:
        system_id = message.get_srcSystem()
        companion = self.companions.get(system_id)
        if companion is not None:
            companion.on_message(message, self._clock())
            self.schedule.heard(system_id)
        if message.get_type() == MSG_ACK:
            return []
        return self.assembler.add_all_flagged(message)

    def is_command_ack(self, message: MavMessage) -> bool:
        return bool(message.command != dialect.MAV_CMD_SET_MESSAGE_INTERVAL)

    def after_sample(self, sample: TelemetrySample, commanded: bool) -> None:
        pass  # the vehicle streams on its own clock: nothing to release

    def vehicle_seen(self, system_id: int) -> None:
        period = self.assembler.config.period
        self.schedule.add(system_id, Companion(self.profile, period, system_id))

    def due(self, now: float) -> list[tuple[int, MavMessage]]:
        return self.schedule.due(now)

    @property
    def samples(self) -> int:
        return self.assembler.counters.samples

    def link_counters(self) -> dict[str, int]:
        return {"unknown_system": self.assembler.counters.unknown_system}

    def counters_for(self, system_id: int) -> dict[str, int]:
        counted = self.assembler.counters_for(system_id)
        return {
            "samples": counted.samples,
            "incomplete": counted.incomplete,
            "out_of_order": counted.out_of_order,
            "invalid": counted.invalid,
            "restarts": counted.restarts,
        }

    def totals(self) -> dict[str, Any]:
        return self.assembler.counters.as_dict()

    def health(self, system_id: int) -> dict[str, Any]:
        sampled = self.assembler.counters_for(system_id)
        return {
            "sampling": {
                "period": self.assembler.config.period,
                "incomplete_reasons": sampled.reasons,
                "fallbacks": sampled.fallbacks,
                # The clock's segments (counters.restarts) as the sampler tells them apart.
                "reboots": sampled.reboots,
                "outages": sampled.restarts - sampled.reboots,
            },
            **companion_health(self.companions.get(system_id)),
        }

    def summary(self) -> dict[str, Any]:
        return {}
