"""A log whose first chunk (every Schema and Channel record of the data section) is damaged
still gives the messages of every later chunk: ``LogReader`` takes their channels from the
summary section, which repeats those records (docs/mcap.md). Without a readable summary
(a damaged one, or a file cut before it) such messages are counted as lost, as before."""

from __future__ import annotations

import struct
from pathlib import Path

from hil_service.mcap.reader import LogReader, ReadReport
from protocols import keys

PAPER = Path(__file__).parent / "data" / "paper.mcap"
FIRST_CHUNK_BYTE = 2000  # inside the first chunk of paper.mcap, after the metadata
FOOTER_AND_MAGIC = 29 + 8


def _read(path: Path) -> tuple[dict[str, int], ReadReport]:
    reader = LogReader(path)
    counts: dict[str, int] = {}
    for message in reader.messages():
        counts[message.topic] = counts.get(message.topic, 0) + 1
    return counts, reader.report


def _damaged_copy(tmp_path: Path, *offsets: int, cut: int | None = None) -> Path:
    data = bytearray(PAPER.read_bytes())
    for offset in offsets:
        data[offset] ^= 0xFF
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data[:cut]))
    return path


def _summary_start() -> int:
    data = PAPER.read_bytes()
    (start,) = struct.unpack_from("<Q", data, len(data) - FOOTER_AND_MAGIC + 9)
    return start


def test_the_summary_defines_the_channels_a_damaged_first_chunk_held(tmp_path) -> None:
    intact, _ = _read(PAPER)
    counts, report = _read(_damaged_copy(tmp_path, FIRST_CHUNK_BYTE))
    assert report.complete and report.damaged_chunks == 1
    assert int(report.first_damage.rsplit(" ", 1)[-1]) < FIRST_CHUNK_BYTE
    assert report.lost_messages == 0 and report.summary_channels > 0
    telemetry = keys.telemetry(1)
    # Only the damaged chunk's own messages (its first half second) are missing.
    assert 0.9 * intact[telemetry] < counts[telemetry] < intact[telemetry]
    assert set(counts) == set(intact)
    assert sum(counts.values()) == report.messages
    assert report.summary_messages > 0.9 * report.messages
    assert all(report.channels[topic]["schema"] is not None for topic in counts if "json" in topic)
    assert "defined from the summary section" in report.describe()


def test_a_damaged_summary_is_not_used(tmp_path) -> None:
    """A summary that fails its CRC defines nothing: the messages are counted lost."""
    counts, report = _read(_damaged_copy(tmp_path, FIRST_CHUNK_BYTE, _summary_start() + 40))
    assert report.damaged_chunks == 1 and report.summary_channels == 0
    assert report.lost_messages > 0 and keys.telemetry(1) not in counts


def test_a_file_cut_before_its_summary_counts_the_messages_lost(tmp_path) -> None:
    cut = _summary_start() - 100
    _, report = _read(_damaged_copy(tmp_path, FIRST_CHUNK_BYTE, cut=cut))
    assert not report.complete and report.damaged_chunks == 1
    assert report.summary_channels == 0 and report.lost_messages > 0
