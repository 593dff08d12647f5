"""The live view's own process: the Foxglove WebSocket server (``foxglove-sdk``) and all the
work of feeding it, outside the service's process.

``LiveView`` (view.py) starts it as ``python -m hil_service.live --fd N …`` (``__main__.py``,
which lowers its priority first) with one end of a Unix ``SOCK_SEQPACKET`` socket pair. Over
it the service's process sends batches (one pickled list per message, see ``wire.py``) of
entries it has already encoded, and this process answers with its status (one JSON object
per message: first ``{"port": N}`` once the server listens, or ``{"error": TEXT}``; then its
counters whenever they change). Here, on its own interpreter and GIL and at a lower
scheduling priority, one loop creates a Foxglove channel per topic (same topic names,
encodings and schemas as the MCAP log, docs/mcap.md), decodes MAVLink frames as the recorder
does (the frame on ``mavlink/raw/{direction}``, its JSON on
``mavlink/json/{direction}/{TYPE}``) and hands each message of a channel a client subscribes
to to the SDK, whose server keeps a bounded backlog per client (``BACKLOG`` messages, oldest
dropped): a slow or vanished viewer costs the service nothing. The process ends when the
service's end of the socket closes (``close()``, or the service's process ended).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import pickle
import select
import signal
import socket
import sys
from typing import Any

import foxglove
from foxglove import Channel, Schema

from hil_service.live.wire import MAVLINK, MAX_MESSAGE
from protocols import keys, payload_json
from protocols.keys import schema_for_key
from protocols.mavlink_io import DIALECT_NAME, MAVLINK_VERSION, MavlinkCodec, MavMessage
from protocols.mavlink_json import message_schema, message_to_json
from protocols.schemas import load_schema

#: The MCAP log's MAVLink topics and raw encoding (hil_service/mcap/recorder.py).
RAW_TOPIC = "mavlink/raw/{direction}"
JSON_TOPIC = "mavlink/json/{direction}/{kind}"
RAW_ENCODING = "mavlink2"

#: Where foxglove-sdk 0.30 reports, at INFO and throttled, that a viewer's outbox was full and
#: its oldest messages were dropped (the Rust module path, as pyo3-log names loggers). The SDK
#: has no counter of those drops; this report is all it gives.
SDK_OVERFLOW_LOGGER = "foxglove.websocket.connected_client.send_lossy"
#: Messages the SDK buffers per client before it drops the oldest.
BACKLOG = 1024
#: The longest between two looks at the channels' subscribers while no batch arrives, s.
STATUS_PERIOD = 0.02


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


class LiveServer:
    """The SDK's server and its channels, fed by ``handle(batch)``."""

    def __init__(self, host: str, port: int, name: str):
        self.received = 0  # entries taken from the socket
        self.sent = 0  # messages passed to the SDK for a subscribed client
        self.encode_errors = 0  # MAVLink messages that could not be decoded or encoded
        self._context = foxglove.Context()
        self._channels: dict[str, Any] = {}  # Channel, or BaseChannel for schemaless ones
        self._raw: dict[str, Any] = {}  # direction → its raw MAVLink channel
        self._decoded: dict[tuple[str, str], Any] = {}  # (direction, type) → JSON channel
        self._codec = MavlinkCodec(0, 0)  # decodes the frames of messages received
        self._overflows = _Counting()
        # The SDK reports each failed send to a vanished client through Python's logging,
        # once per message: quiet it (a failed start still raises).
        logging.getLogger("foxglove").setLevel(logging.CRITICAL)
        # Except the throttled report that a slow viewer's outbox overflowed: counted.
        overflow = logging.getLogger(SDK_OVERFLOW_LOGGER)
        overflow.setLevel(logging.INFO)
        overflow.propagate = False
        overflow.addHandler(self._overflows)
        self._server = foxglove.start_server(
            name=name, host=host, port=port, context=self._context, message_backlog_size=BACKLOG
        )

    @property
    def port(self) -> int:
        return int(self._server.port)

    def status(self) -> dict[str, Any]:
        """What the service's process shows in health and ``status()``."""
        return {
            "received": self.received,
            "sent": self.sent,
            "encode_errors": self.encode_errors,
            "viewer_overflows": self._overflows.count,
            "channels": len(self._channels),
            "watched": any(channel.has_sinks() for channel in self._channels.values()),
            "mavlink_watched": any(
                channel.has_sinks() for channel in (*self._raw.values(), *self._decoded.values())
            ),
        }

    # ---- channels -------------------------------------------------------------------------
    def _channel(self, topic: str) -> Any:
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
            ).base
            self._channels[topic] = channel
        return channel

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
            ).base
            self._channels[topic] = self._decoded[direction, message_type] = channel
        return channel

    # ---- messages -------------------------------------------------------------------------
    def handle(self, batch: list[tuple[str, Any, int]]) -> None:
        """Log each entry of a batch on its channel, if a client subscribes to it (the
        channel is created, so advertised, either way)."""
        self.received += len(batch)
        watched: dict[str, bool] = {}  # has_sinks per topic, once a batch
        for topic, payload, t_ns in batch:
            if topic == MAVLINK:
                self._mavlink(payload, t_ns)
                continue
            channel = self._channel(topic)
            sinks = watched.get(topic)
            if sinks is None:
                sinks = watched[topic] = channel.has_sinks()
            if not sinks:
                continue
            try:
                data = payload if isinstance(payload, bytes) else payload_json.encode(payload)
            except Exception:  # one bad payload must not end the stream
                self.encode_errors += 1
                continue
            channel.log(data, t_ns)
            self.sent += 1

    def _mavlink(self, entry: tuple[str, str | None, bytes, MavMessage | None], t_ns: int) -> None:
        direction, kind, frame, message = entry
        raw = self._raw_channel(direction)
        if raw.has_sinks():
            try:
                data = bytes(frame)
            except TypeError:  # not a frame: counted, never the end of the stream
                self.encode_errors += 1
                return
            raw.log(data, t_ns)
            self.sent += 1
        if kind is None:  # a refused frame: raw only
            return
        decoded = self._json_channel(direction, kind)
        if not decoded.has_sinks():
            return
        try:
            if message is None:  # received: the frame is what the service decoded
                messages = self._codec.parse(bytes(frame), datagram=True)
                if len(messages) != 1 or messages[0].get_type() != kind:
                    raise ValueError(f"not one {kind} frame")
                message = messages[0]
            data = payload_json.encode(message_to_json(message))
        except Exception:  # as the recorder: one bad message must not end the stream
            self.encode_errors += 1
            return
        decoded.log(data, t_ns)
        self.sent += 1

    def close(self) -> None:
        for channel in self._channels.values():
            channel.close()
        self._server.stop()
        logging.getLogger(SDK_OVERFLOW_LOGGER).removeHandler(self._overflows)


def _report(sock: socket.socket, status: dict[str, Any]) -> None:
    """One status message; dropped if the service's process is not reading (it reads
    the latest only)."""
    with contextlib.suppress(BlockingIOError, ConnectionError):
        sock.send(json.dumps(status).encode(), socket.MSG_DONTWAIT)


def serve(sock: socket.socket, server: LiveServer) -> None:
    """Handle batches until the service's end of the socket closes; a status whenever it
    changed, after the batches at hand are handled (so "caught up" is reported at once),
    and every ``STATUS_PERIOD`` while idle (a client subscribed or left)."""
    last: dict[str, Any] = {}
    poller = select.poll()
    poller.register(sock, select.POLLIN)
    open_ = True
    while open_:
        poller.poll(int(STATUS_PERIOD * 1000))
        while True:
            try:
                data = sock.recv(MAX_MESSAGE, socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            except ConnectionError:
                data = b""
            if not data:
                open_ = False
                break
            server.handle(pickle.loads(data))
        status = server.status()
        if status != last:
            _report(sock, status)
            last = status


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="the live view's Foxglove server process")
    parser.add_argument("--fd", type=int, required=True, help="the socket to the service")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--name", default="glider-hil")
    args = parser.parse_args(argv)
    # The service's process stops this one (it closes its end of the socket); a Ctrl-C for
    # the whole process group must not end it first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sock = socket.socket(fileno=args.fd)
    try:
        server = LiveServer(args.host, args.port, args.name)
    except Exception as error:  # foxglove raises its own error type, e.g. for a port in use
        _report(sock, {"error": f"{type(error).__name__}: {error}"})
        return 2
    _report(sock, {"port": server.port})
    try:
        serve(sock, server)
        _report(sock, server.status())  # the last counters, for the service's summary
    finally:
        server.close()
        sock.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
