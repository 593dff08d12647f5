"""A ``Bus`` that also offers every publication to the live view.

It wraps the service's real bus (Zenoh, or nothing for replay without ``--publish``): the
inner bus publishes as before, then the payload is handed to ``LiveView.offer`` (a deque
append). Over Zenoh the payload is encoded once and the same bytes go to both (the live
view's process gets them as they are). Keys and payloads are
the ones the MCAP log records on the same topics.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from hil_service.listeners.zenoh import Bus
from protocols import payload_json

if TYPE_CHECKING:
    from hil_service.live.view import LiveView


class LiveBus:
    def __init__(self, inner: Bus, live: LiveView):
        self.inner = inner
        self.live = live
        #: The inner bus's entry for a payload already encoded (ZenohBus), if it has one.
        self._publish_encoded: Callable[[str, bytes, bool], None] | None = getattr(
            inner, "publish_encoded", None
        )

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        if self._publish_encoded is None:  # a bus that encodes nothing (replay, no --publish)
            self.inner.publish(key, payload, reliable)
            self.live.offer(key, payload, time.time_ns())
            return
        # Encoded once, for Zenoh (and the log) and the live view alike: the same bytes.
        data = payload_json.encode(payload)
        self._publish_encoded(key, data, reliable)
        self.live.offer(key, data, time.time_ns())

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        self.inner.declare_vehicle(system_id, state)

    def close(self) -> None:
        self.inner.close()
