"""A Foxglove WebSocket server (``foxglove-sdk``) fed off the control path.

The service's thread calls ``offer(topic, payload)`` and ``offer_mavlink(direction, message,
frame)``: one bounded-deque append, or a counted drop when the deque is full; it never
encodes, never touches a socket, never waits. While no client subscribes to a MAVLink
channel, a MAVLink message of a type already advertised is not even queued (the sender
thread says at each batch whether one does; a viewer that subscribes gets them from the
next batch on). One sender thread creates a Foxglove channel
per topic (same topic names, encodings and schemas as the MCAP log, docs/mcap.md), encodes
the payload exactly as the bus publishes it (``payload_json.encode``), a MAVLink message as
the recorder does (its frame on ``mavlink/raw/{direction}``, its JSON on
``mavlink/json/{direction}/{TYPE}``), and logs it; the SDK's server then keeps a bounded
backlog per client (``BACKLOG`` messages, oldest dropped), so a slow or vanished viewer costs
the service nothing but dropped frames on its own connection.
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
from protocols.mavlink_io import DIALECT_NAME, MAVLINK_VERSION, MavMessage
from protocols.mavlink_json import message_schema, message_to_json
from protocols.schemas import load_schema

#: The MCAP log's MAVLink topics and raw encoding (hil_service/mcap/recorder.py).
RAW_TOPIC = "mavlink/raw/{direction}"
JSON_TOPIC = "mavlink/json/{direction}/{kind}"
RAW_ENCODING = "mavlink2"
_MAVLINK = "\0mavlink"  # the pending entries that are MAVLink messages, not publications

#: Where foxglove-sdk 0.30 reports, at INFO and throttled, that a viewer's outbox was full and
#: its oldest messages were dropped (the Rust module path, as pyo3-log names loggers). The SDK
#: has no counter of those drops; this report is all it gives.
SDK_OVERFLOW_LOGGER = "foxglove.websocket.connected_client.send_lossy"

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


class _Counting(logging.Handler):
    """Counts the records of one logger (a Python call from the SDK's thread per record: only
    for a throttled report)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1


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
        self.unwatched = 0  # MAVLink messages not queued: no client watched a MAVLink channel
        self.encode_errors = 0  # MAVLink messages whose JSON could not be made (skipped)
        self._pending: deque[tuple[str, Any, int]] = deque()
        self._channels: dict[str, Any] = {}  # Channel, or BaseChannel for schemaless ones
        self._raw: dict[str, Any] = {}  # direction → its raw MAVLink channel
        self._decoded: dict[tuple[str, str], Any] = {}  # (direction, type) → JSON channel
        #: (direction, type) of every MAVLink message whose channels exist (the sender's).
        self._known: set[tuple[str, str]] = set()
        #: Whether a client subscribes to a MAVLink channel (the sender's, at each batch);
        #: while none does, the control path queues no MAVLink message it has seen before.
        self._mavlink_watched = False
        self._context = foxglove.Context()
        self._server: Any = None
        self._inputs: list[Any] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="foxglove-live", daemon=True)
        self._overflows = _Counting()

    def start(self) -> LiveView:
        # The SDK reports each failed send to a vanished client through Python's logging,
        # which takes the GIL from the SDK's threads once per message: quiet it (a failed
        # start still raises).
        logging.getLogger("foxglove").setLevel(logging.CRITICAL)
        # Except the throttled report that a slow viewer's outbox overflowed: counted.
        overflow = logging.getLogger(SDK_OVERFLOW_LOGGER)
        overflow.setLevel(logging.INFO)
        overflow.propagate = False
        overflow.addHandler(self._overflows)
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

    def offer_mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        """A MAVLink message the service received (``in``) or sent (``out``), or a frame it
        refused (``rejected``, no message): streamed raw and, for a message, decoded. The
        frame defaults to the message's own bytes. Never blocks (as ``offer``)."""
        self.offered += 1  # as offer, inlined: this runs for every frame
        if (
            not self._mavlink_watched
            and message is not None
            and (direction, message.get_type()) in self._known
        ):
            self.unwatched += 1
            return  # nobody watches a MAVLink channel, and this one is advertised already
        if len(self._pending) >= self.max_pending:
            self.dropped += 1
            return
        self._pending.append((_MAVLINK, (direction, message, frame), t_ns))

    def watched(self) -> bool:
        """Whether a client subscribes to at least one channel now."""
        return any(channel.has_sinks() for channel in list(self._channels.values()))

    def counters(self) -> dict[str, int]:
        """What health's ``service_wide`` carries: messages offered to the live view, passed
        to the server for a subscribed viewer, dropped because the hand-off queue was full
        (the sender thread fell behind), and the server's reports that a viewer too slow to
        read had its oldest messages dropped (throttled by the SDK: at least one per episode,
        not one per message)."""
        return {
            "live_offered": self.offered,
            "live_sent": self.sent,
            "live_dropped": self.dropped,
            "live_viewer_overflows": self._overflows.count,
        }

    def status(self) -> dict[str, Any]:
        return {
            "url": self.url,
            "offered": self.offered,
            "sent": self.sent,
            "dropped": self.dropped,
            "mavlink_unwatched": self.unwatched,
            "viewer_overflows": self._overflows.count,
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

    def _raw_channel(self, direction: str) -> Any:
        channel = self._raw.get(direction)
        if channel is None:
            topic = RAW_TOPIC.format(direction=direction)
            # No schema, as in the log (a MAVLink frame describes itself). foxglove.Channel
            # refuses a schemaless channel unless its encoding is json; the context's own
            # constructor (what Channel calls) takes one.
            channel = self._context._create_channel(
                topic,
                message_encoding=RAW_ENCODING,
                schema=None,
                metadata={
                    "dialect": DIALECT_NAME,
                    "mavlink_version": str(MAVLINK_VERSION),
                    "direction": direction,
                },
            )
            self._channels[topic] = self._raw[direction] = channel
        return channel

    def _json_channel(self, direction: str, message_type: str) -> Any:
        channel = self._decoded.get((direction, message_type))
        if channel is None:
            topic = JSON_TOPIC.format(direction=direction, kind=message_type)
            schema = Schema(
                name=f"mavlink.{message_type}",
                encoding="jsonschema",
                data=json.dumps(message_schema(message_type)).encode(),
            )
            channel = Channel(
                topic,
                schema=schema,
                message_encoding="json",
                context=self._context,
                metadata={"direction": direction},
            )
            self._channels[topic] = self._decoded[direction, message_type] = channel
        return channel

    def _log_mavlink(self, entry: tuple[str, MavMessage | None, bytes | None], t_ns: int) -> None:
        direction, message, frame = entry
        raw = self._raw_channel(direction)
        if raw.has_sinks():
            data = frame if frame is not None else bytes(message.get_msgbuf())  # type: ignore[union-attr]
            raw.log(data, t_ns)
            self.sent += 1
        if message is None:
            return
        decoded = self._json_channel(direction, message.get_type())
        self._known.add((direction, message.get_type()))
        if decoded.has_sinks():
            try:
                data = payload_json.encode(message_to_json(message))
            except Exception:  # as the recorder: one bad message must not end the stream
                self.encode_errors += 1
                return
            decoded.log(data, log_time=t_ns)
            self.sent += 1

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
        self._mavlink_watched = any(
            channel.has_sinks() for channel in (*self._raw.values(), *self._decoded.values())
        )
        watched: dict[str, bool] = {}  # has_sinks per topic, once a batch
        while pending:
            topic, payload, t_ns = pending.popleft()
            count += 1
            if topic == _MAVLINK:
                self._log_mavlink(payload, t_ns or time.time_ns())
                continue
            channel = self._channel(topic)  # created even unwatched: clients see it advertised
            sinks = watched.get(topic)
            if sinks is None:
                sinks = watched[topic] = channel.has_sinks()
            if not sinks:
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
        logging.getLogger(SDK_OVERFLOW_LOGGER).removeHandler(self._overflows)
