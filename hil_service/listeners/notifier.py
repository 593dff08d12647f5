"""The fan-out of the service's stream to its listeners (``hil_service.listeners``),
compiled: the service tells it about every frame and publication of the per-sample path.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Final

from hil_service.listeners.base import EVENTS, Listener, handler_of
from protocols import payload_json
from protocols.mavlink_io import MavMessage

#: What a held event is (``Notifier.hold``).
_MAVLINK: Final = 0
_PUBLISH: Final = 1
_RECORD: Final = 2
_VEHICLE: Final = 3


class Notifier:
    """Hands each event to every listener, in the order they were added."""

    def __init__(self, listeners: Iterable[Any] = ()) -> None:
        self.listeners: list[Any] = []
        self._mavlink: list[Callable[..., None]] = []
        self._publish: list[Callable[..., None]] = []
        self._record: list[Callable[..., None]] = []
        self._vehicle: list[Callable[..., None]] = []
        #: Events queued while ``hold`` is in force, in their order (``release``).
        self._held: list[tuple[int, Any, Any, Any, Any]] | None = None
        for listener in listeners:
            self.add_listener(listener)

    def add_listener(self, listener: Any) -> None:
        if all(handler_of(listener, event) is None for event in EVENTS) and not isinstance(
            listener, Listener
        ):
            raise TypeError(f"{listener!r} listens to nothing: it defines none of {EVENTS}")
        self.listeners.append(listener)
        self._rebuild()

    def remove_listener(self, listener: Any) -> None:
        self.listeners.remove(listener)
        self._rebuild()

    def _rebuild(self) -> None:
        lists: tuple[list[Callable[..., None]], ...] = ([], [], [], [])
        for listener in self.listeners:
            for event, handlers in zip(EVENTS, lists, strict=True):
                handler = handler_of(listener, event)
                if handler is not None:
                    handlers.append(handler)
        self._mavlink, self._publish, self._record, self._vehicle = lists

    # ---- holding events back ---------------------------------------------------------
    def hold(self) -> None:
        """Queue every event until ``release``.

        A service whose link spins (docs/lockstep.md, "Two cores") holds its listeners back
        while it handles a datagram, so that what it sends the vehicle (a command, a
        lockstep release) goes before the log and Zenoh get the datagram's events: the
        vehicle, on a core of its own, then computes its next step while the service logs
        and publishes this one. Listeners see the same events in the same order; a frame
        keeps the time it was received or sent, and what a listener stamps itself (the
        log's publications) is stamped on release."""
        if self._held is None:
            self._held = []

    def release(self) -> None:
        """Hand the events queued since ``hold`` to the listeners, in order; stop holding."""
        held = self._held
        self._held = None
        if held is None:
            return
        for kind, first, second, third, fourth in held:
            if kind == _MAVLINK:
                for handler in self._mavlink:
                    handler(first, second, third, fourth)
            elif kind == _PUBLISH:
                data = payload_json.encode(second)
                for handler in self._publish:
                    handler(first, second, data, fourth)
            elif kind == _RECORD:
                for handler in self._record:
                    handler(first, second, fourth)
            else:
                for handler in self._vehicle:
                    handler(first, second)

    # ---- the events -----------------------------------------------------------------
    def mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        held = self._held
        if held is not None:
            held.append((_MAVLINK, direction, message, frame, t_ns))
            return
        for handler in self._mavlink:
            handler(direction, message, frame, t_ns)

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        handlers = self._publish
        if not handlers:
            return
        held = self._held
        if held is not None:
            held.append((_PUBLISH, key, payload, None, reliable))
            return
        data = payload_json.encode(payload)
        for handler in handlers:
            handler(key, payload, data, reliable)

    def record(self, key: str, payload: Any, direction: str) -> None:
        held = self._held
        if held is not None:
            held.append((_RECORD, key, payload, None, direction))
            return
        for handler in self._record:
            handler(key, payload, direction)

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        held = self._held
        if held is not None:
            held.append((_VEHICLE, system_id, state, None, None))
            return
        for handler in self._vehicle:
            handler(system_id, state)

    def stop(self) -> None:
        """Stop every listener that has a ``stop`` (the recorder is closed by its owner)."""
        for listener in self.listeners:
            stop = getattr(listener, "stop", None)
            if stop is not None:
                stop()


class PublisherTable:
    """A listener's publishers by key, and its ``on_publish``: each publication's bytes put
    on its key's publisher, declared (``declare(key, reliable)``) the first time the key is
    published. Compiled, so that a listener written in Python (``ZenohPublisher``) that
    hands the notifier this ``on_publish`` costs no Python frame per publication."""

    def __init__(self, declare: Callable[[str, bool], Any]) -> None:
        self.publishers: dict[str, Any] = {}
        self._declare = declare

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        publisher = self.publishers.get(key)
        if publisher is None:
            publisher = self._declare(key, reliable)
        publisher.put(data)
