"""MCAP recording of all traffic (docs/mcap.md), off the control path.

Producers (the control path, Zenoh callbacks) call ``raw``, ``mavlink`` and ``zenoh``: those
encode the record and pack it into the open chunk in memory, under a lock held for a few
microseconds. One writer thread seals the open chunk at least every ``flush_interval``
seconds (so a killed process loses about that much), compresses and writes sealed chunks,
rotates files by size or duration, and survives disk trouble: on an OSError it reports the
error, drops what it cannot write (counted) and retries in a new file. The writer takes the
lock only to swap the open chunk out, never while it compresses or writes, so a slow disk
cannot stall a producer.

Why producers pack and the thread only compresses and writes: when the thread did the
packing, it held the GIL for a dozen small records per sample, and every time the control
path let the GIL go (a Zenoh put does) the two threads handed it back and forth across
cores. Measured on the end-to-end benchmark: 170–215 µs per sample with the packing on the
thread, 110–120 µs with it on the producer (``benchmarks/bench_service.py``). Compression
and file writes release the GIL.

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
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType

from hil_service.mcap.writer import ChunkBuilder, McapFile, SealedChunk
from protocols import payload_json
from protocols.keys import schema_for_key
from protocols.mavlink_io import DIALECT_NAME, MAVLINK_VERSION, MavMessage, frame_of, type_of
from protocols.mavlink_json import message_schema, message_to_json
from protocols.schemas import load_schema

RAW_TOPIC = "mavlink/raw/{direction}"
JSON_TOPIC = "mavlink/json/{direction}/{kind}"
RAW_ENCODING = "mavlink2"
CONFIG_METADATA = "glider-hil.config"
#: Which file of a rotated log this is: ``part`` (from 1) and ``previous`` (the file name of
#: the part before it; "" for the first).
PART_METADATA = "glider-hil.part"
PROFILE = "glider-hil"
POLL_INTERVAL = 0.02  # s between two looks at the sealed chunks by the writer thread
CHUNK_BYTES = 1 << 20  # the default chunk_bytes


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

    def as_dict(self) -> dict[str, Any]:
        return {
            "state": "failed" if self.error else "ok",
            "file": self.files[-1] if self.files else None,
            "files": len(self.files),
            "records": self.records,
            "dropped": self.dropped,
            "error": self.error,
            "last_drop": self.last_drop,
        }


@dataclass(frozen=True)
class _EndOfFile:
    """Queued after a file's last chunk: what its summary lists."""

    builder: ChunkBuilder


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
        retry_interval: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
        chunk_bytes: int = CHUNK_BYTES,
    ):
        """``retry_interval``: s after disk trouble before a new file is tried. ``clock``
        (monotonic s) times the retry and ``max_seconds`` rotation; tests pass a simulated
        one. The writer's flush schedule always runs on the real monotonic clock.
        ``chunk_bytes``: a producer seals the open chunk once it holds this many bytes (a
        test sets it small, and ``flush_interval`` long, for a file of many chunks whose
        boundaries do not depend on timing)."""
        self.log_dir = Path(log_dir)
        self.metadata = metadata or {}
        self.max_bytes = max_bytes
        self.max_seconds = max_seconds
        self.flush_interval = flush_interval
        self.max_queue = max_queue  # records held in memory (open and sealed chunks)
        self.compression = compression
        self.retry_interval = retry_interval
        self._clock = clock
        self.chunk_bytes = chunk_bytes
        self.status = RecorderStatus()
        self._lock = threading.Lock()  # guards everything below up to _closed, and status
        self._builder = ChunkBuilder()
        self._channels: dict[tuple[str, ...], int] = {}  # route → channel of _builder's file
        self._sealed: deque[SealedChunk | _EndOfFile] = deque()
        self._backlog = 0  # records in sealed chunks not yet written
        self._closed = False
        self._wake = threading.Event()
        self._writer_thread = threading.Thread(target=self._run, name="mcap-recorder", daemon=True)
        # Owned by the writer thread:
        self._file: McapFile | None = None
        self._stream: Any = None
        self._opened_at = 0.0
        self._retry_at = 0.0

    def start(self) -> McapRecorder:
        self._writer_thread.start()
        return self

    # ---- producer side (any thread; never waits for the disk) ---------------------------
    # A route is the channel key: one dict lookup per record, a topic formatted only for a
    # channel new to the file.
    def raw(self, direction: str, frame: bytes, t_ns: int | None = None) -> None:
        self._record(("raw", direction), frame, _now_if_none(t_ns))

    def mavlink(self, direction: str, message: MavMessage, t_ns: int | None = None) -> None:
        """A decoded message, logged as JSON on ``mavlink/json/{direction}/{TYPE}``."""
        data = self._json_of(message)
        if data is not None:
            self._record(("json_mav", direction, type_of(message)), data, _now_if_none(t_ns))

    def _json_of(self, message: MavMessage) -> bytes | None:
        """The message as JSON; None (dropped and counted) when it cannot be encoded: an
        unencodable record must not end all logging."""
        try:
            return payload_json.encode(message_to_json(message))
        except Exception as error:
            self._drop(error)
            return None

    def zenoh(self, key: str, payload: Any, direction: str, t_ns: int | None = None) -> None:
        """A payload on ``key``, encoded here; one that JSON cannot hold (an integer beyond
        64 bits) is dropped and counted, as the producer must not fail for its log."""
        try:
            data = payload_json.encode(payload)
        except Exception as error:
            self._drop(error)
            return
        self.zenoh_encoded(key, data, direction, t_ns)

    def _drop(self, error: Exception) -> None:
        """A record that could not be encoded: counted, and why the last one was."""
        with self._lock:
            self.status.last_drop = f"{type(error).__name__}: {error}"
            self.status.dropped += 1

    def zenoh_encoded(self, key: str, data: bytes, direction: str, t_ns: int | None = None) -> None:
        """Record a payload that is already JSON-encoded (what was published, byte for byte)."""
        self._record(("zenoh", key, direction), data, _now_if_none(t_ns))

    # ---- as a listener of the service's stream (hil_service.listeners) -----------------
    def on_mavlink(
        self, direction: str, message: MavMessage | None, frame: bytes | None, t_ns: int
    ) -> None:
        """A frame on ``mavlink/raw/{direction}`` (a received one: the message's own bytes)
        and the message, if any, as JSON; both records under one hold of the lock."""
        if frame is None and message is not None:
            frame = frame_of(message)
        data = None if message is None else self._json_of(message)
        with self._lock:
            full = frame is not None and self._add_locked(("raw", direction), frame, t_ns)
            if data is not None:
                route = ("json_mav", direction, type_of(message))
                full = self._add_locked(route, data, t_ns) or full
        if full:
            self._wake.set()

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        self.zenoh_encoded(key, data, "out")

    def on_record(self, key: str, payload: Any, direction: str) -> None:
        self.zenoh(key, payload, direction)

    def _record(self, route: tuple[str, ...], data: bytes, t_ns: int) -> None:
        with self._lock:
            full = self._add_locked(route, data, t_ns)
        if full:
            self._wake.set()

    def _add_locked(self, route: tuple[str, ...], data: bytes, t_ns: int) -> bool:
        """One record into the open chunk; True when that sealed a full chunk (the writer
        thread must be woken once the lock is released)."""
        builder = self._builder
        if self._closed or self._backlog + builder.messages >= self.max_queue:
            self.status.dropped += 1
            return False
        channel = self._channels.get(route)
        if channel is None:
            channel = self._channels[route] = self._register(builder, route)
        builder.add_message(channel, t_ns, data)
        if builder.size < self.chunk_bytes:
            return False
        self._seal_locked()
        return True

    @property
    def backlog(self) -> int:
        """Records in sealed chunks that the writer thread has not written yet.

        The open chunk is not counted: it is sealed on time or when it reaches
        ``chunk_bytes``, whichever comes first.
        """
        return self._backlog

    def report(self) -> dict[str, Any]:
        """``status`` with ``queue_depth``, the backlog now (``health.logging``)."""
        return {**self.status.as_dict(), "queue_depth": self._backlog}

    def close(self, timeout: float = 10.0) -> None:
        """Write everything recorded so far, finish the file; later records are dropped."""
        with self._lock:
            self._closed = True
        if self._writer_thread.is_alive():
            self._wake.set()
            self._writer_thread.join(timeout)

    # ---- hand-over (lock held) ------------------------------------------------------------
    def _seal_locked(self) -> None:
        sealed = self._builder.seal()
        if sealed is not None:
            self._sealed.append(sealed)
            self._backlog += sealed.messages

    def _end_file_locked(self) -> None:
        """Seal the open chunk and start a builder for the next file."""
        self._seal_locked()
        self._sealed.append(_EndOfFile(self._builder))
        self._builder = ChunkBuilder()
        self._channels = {}

    def _register(self, builder: ChunkBuilder, route: tuple[str, ...]) -> int:
        """The channel (and its schema) for a route seen for the first time in this file."""
        kind, name = route[0], route[1]
        if kind == "raw":
            metadata = {
                "dialect": DIALECT_NAME,
                "mavlink_version": str(MAVLINK_VERSION),
                "direction": name,
            }
            return builder.register_channel(
                RAW_TOPIC.format(direction=name), RAW_ENCODING, 0, metadata
            )
        if kind == "json_mav":
            message_type = route[2]
            schema_id = builder.register_schema(
                f"mavlink.{message_type}",
                "jsonschema",
                json.dumps(message_schema(message_type)).encode(),
            )
            topic = JSON_TOPIC.format(direction=name, kind=message_type)
            return builder.register_channel(topic, "json", schema_id, {"direction": name})
        schema_name = schema_for_key(name)
        schema_id = 0
        if schema_name is not None:
            schema_id = builder.register_schema(
                f"glider-hil.{schema_name}",
                "jsonschema",
                json.dumps(load_schema(schema_name)).encode(),
            )
        metadata = {"direction": route[2], "transport": "zenoh"}
        return builder.register_channel(name, "json", schema_id, metadata)

    # ---- writer thread ----------------------------------------------------------------
    def _run(self) -> None:
        """Every ``POLL_INTERVAL`` (or when a producer seals a full chunk): write the sealed
        chunks; every ``flush_interval``: seal the open chunk too, flush, maybe rotate."""
        next_flush = time.monotonic() + self.flush_interval
        while True:
            self._wake.wait(POLL_INTERVAL)
            self._wake.clear()
            closing = self._closed
            flush_due = closing or time.monotonic() >= next_flush
            if flush_due:
                with self._lock:
                    self._seal_locked()
            self._write_sealed()
            if closing:
                break
            if flush_due:
                next_flush = time.monotonic() + self.flush_interval
                self._guarded(self._flush_and_rotate)
                self._write_sealed()
        with self._lock:
            self._end_file_locked()
        self._write_sealed()

    def _write_sealed(self) -> None:
        while True:
            with self._lock:
                if not self._sealed:
                    return
                item = self._sealed.popleft()
            if isinstance(item, _EndOfFile):
                if self._file is not None:
                    self._guarded(self._finish, item.builder)
                continue
            self._write_chunk(item)

    def _write_chunk(self, sealed: SealedChunk) -> None:
        if self._file is None and (self._clock() < self._retry_at or not self._guarded(self._open)):
            self._discard(sealed)
            return
        assert self._file is not None
        if not self._guarded(self._file.write_chunk, sealed):  # disk trouble: a new file next
            self._discard(sealed)
            return
        with self._lock:
            self._backlog -= sealed.messages
            self.status.records += sealed.messages

    def _discard(self, sealed: SealedChunk) -> None:
        """Drop a chunk that cannot be written, and everything recorded after it.

        The lost chunk may hold the definitions of channels that later chunks use, so the
        builder starts over: the next file defines its channels again.
        """
        with self._lock:
            lost = sealed.messages + self._builder.messages
            self._backlog -= sealed.messages
            for item in self._sealed:
                if isinstance(item, SealedChunk):
                    lost += item.messages
                    self._backlog -= item.messages
            self._sealed.clear()
            self._builder = ChunkBuilder()
            self._channels = {}
            self.status.dropped += lost

    def _guarded(self, action: Any, *args: Any) -> bool:
        try:
            action(*args)
            return True
        except (OSError, ValueError) as error:
            self._failed(error)
            return False

    def _failed(self, error: Exception) -> None:
        """Disk trouble: report it, drop the file, try a new one after ``retry_interval``."""
        self.status.error = f"{type(error).__name__}: {error}"
        self._abandon_file()
        self._retry_at = self._clock() + self.retry_interval

    def _open(self) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        path = self.log_dir / f"glider-hil_{stamp}.mcap"
        index = 1
        while path.exists():
            path = self.log_dir / f"glider-hil_{stamp}_{index:03d}.mcap"
            index += 1
        self._stream = open(path, "wb")  # noqa: SIM115 - owned by the writer until _finish
        self._file = McapFile(self._stream, compression=self.compression)
        self._file.start(profile=PROFILE, library="glider-hil")
        self._file.add_metadata(CONFIG_METADATA, self.metadata)
        files = self.status.files
        previous = Path(files[-1]).name if files else ""
        self._file.add_metadata(PART_METADATA, {"part": str(len(files) + 1), "previous": previous})
        self._opened_at = self._clock()
        self.status.files.append(str(path))
        self.status.error = ""

    def _flush_and_rotate(self) -> None:
        if self._file is None:
            return
        self._file.flush()
        too_big = self._file.tell() >= self.max_bytes
        too_old = self._clock() - self._opened_at >= self.max_seconds
        if too_big or too_old:
            with self._lock:
                self._end_file_locked()

    def _finish(self, builder: ChunkBuilder) -> None:
        file, stream = self._file, self._stream
        self._file, self._stream = None, None
        assert file is not None
        try:
            file.finish(builder.schemas, builder.channels)
        finally:
            stream.close()

    def _abandon_file(self) -> None:
        stream = self._stream
        self._file, self._stream = None, None
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()
