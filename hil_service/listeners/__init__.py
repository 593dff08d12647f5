"""Everything that consumes the service's stream subscribes to one fan-out, as python-can's
``Notifier`` and ``Listener``.

The service tells its ``Notifier`` four things, and the notifier tells every listener:

* ``on_mavlink(direction, message, frame, t_ns)``: a MAVLink frame received (``in``: the
  decoded message; the frame is its own bytes), refused (``rejected``: the frame only) or
  sent (``out``: both);
* ``on_publish(key, payload, data, reliable)``: a publication under one of our Zenoh keys,
  ``data`` its JSON bytes (``payload_json``, encoded once for every listener);
* ``on_record(key, payload, direction)``: what only the log keeps (the decision inputs of a
  sample, received operator inputs);
* ``on_vehicle(system_id, state)``: a newly seen vehicle, with its state query.

Listeners: ``McapRecorder`` (the log), ``ZenohPublisher`` (``zenoh.py``: publications out,
operator inputs in), ``LiveView`` (the Foxglove live view), replay's ``Collector`` and any
test's own. A listener leaves out what it does not consume: the notifier calls only the
methods a listener defines (a subclass of ``Listener`` overrides them).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from protocols import payload_json
from protocols.mavlink_io import MavMessage

EVENTS = ("on_mavlink", "on_publish", "on_record", "on_vehicle")


class Listener:
    """A consumer of the stream; every method does nothing unless overridden."""

    def on_mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        pass

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        pass

    def on_record(self, key: str, payload: Any, direction: str) -> None:
        pass

    def on_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        pass

    def stop(self) -> None:
        pass


def _handler(listener: Any, event: str) -> Callable[..., None] | None:
    """The listener's bound ``event`` method, or None when it does not consume that event."""
    method = getattr(listener, event, None)
    if method is None:
        return None
    function = getattr(type(listener), event, None)
    return None if function is getattr(Listener, event) else method


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
        if all(_handler(listener, event) is None for event in EVENTS) and not isinstance(
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
                handler = _handler(listener, event)
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
