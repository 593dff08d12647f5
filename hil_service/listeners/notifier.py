"""The fan-out of the service's stream to its listeners (``hil_service.listeners``),
compiled: the service tells it about every frame and publication of the per-sample path.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from hil_service.listeners.base import EVENTS, Listener, handler_of
from protocols import payload_json
from protocols.mavlink_io import MavMessage


class Notifier:
    """Hands each event to every listener, in the order they were added."""

    def __init__(self, listeners: Iterable[Any] = ()) -> None:
        self.listeners: list[Any] = []
        self._mavlink: list[Callable[..., None]] = []
        self._publish: list[Callable[..., None]] = []
        self._record: list[Callable[..., None]] = []
        self._vehicle: list[Callable[..., None]] = []
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

    # ---- the events -----------------------------------------------------------------
    def mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        for handler in self._mavlink:
            handler(direction, message, frame, t_ns)

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        handlers = self._publish
        if not handlers:
            return
        data = payload_json.encode(payload)
        for handler in handlers:
            handler(key, payload, data, reliable)

    def record(self, key: str, payload: Any, direction: str) -> None:
        for handler in self._record:
            handler(key, payload, direction)

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
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
