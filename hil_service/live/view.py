"""A Foxglove WebSocket server (``foxglove-sdk``) fed off the control path.

The service's thread calls ``offer(topic, payload)``: one bounded-deque append, or a counted
drop when the deque is full; it never encodes, never touches a socket, never waits. One
sender thread creates a Foxglove channel per topic (same topic names and JSON Schemas as the
MCAP log, docs/mcap.md), encodes the payload exactly as the bus publishes it
(``payload_json.encode``) and logs it; the SDK's server then keeps a bounded backlog per
client (``BACKLOG`` messages, oldest dropped), so a slow or vanished viewer costs the service
nothing but dropped frames on its own connection.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from typing import Any

import foxglove
from foxglove import Channel, Schema

from hil_service.live.address import LiveAddress
from protocols import keys, payload_json
from protocols.keys import schema_for_key
from protocols.schemas import load_schema

#: Payloads held between the service and the sender thread; past that they are dropped.
MAX_PENDING = 10_000
#: Messages the SDK buffers per client before it drops the oldest.
BACKLOG = 1024
IDLE_WAIT = 0.05  # s between two batches of the sender thread


def channel_schema(topic: str) -> Schema | None:
    """The JSON Schema the MCAP log labels ``topic`` with (None: schemaless JSON)."""
    name = schema_for_key(topic)
    if name is None:
        return None
    return Schema(
        name=f"glider-hil.{name}",
        encoding="jsonschema",
        data=json.dumps(load_schema(name)).encode(),
    )


class LiveView:
    """``start()`` opens the server; ``offer`` from any thread; ``close()`` stops both."""

    def __init__(
        self, address: LiveAddress, name: str = "glider-hil", max_pending: int = MAX_PENDING
    ):
        self.address = address
        self.name = name
        self.max_pending = max_pending
        self.offered = 0
        self.dropped = 0  # offered while the pending deque was full
        self.sent = 0
        self._pending: deque[tuple[str, Any, int]] = deque()
        self._channels: dict[str, Channel] = {}
        self._context = foxglove.Context()
        self._server: Any = None
        self._inputs: list[Any] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove-live", daemon=True)

    def start(self) -> LiveView:
        # The SDK reports each failed send to a vanished client through Python's logging,
        # which takes the GIL from the SDK's threads once per message: quiet it (a failed
        # start still raises).
        logging.getLogger("foxglove").setLevel(logging.CRITICAL)
        self._server = foxglove.start_server(
            name=self.name,
            host=self.address.host,
            port=self.address.port,
            context=self._context,
            message_backlog_size=BACKLOG,
        )
        self._thread.start()
        return self

    @property
    def port(self) -> int:
        """The port the server listens on (the one chosen when 0 was asked)."""
        return int(self._server.port) if self._server is not None else self.address.port

    @property
    def url(self) -> str:
        return f"ws://{self.address.host}:{self.port}"

    # ---- producer side: the control path ------------------------------------------------
    def offer(self, topic: str, payload: Any, t_ns: int = 0) -> None:
        """Hand a payload to the sender thread; never blocks. ``payload`` is a JSON-ready
        object the caller does not change afterwards, or already encoded ``bytes``."""
        self.offered += 1
        if len(self._pending) >= self.max_pending:
            self.dropped += 1
            return
        self._pending.append((topic, payload, t_ns))

    def watched(self) -> bool:
        """Whether a client subscribes to at least one channel now."""
        return any(channel.has_sinks() for channel in list(self._channels.values()))

    def status(self) -> dict[str, Any]:
        return {
            "url": self.url,
            "offered": self.offered,
            "sent": self.sent,
            "dropped": self.dropped,
            "pending": len(self._pending),
        }

    # ---- sender thread --------------------------------------------------------------------
    def watch_inputs(self, session: Any) -> None:
        """Also stream the inputs the service receives (setpoints, control), as the log
        records them: a Zenoh subscriber of our own whose callback only offers the bytes."""

        def on_input(sample: Any) -> None:
            self.offer(str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())

        self._inputs = [
            session.declare_subscriber(key_expr, on_input) for key_expr in keys.INPUT_SUBSCRIPTIONS
        ]

    def _channel(self, topic: str) -> Channel:
        channel = self._channels.get(topic)
        if channel is None:
            parsed = keys.parse(topic)
            inbound = parsed is not None and parsed.kind in (keys.SETPOINT, keys.CONTROL)
            channel = Channel(
                topic,
                schema=channel_schema(topic),
                message_encoding="json",
                context=self._context,
                metadata={"transport": "zenoh", "direction": "in" if inbound else "out"},
            )
            self._channels[topic] = channel
        return channel

    def _drain(self) -> int:
        pending = self._pending
        count = 0
        while pending:
            topic, payload, t_ns = pending.popleft()
            channel = self._channel(topic)  # created even unwatched: clients see it advertised
            count += 1
            if not channel.has_sinks():
                continue
            data = payload if isinstance(payload, bytes) else payload_json.encode(payload)
            channel.log(data, log_time=t_ns or time.time_ns())
            self.sent += 1
        return count

    def _run(self) -> None:
        # Drain in batches every IDLE_WAIT: a busy loop here would take the GIL from the
        # control path each time it lets go.
        while not self._stop.wait(IDLE_WAIT):
            self._drain()
        self._drain()

    def close(self) -> None:
        for subscriber in self._inputs:
            subscriber.undeclare()
        self._inputs = []
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        for channel in self._channels.values():
            channel.close()
        if self._server is not None:
            self._server.stop()
            self._server = None
