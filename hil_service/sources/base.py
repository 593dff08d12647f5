"""What every sample source offers the service (``SampleSource``), and the companions' part
that both sources share."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from hil_service.sources.companion import Companion
from protocols.mavlink_io import MavMessage
from protocols.samples import TelemetrySample

#: How a source sends a message to a vehicle (message, system id).
Send = Callable[[MavMessage, int], None]


class SampleSource(Protocol):
    #: Periodic sampling: an input reading may be one a previous sample took already.
    periodic: bool
    #: Each served vehicle's companion (heartbeat; stream requests on periodic profiles).
    companions: dict[int, Companion]

    def take(self, message: MavMessage) -> list[tuple[TelemetrySample, bool]]:
        """The samples ``message`` completes, each with ``inputs_reused``
        (``VehiclePipeline.observe``)."""
        ...

    def is_command_ack(self, message: MavMessage) -> bool:
        """Whether a COMMAND_ACK answers a ballast command (not a stream request)."""
        ...

    def after_sample(self, sample: TelemetrySample, commanded: bool) -> None:
        """The service has finished with ``sample`` (and sent its command, if any)."""
        ...

    def vehicle_seen(self, system_id: int) -> None:
        """A vehicle's first sample: its companion starts."""
        ...

    def due(self, now: float) -> list[tuple[int, MavMessage]]:
        """What the companions have to send now: (system id, message)."""
        ...

    @property
    def samples(self) -> int:
        """Samples assembled, every vehicle together."""
        ...

    def link_counters(self) -> dict[str, int]:
        """What the source counted of the link as a whole, belonging to no vehicle:
        ``unknown_system`` (messages of systems not served) and what else it refuses."""
        ...

    def counters_for(self, system_id: int) -> dict[str, int]:
        """One vehicle's assembly counters: ``samples``, ``incomplete``, ``out_of_order``,
        ``invalid``, ``restarts``."""
        ...

    def totals(self) -> dict[str, Any]:
        """Every vehicle's assembly counters together, with ``unknown_system``."""
        ...

    def health(self, system_id: int) -> dict[str, Any]:
        """The source's own sections of a vehicle's health (``lockstep``, ``sampling``,
        ``companion``)."""
        ...

    def summary(self) -> dict[str, Any]:
        """The source's own sections of the service's summary."""
        ...


def companion_health(companion: Companion | None) -> dict[str, Any]:
    if companion is None:
        return {}
    return {"companion": {**companion.counters.as_dict(), "stream_requests": companion.states}}
