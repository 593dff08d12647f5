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
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

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


@dataclass
class RecorderStatus:
    files: list[str] = field(default_factory=list)
    records: int = 0
    dropped: int = 0
    error: str = ""
    queue_depth: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "state": "failed" if self.error else "ok",
            "file": self.files[-1] if self.files else None,
            "files": len(self.files),
            "records": self.records,
            "dropped": self.dropped,
            "error": self.error,
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
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="mcap-recorder", daemon=True)
        self._writer: Writer | None = None
        self._stream: Any = None
        self._channels: dict[str, int] = {}
        self._opened_at = 0.0
        self._retry_at = 0.0

    # ---- producer side (any thread; never blocks) ----------------------------------
    def start(self) -> McapRecorder:
        self._thread.start()
        return self

    def raw(self, direction: str, frame: bytes, t_ns: int | None = None) -> None:
        self._put(("raw", direction, frame, t_ns or time.time_ns()))

    def mavlink(self, direction: str, message: MavMessage, t_ns: int | None = None) -> None:
        self._put(("json_mav", direction, message, t_ns or time.time_ns()))

    def zenoh(self, key: str, payload: Any, direction: str, t_ns: int | None = None) -> None:
        self._put(("zenoh", key, json.dumps(payload, allow_nan=False).encode(), direction,
                   t_ns or time.time_ns()))  # fmt: skip

    def zenoh_encoded(self, key: str, data: bytes, direction: str, t_ns: int | None = None) -> None:
        """Record a payload that is already JSON-encoded (what was published, byte for byte)."""
        self._put(("zenoh", key, data, direction, t_ns or time.time_ns()))

    def _put(self, item: tuple[Any, ...]) -> None:
        if self._queue.qsize() >= self.max_queue:
            self.status.dropped += 1
            return
        self._queue.put(item)

    def close(self, timeout: float = 10.0) -> None:
        if self._thread.is_alive():
            self._queue.put(_STOP)
            self._thread.join(timeout)

    # ---- writer thread ----------------------------------------------------------------
    def _run(self) -> None:
        next_flush = time.monotonic() + self.flush_interval
        while True:
            try:
                item = self._queue.get(timeout=max(next_flush - time.monotonic(), 0.0))
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is not None:
                self._write(item)
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self.flush_interval
                self.status.queue_depth = self._queue.qsize()
                self._guarded(self._flush_and_rotate)
        self._guarded(self._finish)

    def _guarded(self, action: Any, *args: Any) -> bool:
        try:
            action(*args)
            return True
        except (OSError, ValueError) as error:
            self.status.error = f"{type(error).__name__}: {error}"
            self._abandon_file()
            self._retry_at = time.monotonic() + 2.0
            return False

    def _write(self, item: tuple[Any, ...]) -> None:
        cannot_open = self._writer is None and (
            time.monotonic() < self._retry_at or not self._guarded(self._open)
        )
        if cannot_open:
            self.status.dropped += 1
            return
        if self._guarded(self._write_item, item):
            self.status.records += 1
        else:
            self.status.dropped += 1

    def _write_item(self, item: tuple[Any, ...]) -> None:
        kind = item[0]
        if kind == "raw":
            _, direction, frame, t_ns = item
            channel = self._channel_raw(direction)
            data = frame
        elif kind == "json_mav":
            _, direction, message, t_ns = item
            channel = self._channel_json_mav(direction, message.get_type())
            data = json.dumps(message_to_json(message)).encode()
        else:
            _, key, data, direction, t_ns = item
            channel = self._channel_zenoh(key, direction)
        assert self._writer is not None
        self._writer.add_message(channel, log_time=t_ns, data=data, publish_time=t_ns)

    def _channel_raw(self, direction: str) -> int:
        topic = RAW_TOPIC.format(direction=direction)
        if topic not in self._channels:
            assert self._writer is not None
            self._channels[topic] = self._writer.register_channel(
                topic,
                RAW_ENCODING,
                schema_id=0,
                metadata={
                    "dialect": DIALECT_NAME,
                    "mavlink_version": str(MAVLINK_VERSION),
                    "direction": direction,
                },
            )
        return self._channels[topic]

    def _channel_json_mav(self, direction: str, kind: str) -> int:
        topic = JSON_TOPIC.format(direction=direction, kind=kind)
        if topic not in self._channels:
            assert self._writer is not None
            schema_id = self._writer.register_schema(
                f"mavlink.{kind}", "jsonschema", json.dumps(message_schema(kind)).encode()
            )
            self._channels[topic] = self._writer.register_channel(
                topic, "json", schema_id, metadata={"direction": direction}
            )
        return self._channels[topic]

    def _channel_zenoh(self, key: str, direction: str) -> int:
        if key not in self._channels:
            assert self._writer is not None
            schema_name = schema_for_key(key)
            schema_id = 0
            if schema_name is not None:
                schema_id = self._writer.register_schema(
                    f"glider-hil.{schema_name}",
                    "jsonschema",
                    json.dumps(load_schema(schema_name)).encode(),
                )
            self._channels[key] = self._writer.register_channel(
                key, "json", schema_id, metadata={"direction": direction, "transport": "zenoh"}
            )
        return self._channels[key]

    def _open(self) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        path = self.log_dir / f"glider-hil_{stamp}.mcap"
        index = 1
        while path.exists():
            path = self.log_dir / f"glider-hil_{stamp}_{index:03d}.mcap"
            index += 1
        self._stream = open(path, "wb")  # noqa: SIM115 - owned by the writer until _finish
        self._writer = Writer(self._stream, compression=self.compression, chunk_size=1 << 20)
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
