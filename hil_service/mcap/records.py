"""Reads an MCAP file's records in order, with message records on a fast path.

Why not ``mcap.stream_reader.StreamReader``: it reads every field of every record with a
call of its own and fully parses the message indexes, about 7 µs per logged message,
while ``replay --fast`` has 100 µs for a whole plant step (four raw frames) at its
10,000 steps/s target. Here a record costs one header unpack. A chunk is decompressed
and CRC-checked whole, and each message record inside it costs one ``unpack_from``.
Records that reading in order does not need (message and chunk indexes, statistics,
summary offsets, attachments) are skipped by their length. Headers, schemas, channels,
metadata and the footer are parsed by the ``mcap`` package's own record classes.

Errors in the record stream (bad magic, a record cut short, a length beyond the limit)
raise ``McapFormatError`` naming what was wrong; the caller knows the byte offset and
reports it. A chunk whose contents are damaged (it does not decompress, fails its CRC, or
its records are cut short) while its record is whole is yielded as a ``DamagedChunk`` in
place of its records, and reading goes on with the next record: the chunk's length frames
it, so one damaged chunk loses its own messages, not the rest of the file.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from io import BytesIO
from typing import BinaryIO, NamedTuple

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Footer, Header, McapRecord, Message, Metadata, Schema
from mcap.writer import MCAP0_MAGIC as MAGIC

_RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression length
_U64 = struct.Struct("<Q")

#: Records parsed with the mcap package's classes; every other non-message record is skipped.
_PARSED: dict[int, type[Header] | type[Schema] | type[Channel] | type[Metadata]] = {
    Opcode.HEADER: Header,
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.METADATA: Metadata,
}


class McapFormatError(ValueError):
    """The bytes are not (or no longer) a valid MCAP record stream."""


class DamagedChunk(NamedTuple):
    """A chunk record, whole, whose contents are damaged: what was wrong, where it starts,
    and how many of its messages were read before the damage (a cut inner record)."""

    reason: str
    offset: int
    messages_read: int


def read_records(
    stream: BinaryIO, validate_crcs: bool = True, record_size_limit: int = 1 << 30
) -> Iterator[McapRecord | DamagedChunk]:
    """Header, schemas, channels, metadata, messages (chunked or not) and the footer.

    Ends after the footer, or at the end of the data when there is none (a writer that
    was killed): the caller tells the two apart by whether it saw a ``Footer``.
    """
    if stream.read(len(MAGIC)) != MAGIC:
        raise McapFormatError("no MCAP magic at the start")
    while True:
        start = stream.tell()
        head = stream.read(_RECORD_HEAD.size)
        if not head:
            return
        if len(head) < _RECORD_HEAD.size:
            raise McapFormatError("record header cut short")
        opcode, length = _RECORD_HEAD.unpack(head)
        if length > record_size_limit:
            raise McapFormatError(f"record length {length} beyond the limit {record_size_limit}")
        body = stream.read(length)
        if len(body) < length:
            raise McapFormatError(f"record (opcode {opcode:#x}) cut short")
        if opcode == Opcode.CHUNK:
            messages = 0
            try:
                for record in _chunk_records(body, validate_crcs, record_size_limit):
                    messages += isinstance(record, Message)
                    yield record
            except McapFormatError as error:
                yield DamagedChunk(str(error), start, messages)
        elif opcode == Opcode.MESSAGE:
            yield _message(body, 0, length)
        elif opcode == Opcode.FOOTER:
            yield Footer.read(ReadDataStream(BytesIO(body)))
            if stream.read(len(MAGIC)) != MAGIC:
                raise McapFormatError("no MCAP magic after the footer")
            return
        elif opcode in _PARSED:
            yield _PARSED[opcode].read(ReadDataStream(BytesIO(body)))


def _message(data: bytes, start: int, length: int) -> Message:
    channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(data, start)
    return Message(
        channel_id=channel_id,
        sequence=sequence,
        log_time=log_time,
        publish_time=publish_time,
        data=data[start + _MESSAGE.size : start + length],
    )


def _chunk_records(
    body: bytes, validate_crcs: bool, limit: int
) -> Iterator[McapRecord | DamagedChunk]:
    try:
        _, _, size, crc, name_length = _CHUNK_HEAD.unpack_from(body)
        position = _CHUNK_HEAD.size
        compression = body[position : position + name_length].decode()
        position += name_length
        (records_length,) = _U64.unpack_from(body, position)
    except (struct.error, UnicodeDecodeError) as error:
        raise McapFormatError(f"chunk header damaged ({error})") from error
    position += _U64.size
    compressed = body[position : position + records_length]
    if len(compressed) < records_length or size > limit:
        raise McapFormatError("chunk records cut short or oversized")
    data = _decompress(compression, compressed, size)
    if len(data) != size:
        raise McapFormatError(f"chunk holds {len(data)} bytes, its header says {size}")
    if validate_crcs and crc and zlib.crc32(data) != crc:
        raise McapFormatError("chunk CRC mismatch")
    position, end = 0, len(data)
    while position < end:
        if end - position < _RECORD_HEAD.size:
            raise McapFormatError("record header cut short inside a chunk")
        opcode, length = _RECORD_HEAD.unpack_from(data, position)
        position += _RECORD_HEAD.size
        if position + length > end:
            raise McapFormatError(f"record (opcode {opcode:#x}) cut short inside a chunk")
        if opcode == Opcode.MESSAGE:
            yield _message(data, position, length)
        elif opcode in _PARSED:
            yield _PARSED[opcode].read(ReadDataStream(BytesIO(data[position : position + length])))
        position += length


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    try:
        if compression == "zstd":
            return zstandard.decompress(data, max_output_size=size)
        if compression == "lz4":
            return lz4.frame.decompress(data)
    except (zstandard.ZstdError, RuntimeError) as error:
        raise McapFormatError(f"{compression} chunk does not decompress ({error})") from error
    if compression == "":
        return data
    raise McapFormatError(f"unsupported chunk compression {compression!r}")
