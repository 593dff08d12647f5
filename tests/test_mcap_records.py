"""Our in-order MCAP record reader yields what the mcap package's reader yields."""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from hil_service.mcap.records import DamagedChunk, McapFormatError, read_records

DATA = Path(__file__).parent / "data"


def _summary(records) -> list[tuple]:
    """Schemas, channels and messages in order, as comparable tuples."""
    seen = []
    for record in records:
        if isinstance(record, Message):
            seen.append(("m", record.channel_id, record.log_time, record.publish_time, record.data))
        elif isinstance(record, Channel):
            seen.append(("c", record.id, record.topic, record.message_encoding, record.schema_id))
        elif isinstance(record, Schema):
            seen.append(("s", record.id, record.name, record.data))
    return seen


def _first_occurrences(items: list[tuple]) -> list[tuple]:
    """Schemas and channels repeat in the summary: keep messages and first definitions."""
    defined, kept = set(), []
    for item in items:
        if item[0] == "m" or item[:2] not in defined:
            kept.append(item)
            defined.add(item[:2])
    return kept


@pytest.mark.parametrize("name", ["paper", "disturbed", "nonlinear"])
def test_fixtures_read_the_same_as_with_the_mcap_reader(name: str) -> None:
    data = (DATA / f"{name}.mcap").read_bytes()
    ours = _summary(read_records(io.BytesIO(data)))
    theirs = _summary(StreamReader(io.BytesIO(data), validate_crcs=True).records)
    assert _first_occurrences(ours) == _first_occurrences(theirs)
    assert sum(1 for item in ours if item[0] == "m") > 5000


@pytest.mark.parametrize(
    "compression", [CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE]
)
def test_files_of_the_mcap_librarys_writer_are_read(compression: CompressionType) -> None:
    stream = io.BytesIO()
    writer = Writer(stream, compression=compression, chunk_size=2000)
    writer.start()
    schema = writer.register_schema("s", "jsonschema", b"{}")
    channel = writer.register_channel("t", "json", schema)
    for k in range(500):
        writer.add_message(channel, log_time=k, data=b'{"k": %d}' % k, publish_time=k)
    writer.finish()
    records = list(read_records(io.BytesIO(stream.getvalue())))
    messages = [r for r in records if isinstance(r, Message)]
    assert [m.data for m in messages] == [b'{"k": %d}' % k for k in range(500)]


def test_damage_is_named() -> None:
    data = bytearray((DATA / "paper.mcap").read_bytes())
    with pytest.raises(McapFormatError, match="magic"):
        list(read_records(io.BytesIO(b"not an mcap file at all")))
    with pytest.raises(McapFormatError, match="cut short"):
        list(read_records(io.BytesIO(bytes(data[: len(data) // 3]))))
    # Flip a byte inside the first chunk's compressed records.
    first_chunk = data.index(b"zstd") + 20
    data[first_chunk] ^= 0xFF
    # Its record is whole: the chunk is given as damaged, and reading goes on after it.
    records = list(read_records(io.BytesIO(bytes(data))))
    damaged = [r for r in records if isinstance(r, DamagedChunk)]
    assert len(damaged) == 1 and re.search(r"decompress|CRC|holds", damaged[0].reason)
    assert damaged[0].offset < first_chunk and isinstance(records[-1], Footer)
