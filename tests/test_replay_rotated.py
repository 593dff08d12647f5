"""A log that ``serve`` rotated (``--log-max-mb``, ``--log-max-s``) replays as one run: its
files name their part and the part before them, ``replay`` takes them in order, and
``--check`` refuses to start in the middle instead of failing on the first estimate."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil_service.builder import wire
from hil_service.cli import main
from hil_service.config import ServiceConfig
from hil_service.mcap.reader import LogReader
from hil_service.mcap.recorder import McapRecorder
from hil_service.offline.replay import ReplayInbox
from protocols import keys
from tests.conftest import DATA
from tests.test_recorder import StoppedClock, wait_until


def _rotated_log(directory: Path) -> list[Path]:
    """The disturbed fixture's run logged again by a service whose recorder rotates once,
    half-way: the same frames and decision inputs, in two files."""
    reader = LogReader(DATA / "disturbed.mcap")
    inbox = ReplayInbox()
    frames = []
    for message in reader.messages():
        parsed = keys.parse(message.topic)
        if parsed is not None and parsed.kind == keys.DECISION_INPUTS:
            inbox.add_event(parsed.system_id, message.json())
        elif message.topic == "mavlink/raw/in":
            frames.append(message.data)
    config = ServiceConfig.from_stored(reader.config())
    assert config is not None
    clock = StoppedClock()  # the recorder's clock for max_seconds rotation
    recorder = McapRecorder(
        directory, config.to_metadata(), max_seconds=60.0, flush_interval=0.02, clock=clock
    ).start()
    wired = wire(config, recorder=recorder, inbox=inbox, send_commands=False)
    half = len(frames) // 2
    for frame in frames[:half]:
        wired.service.process_datagram(frame)
    clock.now += 61.0  # the first file is now older than max_seconds: the writer ends it
    assert wait_until(lambda: _one_finished(directory), timeout=20.0), "no rotation"
    for frame in frames[half:]:
        wired.service.process_datagram(frame)
    wired.notifier.stop()
    recorder.close()
    files = [Path(name) for name in recorder.status.files]
    assert len(files) == 2, files
    return files


def _one_finished(directory: Path) -> bool:
    """A file of ``directory`` has its footer: the recorder has ended it."""
    return any(path.stat().st_size and _has_footer(path) for path in directory.glob("*.mcap"))


def _has_footer(path: Path) -> bool:
    reader = LogReader(path)
    for _ in reader.messages():
        pass
    return reader.report.complete


@pytest.fixture(scope="module")
def rotated(tmp_path_factory) -> list[Path]:
    return _rotated_log(tmp_path_factory.mktemp("rotated"))


def test_each_file_names_its_part_and_the_part_before(rotated):
    parts = []
    for path in rotated:
        reader = LogReader(path)
        for _ in reader.messages():
            pass
        parts.append(reader.part())
    assert parts == [(1, ""), (2, rotated[0].name)]


def test_the_parts_in_order_replay_and_check_as_one_run(rotated, capsys):
    code = main(["replay", "--fast", "--check", *map(str, rotated)])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "Traceback" not in err
    whole = main(["replay", "--fast", "--check", str(DATA / "disturbed.mcap")])
    whole_out, _ = capsys.readouterr()
    assert whole == 0
    # The same samples and the same estimates and commands compared as the unrotated log.
    assert out.split(" in ")[0] == whole_out.split(" in ")[0]
    assert out.split("; ")[1] == whole_out.split("; ")[1]


def test_check_from_a_later_part_is_refused_naming_the_part_before(rotated, capsys):
    code = main(["replay", "--fast", "--check", str(rotated[1])])
    _, err = capsys.readouterr()
    assert code == 2
    assert f"is part 2 of a rotated log (it continues {rotated[0].name})" in err
    assert "Traceback" not in err


def test_parts_out_of_order_are_refused(rotated, capsys):
    code = main(["replay", "--fast", str(rotated[1]), str(rotated[0])])
    _, err = capsys.readouterr()
    assert code == 2
    assert f"{rotated[0]} does not continue {rotated[1].name} (it is a first part)" in err


def test_a_later_part_alone_still_replays_without_check(rotated, capsys):
    """Without --check a later part is a log like any other: the service starts afresh."""
    code = main(["replay", "--fast", str(rotated[1])])
    out, _ = capsys.readouterr()
    assert code == 0 and out.startswith("replayed ")
