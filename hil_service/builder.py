"""The one place that wires the service: inbox, bus (Zenoh or not), recorder, link, HilService.

``serve``, ``replay`` and ``benchmarks/bench_service.py`` all build the service here, so what
replay and the benchmarks run is what ``serve`` runs. Each caller opens the parts it owns
(``open_recorder``, a ``Link``, ``zenoh_config.open_session``) and hands them to ``wire``;
``Wired.close`` closes everything it was given, in the right order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hil_service.config import LogOptions, ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners.zenoh import Bus, NullBus, ZenohBus
from hil_service.mcap.recorder import McapRecorder
from hil_service.service import HilService
from protocols.mavlink_io import Link

if TYPE_CHECKING:  # the Foxglove SDK is imported only by a run with a live view
    from hil_service.live.view import LiveView


def open_recorder(
    config: ServiceConfig, log: LogOptions, extra: dict[str, str] | None = None
) -> McapRecorder | None:
    """A started recorder storing ``config`` as the log's metadata (None: no log)."""
    if log.directory is None:
        return None
    metadata = {**config.to_metadata(), **(extra or {})}
    return McapRecorder(
        log.directory, metadata=metadata, max_bytes=log.max_bytes, max_seconds=log.max_seconds
    ).start()


@dataclass
class Wired:
    """A wired service and the parts it runs on."""

    service: HilService
    inbox: Inbox
    bus: Bus
    recorder: McapRecorder | None = None
    link: Link | None = None
    session: Any = None  # zenoh.Session
    live: LiveView | None = None

    def close(self) -> dict[str, Any] | None:
        """Close the bus, the live view, the Zenoh session, the link and the recorder (that
        order: the recorder logs until the end); return the recorder's final report, if any."""
        self.bus.close()
        if self.live is not None:
            self.live.close()
        if self.session is not None:
            self.session.close()
        if self.link is not None:
            self.link.close()
        if self.recorder is None:
            return None
        self.recorder.close()
        return self.recorder.report()


def wire(
    config: ServiceConfig,
    *,
    session: Any = None,
    link: Link | None = None,
    recorder: McapRecorder | None = None,
    inbox: Inbox | None = None,
    bus: Bus | None = None,
    send_commands: bool = True,
    live: LiveView | None = None,
) -> Wired:
    """The service for ``config``. Without ``bus``: a ``ZenohBus`` on ``session`` (recording
    to ``recorder``), or a ``NullBus`` without a session. Without ``inbox``: one that refuses
    setpoints outside ``config.limits``. With ``live`` (a started ``LiveView``), every
    publication is also offered to it (``LiveBus``), and so is every input received on
    ``session``."""
    inbox = Inbox(config.limits) if inbox is None else inbox
    if bus is None:
        bus = NullBus() if session is None else ZenohBus(session, inbox, recorder)
    if live is not None:
        from hil_service.live.bus import LiveBus

        bus = LiveBus(bus, live)
        if session is not None:
            live.watch_inputs(session)
    service = HilService(
        config, bus, inbox, link=link, recorder=recorder, send_commands=send_commands
    )
    if live is not None:
        service.live_counters = live.counters
        service.live_mavlink = live.offer_mavlink
    return Wired(service, inbox, bus, recorder, link, session, live)


def publishing_bus(session: Any) -> Bus:
    """The bus of ``replay --publish``: the replayed service's output on Zenoh under the same
    keys. Inputs it receives go to an inbox nobody reads (replay applies the recorded ones)."""
    return ZenohBus(session, Inbox())
