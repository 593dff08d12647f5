"""The MCAP recorder: rotation, flushing, disk trouble, and the reader on damaged files."""

from __future__ import annotations

import struct
import time

import pytest

from hil_service.mcap.reader import LogError, LogReader
from hil_service.mcap.recorder import McapRecorder
from protocols.mavlink_io import MavlinkCodec, dialect


def frames(n: int) -> list[bytes]:
    codec = MavlinkCodec(1, 1)
    return [codec.pack(dialect.MAVLink_attitude_message(k, 0, 0.1, 0, 0, 0, 0)) for k in range(n)]


def read_all(path) -> tuple[list, LogReader]:
    reader = LogReader(path)
    return list(reader.messages()), reader


def test_rotates_by_size_and_every_file_is_complete(tmp_path):
    recorder = McapRecorder(tmp_path, {"k": "1"}, max_bytes=20_000, flush_interval=0.05).start()
    for frame in frames(5000):
        recorder.raw("in", frame)
        time.sleep(0.0001)
    recorder.close()
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) >= 2, "no rotation"
    total = 0
    for path in files:
        messages, reader = read_all(path)
        assert reader.report.complete
        assert reader.report.metadata["glider-hil.config"] == {"k": "1"}
        total += len(messages)
    assert total == 5000 and recorder.status.dropped == 0


class StoppedClock:
    """A monotonic clock that moves only when the test says so."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def wait_until(predicate, timeout: float = 10.0) -> bool:
    """Poll ``predicate`` (the recorder's writer thread works asynchronously)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_unwritable_directory_is_reported_and_recording_resumes(tmp_path):
    # As root a read-only directory is still writable: a file where the directory should be
    # fails for everyone.
    target = tmp_path / "not-a-dir"
    target.write_text("a file where the log directory should be")
    clock = StoppedClock()
    recorder = McapRecorder(target, flush_interval=0.05, clock=clock).start()
    recorder.zenoh("glider/1/telemetry", {"t": 0.0}, "out")
    assert wait_until(lambda: recorder.status.dropped == 1), "the record was not dropped"
    assert "NotADirectoryError" in recorder.status.error or "FileExistsError" in (
        recorder.status.error
    ), recorder.status.error
    # The disk comes back, but the retry interval (2 s) has not passed: still dropped.
    target.unlink()
    recorder.zenoh("glider/1/telemetry", {"t": 1.0}, "out")
    assert wait_until(lambda: recorder.status.dropped == 2)
    assert not target.exists()
    # Two seconds later the next records go to a new file.
    clock.now += 2.0
    recorder.zenoh("glider/1/telemetry", {"t": 2.0}, "out")
    recorder.close()
    files = list(target.glob("*.mcap"))
    assert len(files) == 1
    messages, _ = read_all(files[0])
    assert [m.json() for m in messages] == [{"t": 2.0}]
    assert recorder.status.error == "" and recorder.status.dropped == 2


def test_rotates_by_age_on_the_recorder_clock(tmp_path):
    """``--log-max-s``: a file older than ``max_seconds`` is finished and a new one begun."""
    clock = StoppedClock()
    recorder = McapRecorder(tmp_path, max_seconds=60.0, flush_interval=0.02, clock=clock).start()
    recorder.zenoh("glider/1/telemetry", {"t": 0.0}, "out")
    assert wait_until(lambda: recorder.status.records == 1)
    clock.now += 59.0  # younger than max_seconds: flushes keep the same file
    recorder.zenoh("glider/1/telemetry", {"t": 1.0}, "out")
    assert wait_until(lambda: recorder.status.records == 2)
    assert len(recorder.status.files) == 1
    clock.now += 1.0
    assert wait_until(lambda: len(list(tmp_path.glob("*.mcap"))) == 1 and _finished(tmp_path))
    recorder.zenoh("glider/1/telemetry", {"t": 2.0}, "out")
    recorder.close()
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == 2
    contents = [[m.json()["t"] for m in read_all(path)[0]] for path in files]
    assert sorted(contents) == [[0.0, 1.0], [2.0]]
    for path in files:
        assert read_all(path)[1].report.complete


def _finished(directory) -> bool:
    """The (only) file in ``directory`` has its footer: the recorder closed it."""
    (path,) = directory.glob("*.mcap")
    return read_all(path)[1].report.complete


def _chunk_indexes(path) -> list:
    """The file's chunk indexes (its summary, read by the ``mcap`` library), in file order."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)


def test_reader_reports_truncation_and_corruption_with_offsets(tmp_path):
    # Small chunks sealed by size alone (the timed flush never comes: flush_interval is an
    # hour) and given log times: the same bytes, and the same chunk boundaries, every run.
    recorder = McapRecorder(tmp_path, flush_interval=3600.0, chunk_bytes=16_384).start()
    for k, frame in enumerate(frames(3000)):
        recorder.raw("in", frame, t_ns=k + 1)
    recorder.close()
    path = next(tmp_path.glob("*.mcap"))
    data = path.read_bytes()
    whole, _ = read_all(path)
    assert len(whole) == 3000
    chunks = _chunk_indexes(path)
    assert len(chunks) >= 5

    def before(chunk) -> list[bytes]:
        """The messages of the chunks before ``chunk``."""
        return [m.data for m in whole if m.log_time_ns < chunk.message_start_time]

    # Cut in the middle of the second chunk: the first chunk's messages are recovered.
    second = chunks[1]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: second.chunk_start_offset + second.chunk_length // 2])
    recovered, reader = read_all(cut)
    assert not reader.report.complete
    assert 0 < len(recovered) < len(whole)
    assert [m.data for m in recovered] == before(second)
    assert reader.report.error_offset is not None
    assert reader.report.error_offset <= second.chunk_start_offset
    assert "recovered" in reader.report.describe()

    # One byte flipped inside the middle chunk's compressed records, which end its record
    # (after their length, a u64): that chunk is skipped and counted, every other one read.
    middle = chunks[len(chunks) // 2]
    records = middle.chunk_start_offset + middle.chunk_length - middle.compressed_size
    assert struct.unpack_from("<Q", data, records - 8)[0] == middle.compressed_size
    damaged = bytearray(data)
    damaged[records + middle.compressed_size // 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(damaged))
    recovered, reader = read_all(bad)
    report = reader.report

    def in_middle(message) -> bool:
        return middle.message_start_time <= message.log_time_ns <= middle.message_end_time

    assert any(in_middle(m) for m in whole)
    assert [m.data for m in recovered] == [m.data for m in whole if not in_middle(m)]
    assert report.complete and not report.intact and report.damaged_chunks == 1
    assert f"at byte {middle.chunk_start_offset}" in report.first_damage
    assert "1 damaged chunk(s) skipped" in report.describe()

    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(LogError):
        read_all(junk)


class _Unencodable:
    """A decoded message whose field cannot be JSON-encoded (as a buggy dialect might give)."""

    fieldnames = ("value",)
    fieldtypes = ("float",)
    value = object()
    # What pymavlink's accessors return, read as the codec reads them (mavlink_io.type_of).
    _type = "ATTITUDE"
    _header = dialect.MAVLink_header(30, seq=0, srcSystem=1, srcComponent=1)

    def get_type(self) -> str:
        return self._type

    def get_header(self) -> dialect.MAVLink_header:
        return self._header


def test_an_unencodable_record_is_counted_and_logging_goes_on(tmp_path):
    recorder = McapRecorder(tmp_path, flush_interval=0.05).start()
    recorder.mavlink("in", _Unencodable())
    for frame in frames(10):
        recorder.raw("in", frame)
    recorder.close()
    assert recorder.status.dropped == 1
    assert "TypeError" in recorder.status.last_drop
    assert recorder.status.as_dict()["state"] == "ok"  # a bad record is not a disk failure
    messages, reader = read_all(next(tmp_path.glob("*.mcap")))
    assert reader.report.complete and len(messages) == 10


def test_a_zenoh_payload_json_cannot_hold_is_counted_and_logging_goes_on(tmp_path):
    recorder = McapRecorder(tmp_path, flush_interval=0.05).start()
    recorder.zenoh("glider/1/setpoint/depth", {"value": 10**20}, "in")  # beyond 64 bits
    recorder.zenoh("glider/1/setpoint/depth", {"value": 12.5}, "in")
    recorder.close()
    assert recorder.status.dropped == 1 and "Integer" in recorder.status.last_drop
    messages, reader = read_all(next(tmp_path.glob("*.mcap")))
    assert reader.report.complete and [m.json() for m in messages] == [{"value": 12.5}]


def test_files_open_in_the_mcap_librarys_indexed_reader(tmp_path):
    """Our writer's summary, chunk and message indexes, as another MCAP tool uses them."""
    from mcap.reader import make_reader

    recorder = McapRecorder(tmp_path, {"k": "1"}, flush_interval=0.05).start()
    sent = frames(3000)
    for k, frame in enumerate(sent):
        recorder.raw("in", frame, t_ns=1_000_000 * (k + 1))
        recorder.zenoh("glider/1/telemetry", {"t": float(k)}, "out", t_ns=1_000_000 * (k + 1))
        if k == 1500:
            time.sleep(0.1)  # a flush in the middle: more than one chunk
    recorder.close()
    (path,) = tmp_path.glob("*.mcap")
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics.message_count == 6000
        assert len(summary.chunk_indexes) >= 2
        topics = {channel.topic for channel in summary.channels.values()}
        assert topics == {"mavlink/raw/in", "glider/1/telemetry"}
        raw = [m.data for _, c, m in reader.iter_messages(topics=["mavlink/raw/in"])]
        assert raw == sent
        window = list(reader.iter_messages(starting_at=1_000_000_000, ending_before=1_100_000_000))
        assert len(window) == 2 * 100  # 1000 ms ≤ t < 1100 ms, found through the indexes
        assert {m.name: m.metadata for m in reader.iter_metadata()}["glider-hil.config"] == {
            "k": "1"
        }


def test_a_log_time_of_zero_is_kept_not_replaced_by_the_clock(tmp_path):
    """t_ns = 0 is a time (a log that starts at zero), not "no time given"."""
    recorder = McapRecorder(tmp_path, flush_interval=0.05).start()
    for k, frame in enumerate(frames(3)):
        recorder.raw("in", frame, t_ns=k * 1_000_000)
    recorder.zenoh("glider/1/telemetry", {"t": 0.0}, "out", t_ns=0)
    recorder.close()
    messages, _ = read_all(next(tmp_path.glob("*.mcap")))
    assert sorted(m.log_time_ns for m in messages) == [0, 0, 1_000_000, 2_000_000]


def test_producers_do_not_wait_for_a_stalled_disk(tmp_path, monkeypatch):
    """The control path records while the writer thread is stuck in a write."""
    import threading

    from hil_service.mcap import recorder as recorder_module

    entered, release = threading.Event(), threading.Event()
    original = recorder_module.McapFile.write_chunk

    def stalled(self, sealed):
        entered.set()
        release.wait(10)
        original(self, sealed)

    monkeypatch.setattr(recorder_module.McapFile, "write_chunk", stalled)
    recorder = McapRecorder(tmp_path, flush_interval=0.02).start()
    sent = frames(4000)
    recorder.raw("in", sent[0])
    assert entered.wait(5), "the writer never started a chunk"
    for frame in sent[1:]:
        recorder.raw("in", frame)  # would hang here if producers waited for the writer
    assert recorder.status.records == 0  # the writer is still stuck in its first chunk
    release.set()
    recorder.close()
    messages, reader = read_all(next(tmp_path.glob("*.mcap")))
    assert reader.report.complete
    assert [m.data for m in messages] == sent


def test_after_a_failed_write_the_next_file_defines_its_channels_again(tmp_path, monkeypatch):
    """A lost chunk may have held the channel records: the next file must not need them."""
    from hil_service.mcap import recorder as recorder_module

    original = recorder_module.McapFile.write_chunk
    failures = []

    def failing_once(self, sealed):
        if not failures:
            failures.append(sealed.messages)
            raise OSError(28, "No space left on device")
        original(self, sealed)

    monkeypatch.setattr(recorder_module.McapFile, "write_chunk", failing_once)
    clock = StoppedClock()
    recorder = McapRecorder(tmp_path, flush_interval=0.02, clock=clock).start()
    recorder.raw("in", frames(1)[0])
    recorder.zenoh("glider/1/telemetry", {"t": 0.0}, "out")
    assert wait_until(lambda: recorder.status.dropped == 2)
    assert "No space left" in recorder.status.error
    clock.now += 2.0  # the recorder retries 2 s after a failure
    recorder.raw("in", frames(2)[1])
    recorder.zenoh("glider/1/telemetry", {"t": 1.0}, "out")
    recorder.close()
    newest = max(tmp_path.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
    messages, reader = read_all(newest)
    assert reader.report.complete
    assert {m.topic for m in messages} == {"mavlink/raw/in", "glider/1/telemetry"}
    assert recorder.status.dropped == 2 and recorder.status.records == 2


def test_records_after_close_are_counted_as_dropped(tmp_path):
    recorder = McapRecorder(tmp_path, flush_interval=0.05).start()
    recorder.raw("in", frames(1)[0])
    recorder.close()
    recorder.raw("in", frames(1)[0])
    assert recorder.status.records == 1 and recorder.status.dropped == 1


@pytest.mark.parametrize("size", [8, 12, 20])
def test_a_log_cut_inside_its_header_is_named_as_cut_not_as_another_format(tmp_path, size):
    """The MCAP magic is there, the header record is not whole (or not there at all: the
    magic alone): the file is a cut log."""
    recorder = McapRecorder(tmp_path / "whole", flush_interval=0.05).start()
    for frame in frames(5):
        recorder.raw("in", frame)
    recorder.close()
    (whole,) = (tmp_path / "whole").glob("*.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[:size])
    with pytest.raises(LogError, match=rf"an MCAP file cut short in its header \({size} bytes\)"):
        read_all(cut)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * size)
    with pytest.raises(LogError, match="not an MCAP file"):
        read_all(junk)
