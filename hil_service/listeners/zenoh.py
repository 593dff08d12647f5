"""The service's Zenoh side, a listener of its stream (``hil_service.listeners``).

``ZenohPublisher`` puts every publication's bytes on its key (commands with congestion
control BLOCK, the rest with DROP), declares each vehicle's liveliness token and state
queryable, and hands received setpoints and control messages to an ``Inbox`` without
blocking Zenoh's callback threads; each received input is also told to ``record`` (the
notifier's, so that the log keeps it; refused ones apart, with the reason).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import zenoh

from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from protocols import keys, payload_json

#: Where a received input goes besides the inbox: (key, payload, direction).
Record = Callable[[str, Any, str], None]


class ZenohPublisher(Listener):
    def __init__(self, session: zenoh.Session, inbox: Inbox, record: Record | None = None):
        self.session = session
        self.inbox = inbox
        self.record = record
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._declared: dict[int, list[Any]] = {}
        self._subscribers: list[Any] = [
            session.declare_subscriber(key_expr, self._on_input)
            for key_expr in keys.INPUT_SUBSCRIPTIONS
        ]

    def _on_input(self, sample: zenoh.Sample) -> None:
        # Runs on a Zenoh thread: parse and store only, never block.
        key = str(sample.key_expr)
        raw = sample.payload.to_bytes()
        reason = self.inbox.accept(key, raw)
        if self.record is None:
            return
        if reason:  # kept apart, so each input channel holds only what its schema allows
            text = raw.decode("utf-8", "replace")
            refused = {"key": key, "text": text, "reason": reason}
            self.record(keys.rejected_inputs(), refused, "in")
        else:
            self.record(key, json.loads(raw), "in")

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._declare(key, reliable)
        publisher.put(data)

    def _declare(self, key: str, reliable: bool) -> zenoh.Publisher:
        congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
        publisher = self.session.declare_publisher(
            key, congestion_control=congestion, encoding=zenoh.Encoding.APPLICATION_JSON
        )
        self._publishers[key] = publisher
        return publisher

    def on_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        """Liveliness token and state queryable for a newly seen vehicle, and the
        publishers of its keys: declaring one costs in proportion to the keys already
        declared (about 1 ms each with 1,000 vehicles), so a fleet pays it when its
        vehicles appear, not on the sample its control starts."""
        if system_id in self._declared:
            return
        for key, reliable in keys.VehicleKeys.of(system_id).publications():
            if key not in self._publishers:
                self._declare(key, reliable)

        def answer(query: zenoh.Query) -> None:
            query.reply(keys.state(system_id), payload_json.encode(state()))

        self._declared[system_id] = [
            self.session.liveliness().declare_token(keys.service(system_id)),
            self.session.declare_queryable(keys.state(system_id), answer),
        ]

    def stop(self) -> None:
        for declared in [*self._subscribers, *self._publishers.values()]:
            declared.undeclare()
        for items in self._declared.values():
            for item in items:
                item.undeclare()
        self._publishers.clear()
        self._declared.clear()
