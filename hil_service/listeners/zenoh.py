"""The service's Zenoh side behind a small interface (``Bus``), so replay and benchmarks can
swap it.

``ZenohBus`` publishes JSON payloads (commands with congestion control BLOCK, the rest with
DROP), records every publication and every received input to MCAP, and hands received
setpoints and control messages to an ``Inbox`` without blocking Zenoh's callback threads.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, Protocol

import zenoh

from hil_service.inputs import Inbox
from hil_service.mcap.recorder import McapRecorder
from protocols import keys, payload_json


class Bus(Protocol):
    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None: ...

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None: ...

    def close(self) -> None: ...


class NullBus:
    """Publishes nothing: replay without ``--publish``, benchmarks of the decode path."""

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        pass

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        pass

    def close(self) -> None:
        pass


class ZenohBus:
    def __init__(
        self,
        session: zenoh.Session,
        inbox: Inbox,
        recorder: McapRecorder | None = None,
    ):
        self.session = session
        self.inbox = inbox
        self.recorder = recorder
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
        if self.recorder is None:
            return
        if reason:  # kept apart, so each input channel holds only what its schema allows
            text = raw.decode("utf-8", "replace")
            refused = {"key": key, "text": text, "reason": reason}
            self.recorder.zenoh(keys.rejected_inputs(), refused, "in")
        else:
            self.recorder.zenoh(key, json.loads(raw), "in")

    def publish(self, key: str, payload: dict[str, Any], reliable: bool = False) -> None:
        self.publish_encoded(key, payload_json.encode(payload), reliable)

    def publish_encoded(self, key: str, data: bytes, reliable: bool = False) -> None:
        """``publish`` of a payload already encoded (``payload_json.encode``): the live view's
        bus encodes once for Zenoh, the log and the viewer."""
        publisher = self._publishers.get(key)
        if publisher is None:
            congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
            publisher = self.session.declare_publisher(
                key, congestion_control=congestion, encoding=zenoh.Encoding.APPLICATION_JSON
            )
            self._publishers[key] = publisher
        publisher.put(data)
        if self.recorder is not None:
            self.recorder.zenoh_encoded(key, data, "out")

    def declare_vehicle(self, system_id: int, state: Callable[[], dict[str, Any]]) -> None:
        """Liveliness token and state queryable for a newly seen vehicle."""
        if system_id in self._declared:
            return

        def answer(query: zenoh.Query) -> None:
            query.reply(keys.state(system_id), payload_json.encode(state()))

        self._declared[system_id] = [
            self.session.liveliness().declare_token(keys.service(system_id)),
            self.session.declare_queryable(keys.state(system_id), answer),
        ]

    def close(self) -> None:
        for declared in [*self._subscribers, *self._publishers.values()]:
            declared.undeclare()
        for items in self._declared.values():
            for item in items:
                item.undeclare()
        self._publishers.clear()
        self._declared.clear()
