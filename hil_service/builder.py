"""The one place that wires the service: inbox, bus (Zenoh or not), recorder, link, HilService.

``serve``, ``replay`` and ``benchmarks/bench_service.py`` all build the service here, so what
replay and the benchmarks run is what ``serve`` runs. Each caller opens the parts it owns
(``open_recorder``, a ``Link``, ``zenoh_config.open_session``) and hands them to ``wire``;
``Wired.close`` closes everything it was given, in the right order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hil_service.config import LogOptions, ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Notifier
from hil_service.listeners.zenoh import ZenohPublisher
from hil_service.mcap.recorder import McapRecorder
from hil_service.service import HilService
from hil_service.vehicle_links import LinkSet
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
    notifier: Notifier
    recorder: McapRecorder | None = None
    link: Link | LinkSet | None = None
    session: Any = None  # zenoh.Session
    live: LiveView | None = None

    def close(self) -> dict[str, Any] | None:
        """Stop the listeners, close the live view, the Zenoh session, the link and the
        recorder (that order: the recorder logs until the end); return the recorder's final
        report, if any."""
        self.notifier.stop()
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
    link: Link | LinkSet | None = None,
    recorder: McapRecorder | None = None,
    inbox: Inbox | None = None,
    listeners: Sequence[Any] = (),
    send_commands: bool = True,
    live: LiveView | None = None,
) -> Wired:
    """The service for ``config`` and its listeners, in this order: a ``ZenohPublisher`` on
    ``session`` (its received inputs recorded), ``recorder``, ``listeners``, and ``live`` (a
    started ``LiveView``, which also streams the inputs received on ``session``). Without
    ``inbox``: one that refuses setpoints outside ``config.limits``."""
    inbox = Inbox(config.limits) if inbox is None else inbox
    notifier = Notifier()
    zenoh_publisher = None
    if session is not None:
        zenoh_publisher = ZenohPublisher(session, inbox, notifier.record)
        notifier.add_listener(zenoh_publisher)
    if recorder is not None:
        notifier.add_listener(recorder)
    for listener in listeners:
        notifier.add_listener(listener)
    if live is not None:
        notifier.add_listener(live)
        if session is not None:
            live.watch_inputs(session)
    service = HilService(
        config, notifier, inbox, link=link, recorder=recorder, send_commands=send_commands
    )
    if zenoh_publisher is not None:
        service.wide_counters.append(zenoh_publisher.counters)
    if live is not None:
        service.wide_counters.append(live.counters)
    return Wired(service, inbox, notifier, recorder, link, session, live)


def publisher(session: Any) -> ZenohPublisher:
    """The listener of ``replay --publish``: the replayed service's output on Zenoh under the
    same keys. Inputs it receives go to an inbox nobody reads (replay applies the recorded
    ones)."""
    return ZenohPublisher(session, Inbox(), program="glider-hil replay")
