"""Recorded logs replay through the service path: bit-for-bit checks, timing, damaged files."""

from __future__ import annotations

import json
import time

import pytest
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from hil_service.cli import main
from tests.conftest import DATA

SCENARIOS = ("paper", "disturbed", "nonlinear")


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_fixtures_replay_bit_for_bit(replay_log, scenario):
    result = replay_log(DATA / f"{scenario}.mcap", check=True)
    assert result.mismatch is None, result.mismatch.describe()
    assert result.samples == 2000
    assert result.compared > 4000  # both channels' estimates and the commands


def copy_with_changed_estimate(source, target, index: int) -> float:
    """Rewrite ``source`` with one byte of the index-th depth estimate changed."""
    changed_t = None
    with open(source, "rb") as src, open(target, "wb") as out:
        writer = Writer(out)
        writer.start(profile="glider-hil", library="test")
        seen = 0
        topics, schema_ids, channel_ids = {}, {0: 0}, {}
        for record in StreamReader(src).records:
            # Definitions are repeated in the summary: register each id once, map old to new.
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.id not in channel_ids:
                topics[record.id] = record.topic
                channel_ids[record.id] = writer.register_channel(
                    record.topic,
                    record.message_encoding,
                    schema_ids[record.schema_id],
                    record.metadata,
                )
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Message):
                data = record.data
                if topics[record.channel_id] == "glider/1/umodel/depth":
                    if seen == index:
                        payload = json.loads(data)
                        changed_t = payload["t"]
                        text = data.decode()
                        at = text.index('"y_hat":') + len('"y_hat":')
                        at += len(text[at:]) - len(text[at:].lstrip()) + 3  # a digit of the value
                        digit = "1" if text[at] != "1" else "2"
                        data = (text[:at] + digit + text[at + 1 :]).encode()
                    seen += 1
                writer.add_message(
                    channel_ids[record.channel_id], record.log_time, data, record.publish_time
                )
        writer.finish()
    assert changed_t is not None
    return changed_t


def test_check_fails_naming_the_first_changed_estimate(tmp_path, capsys):
    changed = tmp_path / "changed.mcap"
    t = copy_with_changed_estimate(DATA / "paper.mcap", changed, index=1234)
    assert main(["replay", "--fast", "--check", str(changed)]) == 1
    err = capsys.readouterr().err
    assert "glider/1/umodel/depth" in err
    assert f"message #1234 (t = {t:g} s)" in err
    # The check stopped reading early; the file itself is whole and must not be called damaged.
    assert "not finished" not in err and "recovered" not in err


def test_truncated_fixture_replays_up_to_the_cut(tmp_path, replay_log):
    data = (DATA / "disturbed.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    result = replay_log(cut, check=True)
    assert not result.complete
    assert "recovered" in result.recovered
    assert 200 < result.samples < 2000
    assert result.mismatch is None


def test_timed_replay_keeps_its_schedule_and_equals_fast_replay(replay_log):
    path = DATA / "paper.mcap"
    fast = replay_log(path)
    started = time.monotonic()
    timed = replay_log(path, speed=5.0)
    elapsed = time.monotonic() - started
    log_span = 20.0  # the fixture covers 20 s of wall time (2000 samples at 100x)
    assert elapsed == pytest.approx(log_span / 5.0, abs=0.6)
    assert timed.lag_s < 0.25
    assert timed.summary == fast.summary


def test_info_and_cli_errors(capsys, tmp_path):
    assert main(["info", "--json", str(DATA / "nonlinear.mcap")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["complete"] and info["channels"]["mavlink/raw/in"]["count"] > 8000
    assert info["config"]["service"]["pipeline"]["model"] == "dynamic"
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    assert main(["replay", "--fast", str(junk)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def _log_with(tmp_path, metadata: dict[str, str], raw_frames: list[bytes]):
    """A log written by the service's recorder with the given metadata and raw frames."""
    from hil_service.mcap.recorder import McapRecorder

    recorder = McapRecorder(tmp_path, metadata).start()
    recorder.zenoh("glider/1/telemetry", {"t": 0.0}, "out", t_ns=1)
    for k, frame in enumerate(raw_frames):
        recorder.raw("in", frame, t_ns=2 + k)
    recorder.close()
    (path,) = tmp_path.glob("*.mcap")
    return path


def test_a_log_without_raw_frames_is_refused_clearly(tmp_path, capsys):
    path = _log_with(tmp_path, {"service": "{}"}, [])
    assert main(["replay", "--fast", str(path)]) == 2
    assert "no mavlink/raw/in frames to replay" in capsys.readouterr().err


def test_check_needs_the_stored_configuration(tmp_path, capsys):
    from protocols.mapping import TelemetryMapping
    from protocols.mavlink_io import MavlinkCodec
    from protocols.samples import TelemetrySample

    codec, mapping = MavlinkCodec(1, 1), TelemetryMapping()
    frames = [
        codec.pack(message)
        for k in range(5)
        for message in mapping.encode_telemetry(TelemetrySample(1, 1000 * k, 15.0, 0.0, 0.1, -0.1))
    ]
    path = _log_with(tmp_path, {}, frames)  # no "service" entry: written by another tool
    assert main(["replay", "--fast", "--check", str(path)]) == 2
    assert "no stored configuration, cannot --check" in capsys.readouterr().err
    # Without --check it replays with the default configuration.
    assert main(["replay", "--fast", str(path)]) == 0
    assert "replayed 5 samples" in capsys.readouterr().out


def test_timed_replay_of_a_log_that_starts_at_time_zero_keeps_its_schedule(tmp_path):
    from hil_service.mcap.recorder import McapRecorder
    from hil_service.offline.replay import ReplayOptions, replay
    from protocols.mapping import TelemetryMapping
    from protocols.mavlink_io import MavlinkCodec
    from protocols.samples import TelemetrySample

    codec, mapping = MavlinkCodec(1, 1), TelemetryMapping()
    recorder = McapRecorder(tmp_path, {}).start()
    for k in range(3):  # three plant steps, 0.3 s apart, the first at t = 0
        sample = TelemetrySample(1, 1000 * k, 15.0, 0.0, 0.1, -0.1)
        for message in mapping.encode_telemetry(sample):
            recorder.raw("in", codec.pack(message), t_ns=300_000_000 * k)
    recorder.close()
    (path,) = tmp_path.glob("*.mcap")
    result = replay(path, ReplayOptions(speed=1.0))
    assert result.samples == 3
    # 0.6 s of log at 1x; taking t = 0 for "no start yet" lost the first 0.3 s.
    assert 0.55 <= result.wall_s < 2.0
