"""MCAP recording of all traffic (DESIGN.md section 4), off the control path.

Producers call ``raw``, ``mavlink`` and ``zenoh``; those only enqueue. One writer thread
encodes and writes, finishes a chunk at least every ``flush_interval`` seconds (so a killed
process loses about that much), rotates files by size or duration, and survives disk
trouble: on an OSError it reports the error, drops what it cannot write (counted) and
retries in a new file.

Channels:
* ``mavlink/raw/in``, ``mavlink/raw/out``: the frames exactly as they crossed the link,
  message encoding ``mavlink2``, the dialect in the channel metadata (replay reads these).
* ``mavlink/json/{in|out}/{MESSAGE}``: each decoded message as JSON with a JSON Schema.
* every Zenoh key published or received, as JSON with the payload's JSON Schema.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType

from hil_service.mcap_writer import McapWriter
from protocols import payload_json
from protocols.keys import schema_for_key
from protocols.mavlink_io import DIALECT_NAME, MAVLINK_VERSION, MavMessage
from protocols.mavlink_json import message_schema, message_to_json
from protocols.schemas import load_schema

RAW_TOPIC = "mavlink/raw/{direction}"
JSON_TOPIC = "mavlink/json/{direction}/{kind}"
RAW_ENCODING = "mavlink2"
CONFIG_METADATA = "glider-hil.config"
PROFILE = "glider-hil"
_STOP = object()
POLL_INTERVAL = 0.02  # s between two drains of the queue by the writer thread
WRITE_BATCH = 256  # records written between two looks at the flush clock


def _now_if_none(t_ns: int | None) -> int:
    """The log time given, or now (0 is a time: a log may start there)."""
    return time.time_ns() if t_ns is None else t_ns


@dataclass
class RecorderStatus:
    files: list[str] = field(default_factory=list)
    records: int = 0
    dropped: int = 0
    error: str = ""
    last_drop: str = ""  # why the last record that could not be encoded was dropped
    queue_depth: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "state": "failed" if self.error else "ok",
            "file": self.files[-1] if self.files else None,
            "files": len(self.files),
            "records": self.records,
            "dropped": self.dropped,
            "error": self.error,
            "last_drop": self.last_drop,
            "queue_depth": self.queue_depth,
        }


class McapRecorder:
    def __init__(
        self,
        log_dir: str | Path,
        metadata: dict[str, str] | None = None,
        max_bytes: int = 256 * 1024 * 1024,
        max_seconds: float = 3600.0,
        flush_interval: float = 0.5,
        max_queue: int = 2_000_000,
        compression: CompressionType = CompressionType.ZSTD,
    ):
        self.log_dir = Path(log_dir)
        self.metadata = metadata or {}
        self.max_bytes = max_bytes
        self.max_seconds = max_seconds
        self.flush_interval = flush_interval
        self.max_queue = max_queue
        self.compression = compression
        self.status = RecorderStatus()
        # A deque, not a queue.Queue: append and popleft are atomic in CPython and take no
        # lock, and the writer thread polls it rather than blocking on it (see _run).
        self._queue: deque[Any] = deque()
        self._thread = threading.Thread(target=self._run, name="mcap-recorder", daemon=True)
        self._writer: McapWriter | None = None
        self._stream: Any = None
        self._channels: dict[tuple[str, ...], int] = {}
        self._opened_at = 0.0
        self._retry_at = 0.0

    # ---- producer side (any thread; never blocks) ----------------------------------
    def start(self) -> McapRecorder:
        self._thread.start()
        return self

    # An item is (route, payload, t_ns); the route is also the writer's channel key, so the
    # writer needs one dict lookup per record and formats a topic only for a new channel.
    def raw(self, direction: str, frame: bytes, t_ns: int | None = None) -> None:
        self._put((("raw", direction), frame, _now_if_none(t_ns)))

    def mavlink(self, direction: str, message: MavMessage, t_ns: int | None = None) -> None:
        """A decoded message; encoded to JSON on the writer thread, off the control path."""
        route = ("json_mav", direction, message.get_type())
        self._put((route, message, _now_if_none(t_ns)))

    def zenoh(self, key: str, payload: Any, direction: str, t_ns: int | None = None) -> None:
        self.zenoh_encoded(key, payload_json.encode(payload), direction, t_ns)

    def zenoh_encoded(self, key: str, data: bytes, direction: str, t_ns: int | None = None) -> None:
        """Record a payload that is already JSON-encoded (what was published, byte for byte)."""
        self._put((("zenoh", key, direction), data, _now_if_none(t_ns)))

    def _put(self, item: tuple[Any, ...]) -> None:
        if len(self._queue) >= self.max_queue:
            self.status.dropped += 1
            return
        self._queue.append(item)

    @property
    def backlog(self) -> int:
        """Records queued and not yet written."""
        return len(self._queue)

    def close(self, timeout: float = 10.0) -> None:
        if self._thread.is_alive():
            self._queue.append(_STOP)
            self._thread.join(timeout)

    # ---- writer thread ----------------------------------------------------------------
    def _run(self) -> None:
        """Wake every ``POLL_INTERVAL`` and write what has queued since.

        Not a blocking ``get`` per record: each put would then wake this thread, and it
        would take the GIL from the control path once per record (measured: more CPU in
        thread switches than in writing).
        """
        pending, write = self._queue, self._write
        next_flush = time.monotonic() + self.flush_interval
        stopping = False
        drained = True
        while not stopping:
            if drained:
                time.sleep(POLL_INTERVAL)
            drained = True
            written = 0
            while pending:
                item = pending.popleft()
                if item is _STOP:
                    stopping = True
                    break
                write(item)
                written += 1
                if written % WRITE_BATCH == 0 and time.monotonic() >= next_flush:
                    drained = False  # a long backlog: flush on time, then go on at once
                    break
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self.flush_interval
                self.status.queue_depth = len(pending)
                self._guarded(self._flush_and_rotate)
        self._guarded(self._finish)

    def _guarded(self, action: Any, *args: Any) -> bool:
        try:
            action(*args)
            return True
        except (OSError, ValueError) as error:
            self._failed(error)
            return False

    def _failed(self, error: Exception) -> None:
        """Disk trouble: report it, drop the file, try a new one in two seconds."""
        self.status.error = f"{type(error).__name__}: {error}"
        self._abandon_file()
        self._retry_at = time.monotonic() + 2.0

    def _write(self, item: tuple[Any, ...]) -> None:
        writer = self._writer
        if writer is None:
            if time.monotonic() < self._retry_at or not self._guarded(self._open):
                self.status.dropped += 1
                return
            writer = self._writer
            assert writer is not None
        route, payload, t_ns = item
        if route[0] == "json_mav":
            try:
                payload = payload_json.encode(message_to_json(payload))
            except Exception as error:  # an unencodable record must not end all logging
                self.status.last_drop = f"{type(error).__name__}: {error}"
                self.status.dropped += 1
                return
        try:
            channel = self._channels.get(route)
            if channel is None:
                channel = self._channels[route] = self._register(writer, route)
            writer.add_message(channel, t_ns, payload)
        except (OSError, ValueError) as error:  # disk trouble: a new file when possible
            self._failed(error)
            self.status.dropped += 1
        else:
            self.status.records += 1

    def _register(self, writer: McapWriter, route: tuple[str, ...]) -> int:
        """The channel (and its schema) for a route seen for the first time in this file."""
        kind, name = route[0], route[1]
        if kind == "raw":
            metadata = {
                "dialect": DIALECT_NAME,
                "mavlink_version": str(MAVLINK_VERSION),
                "direction": name,
            }
            return writer.register_channel(
                RAW_TOPIC.format(direction=name), RAW_ENCODING, 0, metadata
            )
        if kind == "json_mav":
            message_type = route[2]
            schema_id = writer.register_schema(
                f"mavlink.{message_type}",
                "jsonschema",
                json.dumps(message_schema(message_type)).encode(),
            )
            topic = JSON_TOPIC.format(direction=name, kind=message_type)
            return writer.register_channel(topic, "json", schema_id, {"direction": name})
        schema_name = schema_for_key(name)
        schema_id = 0
        if schema_name is not None:
            schema_id = writer.register_schema(
                f"glider-hil.{schema_name}",
                "jsonschema",
                json.dumps(load_schema(schema_name)).encode(),
            )
        metadata = {"direction": route[2], "transport": "zenoh"}
        return writer.register_channel(name, "json", schema_id, metadata)

    def _open(self) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        path = self.log_dir / f"glider-hil_{stamp}.mcap"
        index = 1
        while path.exists():
            path = self.log_dir / f"glider-hil_{stamp}_{index:03d}.mcap"
            index += 1
        self._stream = open(path, "wb")  # noqa: SIM115 - owned by the writer until _finish
        self._writer = McapWriter(self._stream, compression=self.compression)
        self._writer.start(profile=PROFILE, library="glider-hil")
        self._writer.add_metadata(CONFIG_METADATA, self.metadata)
        self._channels = {}
        self._opened_at = time.monotonic()
        self.status.files.append(str(path))
        self.status.error = ""

    def _flush_and_rotate(self) -> None:
        if self._writer is None:
            return
        self._writer.flush()
        too_big = self._stream.tell() >= self.max_bytes
        too_old = time.monotonic() - self._opened_at >= self.max_seconds
        if too_big or too_old:
            self._finish()

    def _finish(self) -> None:
        if self._writer is None:
            return
        writer, stream = self._writer, self._stream
        self._writer, self._stream = None, None
        try:
            writer.finish()
        finally:
            stream.close()

    def _abandon_file(self) -> None:
        stream = self._stream
        self._writer, self._stream = None, None
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()
