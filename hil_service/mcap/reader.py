"""Reads our MCAP logs, including ones whose writer was killed or that were cut or damaged.

A complete file is read through its records like any other; a file with no summary section
(the writer was killed) is read up to its last complete chunk, and a truncated or corrupted
file stops at the first bad record with the byte offset reported, never an exception. A
chunk whose contents are damaged but whose record is whole is skipped and counted, and
reading goes on after it. A message on a channel no record read so far defined (its
definition was in such a chunk) takes its channel, and that channel's schema, from the
file's summary section, which repeats every Schema and Channel record; only when the file
has no readable summary (a writer that was killed, a damaged footer or summary) is it
counted as lost.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

from mcap.opcode import Opcode
from mcap.records import Channel, Footer, Message, Metadata, Schema

from hil_service.mcap.recorder import CONFIG_METADATA, PART_METADATA
from hil_service.mcap.records import MAGIC, DamagedChunk, read_records
from protocols.input_files import not_a_file

RECORD_SIZE_LIMIT = 256 * 1024 * 1024  # a corrupted length must not allocate gigabytes
#: The footer record at the end of a finished file, before the closing magic: opcode,
#: length (20), summary start, summary offset start, summary CRC.
_FOOTER = struct.Struct("<BQQQI")


class LogError(Exception):
    """The file is not an MCAP log at all (missing or wrong magic)."""


class StoredConfigError(ValueError):
    """A value of a log's stored configuration (the ``glider-hil.config`` record) that
    cannot be used: not JSON, of the wrong JSON type, or out of range. The message names
    the log (when known), the stored key (``service.stale_timeout``) and what is wrong."""

    def __init__(self, key: str, problem: str, log: str | Path | None = None) -> None:
        self.key = key
        self.problem = problem
        self.log = None if log is None else str(log)
        where = "" if log is None else f"{log}: "
        super().__init__(f"{where}stored config {key}: {problem}")

    def of_log(self, log: str | Path) -> StoredConfigError:
        """The same problem, naming the log it was read from."""
        return StoredConfigError(self.key, self.problem, log)


class LogMessage(NamedTuple):
    """One logged message (a named tuple: replay builds tens of thousands per second)."""

    topic: str
    log_time_ns: int
    data: bytes
    message_encoding: str
    channel_metadata: dict[str, str]

    def json(self) -> Any:
        return json.loads(self.data)


@dataclass
class ReadReport:
    """What reading found: whether the file was finished, and where it stopped if not."""

    path: str
    complete: bool = False
    #: The reader got to the end of what it could read (EOF, footer or a damaged record);
    #: False while a consumer stopped early, when nothing can be said about the file's end.
    ended: bool = False
    messages: int = 0
    bytes_read: int = 0
    file_size: int = 0
    error: str = ""
    error_offset: int | None = None
    #: Chunks skipped for damaged contents, and the first one's reason and offset.
    damaged_chunks: int = 0
    first_damage: str = ""
    #: Messages on a channel no readable record defined (its definition was in a damaged
    #: chunk, and the file has no readable summary section to repeat it): skipped.
    lost_messages: int = 0
    #: Channels defined only by the summary section (their data-section record was in a
    #: damaged chunk), and the messages read on them.
    summary_channels: int = 0
    summary_messages: int = 0
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def intact(self) -> bool:
        """Finished, and every chunk read."""
        return self.complete and not self.damaged_chunks

    def describe(self) -> str:
        damage = ""
        if self.damaged_chunks:
            damage = (
                f"; {self.damaged_chunks} damaged chunk(s) skipped, their messages lost (the "
                f"first: {self.first_damage}), {self.lost_messages} messages on channels "
                "they defined lost"
            )
            if self.summary_channels:
                damage += (
                    f", {self.summary_messages} read on {self.summary_channels} channel(s) "
                    "defined from the summary section"
                )
        if self.complete:
            return f"{self.path}: complete, {self.messages} messages{damage}"
        return (
            f"{self.path}: not finished ({self.error or 'no footer'}"
            f"{'' if self.error_offset is None else f' at byte {self.error_offset}'}); "
            f"recovered {self.messages} messages from {self.bytes_read} of "
            f"{self.file_size} bytes{damage}"
        )


class LogReader:
    """Iterate a log's messages in file order; ``report`` is filled in as it goes."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.report = ReadReport(path=str(self.path))

    def messages(self, topics: set[str] | None = None) -> Iterator[LogMessage]:
        """Messages in file order, only on ``topics`` if given (all are counted in ``report``)."""
        report = self.report
        problem = not_a_file(self.path, "log", directory_hint="give the .mcap files in it")
        if problem:
            raise LogError(problem)
        report.file_size = self.path.stat().st_size
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        #: The summary section's Schema and Channel records, read when first needed.
        summary: tuple[dict[int, Schema], dict[int, Channel]] | None = None
        from_summary: set[int] = set()
        with open(self.path, "rb") as stream:
            records = read_records(stream, validate_crcs=True, record_size_limit=RECORD_SIZE_LIMIT)
            while True:
                offset = stream.tell()
                try:
                    record = next(records)
                except StopIteration:
                    if offset == 0:  # the magic alone: a log cut before its header record
                        raise LogError(self._unreadable_start(stream, EOFError())) from None
                    report.ended = True
                    break
                except Exception as error:  # truncated or corrupted: stop, say where
                    if offset == 0:
                        raise LogError(self._unreadable_start(stream, error)) from error
                    report.error = f"{type(error).__name__}: {error}".strip()
                    report.error_offset = offset  # the start of the first bad record
                    report.ended = True
                    break
                report.bytes_read = stream.tell()
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    self._add_channel(record, schemas.get(record.schema_id))
                elif isinstance(record, Metadata):
                    report.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        if summary is None:
                            summary = self._summary(stream)
                        channel = summary[1].get(record.channel_id)
                        if channel is None:
                            report.lost_messages += 1
                            continue
                        channels[channel.id] = channel
                        from_summary.add(channel.id)
                        report.summary_channels += 1
                        schema = schemas.get(channel.schema_id, summary[0].get(channel.schema_id))
                        self._add_channel(channel, schema)
                    if from_summary and record.channel_id in from_summary:
                        report.summary_messages += 1
                    report.messages += 1
                    report.channels[channel.topic]["count"] += 1
                    if topics is None or channel.topic in topics:
                        yield LogMessage(
                            channel.topic,
                            record.log_time,
                            record.data,
                            channel.message_encoding,
                            channel.metadata,
                        )
                elif isinstance(record, Footer):
                    report.complete = True
                elif isinstance(record, DamagedChunk):
                    report.damaged_chunks += 1
                    if not report.first_damage:
                        report.first_damage = f"{record.reason} at byte {record.offset}"

    def _add_channel(self, channel: Channel, schema: Schema | None) -> None:
        self.report.channels.setdefault(
            channel.topic,
            {
                "encoding": channel.message_encoding,
                "schema": schema.name if schema else None,
                "schema_encoding": schema.encoding if schema else None,
                "metadata": dict(channel.metadata),
                "count": 0,
            },
        )

    def _summary(self, stream: BinaryIO) -> tuple[dict[int, Schema], dict[int, Channel]]:
        """The Schema and Channel records of the file's summary section, found through its
        footer (the file's last record), its CRC checked where the writer gave one; none
        when the file has no footer, no summary or a damaged one. ``stream`` is left where
        it was."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        position = stream.tell()
        footer_start = self.report.file_size - len(MAGIC) - _FOOTER.size
        try:
            if footer_start <= len(MAGIC):
                return schemas, channels
            stream.seek(footer_start)
            tail = stream.read(_FOOTER.size + len(MAGIC))
            opcode, length, start, _, crc = _FOOTER.unpack_from(tail)
            if opcode != Opcode.FOOTER or length != 20 or tail[_FOOTER.size :] != MAGIC:
                return schemas, channels
            if not len(MAGIC) <= start < footer_start:
                return schemas, channels  # 0: no summary section
            stream.seek(start)
            section = stream.read(footer_start - start)
            # The CRC covers the summary and the footer up to (not with) the CRC itself.
            if crc and zlib.crc32(section + tail[: _FOOTER.size - 4]) != crc:
                return schemas, channels
            records = read_records(
                BytesIO(MAGIC + section), validate_crcs=True, record_size_limit=RECORD_SIZE_LIMIT
            )
            for record in records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
        except Exception:  # a damaged summary, whatever the record parser makes of it
            return {}, {}
        finally:
            stream.seek(position)
        return schemas, channels

    def _unreadable_start(self, stream: Any, error: Exception) -> str:
        """Why a file gave no first record: not MCAP at all, or an MCAP file (its magic
        is there) cut short before its header record ended."""
        stream.seek(0)
        if stream.read(len(MAGIC)) != MAGIC:
            return f"{self.path}: not an MCAP file ({error})"
        size = self.report.file_size
        return (
            f"{self.path}: an MCAP file cut short in its header ({size} bytes): no record to read"
        )

    def part(self) -> tuple[int, str] | None:
        """Which file of a rotated log this is (read the messages first): its part number
        (from 1) and the file name of the part before it ("" for the first); None for a log
        that does not say (written before the record existed, or by another tool)."""
        stored = self.report.metadata.get(PART_METADATA)
        if stored is None:
            return None
        number = stored.get("part", "")
        if not number.isdigit() or int(number) < 1:
            raise LogError(f"{self.path}: its {PART_METADATA} part is {number!r}, not a count")
        return int(number), stored.get("previous", "")

    def config(self) -> dict[str, Any]:
        """The service configuration stored in the log, each value decoded (read the
        messages first); StoredConfigError, naming the log and the key, when a value is not
        JSON."""
        decoded, problems = self.config_parts()
        if problems:
            raise problems[0]
        return decoded

    def config_parts(self) -> tuple[dict[str, Any], list[StoredConfigError]]:
        """What can be read of the stored configuration: each value decoded, one that is not
        JSON left as its text; and a StoredConfigError for each of those."""
        decoded: dict[str, Any] = {}
        problems: list[StoredConfigError] = []
        for key, value in self.report.metadata.get(CONFIG_METADATA, {}).items():
            try:
                decoded[key] = json.loads(value)
            except ValueError as error:
                decoded[key] = value
                problems.append(StoredConfigError(key, f"not JSON ({error})", self.path))
        return decoded, problems
