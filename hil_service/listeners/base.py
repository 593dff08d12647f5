"""What a consumer of the service's stream is (``Listener``), and which of its methods the
notifier calls (``handler_of``): interpreted, so that any class, a test's included, may
subclass ``Listener``. ``hil_service.listeners`` describes the four events.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

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


def handler_of(listener: Any, event: str) -> Callable[..., None] | None:
    """The listener's ``event`` handler, or None when it does not consume that event: its
    bound method where its class overrides ``Listener``'s, or a callable set on the instance
    itself (a compiled handler it hands the notifier, as ``ZenohPublisher`` does)."""
    method = getattr(listener, event, None)
    if method is None:
        return None
    if event in getattr(listener, "__dict__", ()):
        return method
    function = getattr(type(listener), event, None)
    return None if function is getattr(Listener, event) else method
