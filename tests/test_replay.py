"""Recorded logs replay through the service path: bit-for-bit checks, timing, damaged files."""

from __future__ import annotations

import itertools
import json
import os

import pytest
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from hil_service.cli import main
from hil_service.mcap.reader import LogReader
from hil_service.offline import replay as replay_module
from protocols import keys
from tests.conftest import DATA

SCENARIOS = ("paper", "disturbed", "nonlinear")


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_fixtures_replay_bit_for_bit(replay_log, scenario):
    result = replay_log(DATA / f"{scenario}.mcap", check=True)
    assert result.mismatch is None, result.mismatch.describe()
    assert result.complete is True
    assert result.samples == 2000
    # Every recorded estimate of both channels and every command, each compared once.
    recorded = sum(1 for m in LogReader(DATA / f"{scenario}.mcap").messages() if _checked(m.topic))
    assert result.compared == recorded


def _checked(topic: str) -> bool:
    """The records ``replay --check`` compares: every estimate and every command."""
    parsed = keys.parse(topic)
    return parsed is not None and parsed.kind in (keys.UMODEL, keys.COMMAND_BALLAST)


def copy_with_changed_estimate(
    source, target, index: int, topic: str = "glider/1/umodel/depth", field: str = "y_hat"
) -> float:
    """Rewrite ``source`` with one byte of ``field`` in the index-th ``topic`` record changed."""
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
                if topics[record.channel_id] == topic:
                    if seen == index:
                        payload = json.loads(data)
                        changed_t = payload["t"]
                        text = data.decode()
                        at = text.index(f'"{field}":') + len(f'"{field}":')
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


def test_check_fails_on_one_changed_command_byte(tmp_path, capsys):
    changed = tmp_path / "changed.mcap"
    t = copy_with_changed_estimate(
        DATA / "paper.mcap", changed, index=600, topic="glider/1/command/ballast", field="u_depth"
    )
    assert main(["replay", "--fast", "--check", str(changed)]) == 1
    err = capsys.readouterr().err
    assert "glider/1/command/ballast" in err
    assert f"message #600 (t = {t:g} s)" in err


def test_truncated_fixture_replays_up_to_the_cut(tmp_path, replay_log):
    data = (DATA / "disturbed.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    result = replay_log(cut, check=True)
    assert result.complete is False
    assert "recovered" in result.recovered
    assert 200 < result.samples < 2000
    assert result.mismatch is None


class SimulatedClock:
    """Stands in for the replay module's ``time``: its clock moves only by ``sleep`` and by
    ``cost`` s per reading (the work done between two readings)."""

    def __init__(self, cost: float = 0.0) -> None:
        self.now = 1000.0
        self.cost = cost
        self.slept = 0.0
        self.calls = 0

    def monotonic(self) -> float:
        self.calls += 1
        self.now += self.cost
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.slept += seconds
        self.now += seconds


def _raw_times_s(path) -> list[float]:
    return sorted(m.log_time_ns / 1e9 for m in LogReader(path).messages({"mavlink/raw/in"}))


def _raw_span_s(path) -> float:
    times = [m.log_time_ns for m in LogReader(path).messages({"mavlink/raw/in"})]
    return (max(times) - min(times)) / 1e9


def _worst_backlog_s(times: list[float], speed: float, per_frame: float) -> float:
    """The worst lateness when each frame costs ``per_frame`` and deadlines are absolute:
    frames logged closer together than they take to replay (a recording made under load
    has such clumps) queue up, and the queue drains in the gaps after them."""
    late = worst = 0.0
    for before, now in itertools.pairwise(times):
        late = max(0.0, late + per_frame - (now - before) / speed)
        worst = max(worst, late)
    return worst


@pytest.mark.parametrize("cost", [0.0, 1e-4])
def test_timed_replay_keeps_its_schedule_and_equals_fast_replay(replay_log, monkeypatch, cost):
    path = DATA / "paper.mcap"
    fast = replay_log(path)
    clock = SimulatedClock(cost)
    monkeypatch.setattr(replay_module, "time", clock)
    timed = replay_log(path, speed=5.0)
    span = _raw_span_s(path) / 5.0
    # Deadlines are absolute: ~9,000 frames' work (0.9 s at 1e-4 s each) does not add up,
    # only the last readings' cost shows.
    assert timed.wall_s == pytest.approx(span, abs=10 * cost + 1e-9)
    assert clock.slept == pytest.approx(span, abs=timed.frames * 2 * cost + 1e-9)
    # Lateness only where frames were logged closer together than they take to replay.
    per_frame = clock.calls * cost / timed.frames
    backlog = _worst_backlog_s(_raw_times_s(path), 5.0, per_frame)
    assert timed.lag_s == pytest.approx(0.0, abs=backlog + 10 * cost + 1e-12)
    assert timed.summary == fast.summary


def test_timed_replay_reports_how_late_it_fell(replay_log, monkeypatch):
    """Work slower than the schedule: replay never sleeps and says how late it is."""
    path = DATA / "paper.mcap"
    clock = SimulatedClock(cost=0.01)  # a reading per frame at least: ≥ 0.01 s per frame
    monkeypatch.setattr(replay_module, "time", clock)
    timed = replay_log(path, speed=100.0)  # the log's frames are ~2 ms apart at 100x
    assert clock.slept == 0.0
    behind = timed.frames * 0.01 - _raw_span_s(path) / 100.0  # 92 s of work for 0.2 s of log
    assert timed.lag_s == pytest.approx(behind, rel=0.01)


def test_info_and_cli_errors(capsys, tmp_path):
    assert main(["info", "--json", str(DATA / "nonlinear.mcap")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["complete"] and info["channels"]["mavlink/raw/in"]["count"] > 8000
    assert info["config"]["service"]["pipeline"]["model"] == "dynamic"
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    assert main(["replay", "--fast", str(junk)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


@pytest.mark.parametrize(
    "verb", [("info",), ("replay", "--fast"), ("report",), ("experiment", "--log")]
)
def test_what_is_not_a_log_file_is_named_for_what_it_is(capsys, tmp_path, verb):
    """A missing path, a directory and a named pipe are refused before they are opened,
    each in one line saying which: a pipe would block the open until a writer came."""
    pipe = tmp_path / "stream.mcap"
    os.mkfifo(pipe)
    cases = (
        (tmp_path / "none.mcap", "no such log"),
        (tmp_path, "a directory, not a log"),
        (pipe, "not a regular file (a pipe or a device"),
    )
    for path, says in cases:
        assert main([*verb, str(path)]) == 2
        err = capsys.readouterr().err
        assert f"{path}: {says}" in err and "Traceback" not in err, err


def test_a_chunk_damaged_inside_is_skipped_and_the_rest_read(capsys, tmp_path):
    from mcap.reader import make_reader

    data = bytearray((DATA / "nonlinear.mcap").read_bytes())
    with open(DATA / "nonlinear.mcap", "rb") as stream:
        summary = make_reader(stream).get_summary()
    chunks = sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)
    middle = chunks[len(chunks) // 2]
    end = middle.chunk_start_offset + middle.chunk_length
    data[end - middle.compressed_size // 2] ^= 0xFF  # inside its compressed records
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    assert main(["info", "--json", str(damaged)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["complete"] and info["damaged_chunks"] == 1
    assert f"at byte {middle.chunk_start_offset}" in info["recovery"]
    times = [m.log_time_ns for m in LogReader(DATA / "nonlinear.mcap").messages()]
    in_middle = sum(middle.message_start_time <= t <= middle.message_end_time for t in times)
    read = sum(c["count"] for c in info["channels"].values())
    assert len(times) - in_middle <= read < len(times)  # only the damaged chunk is lost


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


def test_timed_replay_of_a_log_that_starts_at_time_zero_keeps_its_schedule(tmp_path, monkeypatch):
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
    monkeypatch.setattr(replay_module, "time", SimulatedClock())
    result = replay(path, ReplayOptions(speed=1.0))
    assert result.samples == 3
    # 0.6 s of log at 1x; taking t = 0 for "no start yet" lost the first 0.3 s.
    assert result.wall_s == pytest.approx(0.6)


def test_non_default_units_replay_with_the_units_of_the_log(tmp_path):
    """A log recorded with other units (fresh water, another surface pressure, a smaller
    actuator full scale) replays bit for bit only with the units stored in it."""
    from hil_service.config import ServiceConfig, Units
    from hil_service.inputs import Inbox
    from hil_service.listeners import Notifier
    from hil_service.mcap.recorder import McapRecorder
    from hil_service.offline.replay import ReplayOptions, replay
    from hil_service.pipeline import PipelineSettings
    from hil_service.service import HilService
    from plant_emulator.excitation import RandomSteps
    from plant_emulator.plant import GliderPlant, PlantConfig
    from protocols.mavlink_io import MavlinkCodec

    units = Units(full_scale=1.5, water_density=1000.0, surface_pressure=990.0)
    mapping = units.mapping()
    config = ServiceConfig(control_default=True, pipeline=PipelineSettings(burn_in=50), units=units)
    metadata = config.to_metadata()
    recorder = McapRecorder(tmp_path, metadata=metadata).start()

    # The recorder, the only listener, logs every publication as serve's does.
    service = HilService(config, Notifier(), Inbox(), recorder=recorder)
    service.inbox.set_setpoint(1, "depth", 16.0)
    plant, codec = GliderPlant(PlantConfig(seed=2, input_limit=1.5)), MavlinkCodec(1, 1)
    excitation = RandomSteps(amplitude=1.4, min_hold=5, max_hold=20, seed=2)
    for k in range(150):
        sample = plant.step(excitation.value(k), 0.0)
        for message in mapping.encode_telemetry(sample):
            service.process_datagram(codec.pack(message))
    recorder.close()
    (log,) = tmp_path.glob("*.mcap")
    recorded = [m.json() for m in LogReader(log).messages() if _checked(m.topic)]
    assert any(r.get("u_depth") is not None for r in recorded), "no command was recorded"

    result = replay(log, ReplayOptions(check=True))
    assert result.mismatch is None, result.mismatch.describe()
    assert result.compared == len(recorded)
    # The same log read with the default units is another plant: the check says so.
    bare = tmp_path / "bare"
    bare.mkdir()
    copy_without_units = bare / "log.mcap"
    _copy_metadata_without(log, copy_without_units, "mapping")
    assert replay(copy_without_units, ReplayOptions(check=True)).mismatch is not None


def _copy_metadata_without(source, target, key: str) -> None:
    """``source`` rewritten with ``key`` left out of its stored configuration metadata."""
    with open(source, "rb") as src, open(target, "wb") as out:
        writer = Writer(out)
        writer.start(profile="glider-hil", library="test")
        schema_ids, channel_ids = {0: 0}, {}
        for record in StreamReader(src).records:
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids[record.schema_id],
                    record.metadata,
                )  # fmt: skip
            elif isinstance(record, Metadata):
                writer.add_metadata(
                    record.name, {k: v for k, v in record.metadata.items() if k != key}
                )
            elif isinstance(record, Message):
                writer.add_message(
                    channel_ids[record.channel_id],
                    record.log_time,
                    record.data,
                    record.publish_time,
                )
        writer.finish()


@pytest.mark.wire
@pytest.mark.timeout(90)
def test_replay_publish_and_loop_republish_the_log_on_zenoh(processes):
    """`replay --publish --loop`: the log's telemetry appears on Zenoh, in order, again and
    again (a restart is where the sample time goes back to the log's first)."""
    import socket
    import time

    from tests.conftest import free_tcp_port
    from tests.zenoh_peer import ZenohProbe

    path = DATA / "paper.mcap"
    logged = [m.json() for m in LogReader(path).messages({"glider/1/telemetry"})]
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    replaying = processes.start(
        "replay", str(path), "--speed", "5", "--loop", "--publish", "--zenoh-listen", endpoint
    )  # fmt: skip

    def listening() -> bool:
        with socket.socket() as probe_socket:
            return probe_socket.connect_ex(("127.0.0.1", port)) == 0

    deadline = time.monotonic() + 30
    while not listening():
        assert replaying.poll() is None, replaying.communicate()[1]
        assert time.monotonic() < deadline, "replay never opened its Zenoh endpoint"
        time.sleep(0.05)
    probe = ZenohProbe(endpoint, key="glider/1/telemetry")
    try:

        def restarts() -> list[int]:
            seen = probe.payloads("glider/1/telemetry")
            return [i for i in range(1, len(seen)) if seen[i]["t"] < seen[i - 1]["t"]]

        assert probe.wait_for(lambda: len(restarts()) >= 2, 60), (
            len(restarts()),
            probe.count("glider/1/telemetry"),
        )
    finally:
        probe.close()
        processes.stop(replaying)
    seen = probe.payloads("glider/1/telemetry")
    first, second = restarts()[:2]
    assert seen[first:second] == logged  # one whole pass, every sample, as recorded


def _rewrite(source, target, edit) -> None:
    """``source`` copied to ``target`` with each message's data replaced by
    ``edit(topic, n, data)`` (a list: [] drops it, two entries duplicate it), ``n`` counting
    that topic's messages from 0."""
    with open(source, "rb") as src, open(target, "wb") as out:
        writer = Writer(out)
        writer.start(profile="glider-hil", library="test")
        schema_ids, channel_ids, topics = {0: 0}, {}, {}
        seen: dict[str, int] = {}
        for record in StreamReader(src).records:
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data
                )
            elif isinstance(record, Channel) and record.id not in channel_ids:
                topics[record.id] = record.topic
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids[record.schema_id],
                    record.metadata,
                )  # fmt: skip
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Message):
                topic = topics[record.channel_id]
                n = seen.get(topic, 0)
                seen[topic] = n + 1
                for data in edit(topic, n, record.data):
                    writer.add_message(
                        channel_ids[record.channel_id], record.log_time, data, record.publish_time
                    )
        writer.finish()


def test_a_recorded_estimate_the_replay_does_not_produce_is_named(tmp_path, replay_log):
    changed = tmp_path / "extra.mcap"
    duplicated = {}

    def duplicate(topic, n, data):
        if topic == "glider/1/umodel/depth" and n == 100:
            duplicated["data"] = data
            return [data, data]
        return [data]

    _rewrite(DATA / "paper.mcap", changed, duplicate)
    mismatch = replay_log(changed, check=True).mismatch
    assert mismatch is not None
    assert (mismatch.key, mismatch.index) == ("glider/1/umodel/depth", 101)
    assert mismatch.t == json.loads(duplicated["data"])["t"]
    assert (mismatch.recorded, mismatch.recomputed) == (duplicated["data"].decode(), "<nothing>")


def test_check_compares_values_not_spelling(tmp_path, replay_log):
    """A log written by another JSON encoder (other spacing) checks; a record that is not
    JSON at all is a mismatch."""
    respaced, broken = tmp_path / "respaced.mcap", tmp_path / "broken.mcap"

    def respace(topic, n, data):
        return [json.dumps(json.loads(data), indent=1).encode() if _checked(topic) else data]

    def garble(topic, n, data):
        return [b"not json" if topic == "glider/1/command/ballast" and n == 10 else data]

    _rewrite(DATA / "paper.mcap", respaced, respace)
    result = replay_log(respaced, check=True)
    assert result.mismatch is None, result.mismatch.describe()
    assert result.compared == sum(
        1 for m in LogReader(DATA / "paper.mcap").messages() if _checked(m.topic)
    )
    _rewrite(DATA / "paper.mcap", broken, garble)
    mismatch = replay_log(broken, check=True).mismatch
    assert mismatch is not None
    assert (mismatch.key, mismatch.index, mismatch.recorded) == (
        "glider/1/command/ballast",
        10,
        "not json",
    )


def test_an_estimate_the_log_lacks_is_named(tmp_path, replay_log):
    """The replay publishes one more estimate than the (complete) log recorded."""
    estimates = [m.data for m in LogReader(DATA / "paper.mcap").messages({"glider/1/umodel/pitch"})]
    last = len(estimates) - 1
    shorter = tmp_path / "shorter.mcap"
    _rewrite(
        DATA / "paper.mcap",
        shorter,
        lambda topic, n, data: [] if topic == "glider/1/umodel/pitch" and n == last else [data],
    )
    result = replay_log(shorter, check=True)
    assert result.complete is True
    mismatch = result.mismatch
    assert mismatch is not None
    assert (mismatch.key, mismatch.index, mismatch.recorded) == (
        "glider/1/umodel/pitch",
        last,
        "<not in the log>",
    )
    # What the replay computed is the record that was left out, bit for bit.
    assert mismatch.recomputed == estimates[last].decode()
    assert mismatch.t == json.loads(estimates[last])["t"]


def test_a_periodic_profile_log_replays_with_the_samplers_count(tmp_path):
    """An ArduSub-style dive (each stream every 0.1 s, from a tlog) replays through the
    periodic sampler, and the result counts that sampler's samples (the lockstep assembler
    forms none from such streams)."""
    from hil_service.offline.tlog_import import import_tlog
    from protocols.mavlink_io import MavlinkCodec, dialect
    from protocols.profiles import load_profile

    profile = load_profile("ardusub")
    vehicle = MavlinkCodec(1, 1)
    t0_us, steps, data = 1_700_000_000_000_000, 60, b""
    for k in range(steps):
        ms = 1000 + 100 * k
        hpa = profile.pressure.pressure_hpa(10.0 + 0.01 * k)
        for i, message in enumerate(
            (
                dialect.MAVLink_attitude_message(ms, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0),
                dialect.MAVLink_scaled_pressure2_message(ms, hpa, 0.0, 1500, 0),
                dialect.MAVLink_servo_output_raw_message(ms * 1000, 0, *([1500] * 16)),
            )
        ):
            data += (t0_us + (ms + i) * 1000).to_bytes(8, "big") + vehicle.pack(message)
    tlog = tmp_path / "dive.tlog"
    tlog.write_bytes(data)
    import_tlog(tlog, tmp_path / "dive.mcap", profile)
    result = replay_module.replay(tmp_path / "dive.mcap", replay_module.ReplayOptions())
    assert result.complete
    assert steps - 3 <= result.samples <= steps, result.samples


def test_a_log_of_an_older_identifier_replays_without_the_options_it_dropped(capsys):
    """legacy-paper.mcap stores a model option (``y_scale``) the scale-free identifier no
    longer takes: it replays with this identifier, and ``--check`` names the first
    difference instead of failing on the option."""
    reader = LogReader(DATA / "legacy-paper.mcap")
    for _ in reader.messages():
        pass
    stored = reader.config()
    options = stored["service"]["pipeline"]["model_options"]
    assert options["depth"] == {"y_scale": 1.0}
    assert main(["replay", str(DATA / "legacy-paper.mcap"), "--fast"]) == 0
    assert "replayed 2000 samples" in capsys.readouterr().out
    assert main(["replay", str(DATA / "legacy-paper.mcap"), "--fast", "--check"]) == 1
    assert "first difference on glider/1/umodel/depth" in capsys.readouterr().err


@pytest.mark.parametrize("model", ["paper", "dynamic"])
def test_a_log_replays_with_another_model(replay_log, model):
    # The fixtures were recorded with the input lags chosen from the record, which only the
    # dynamic model has: another model replays without them, the dynamic one keeps them.
    result = replay_log(DATA / "paper.mcap", model=model)
    assert result.complete is True and result.samples == 2000
    identifier = result.summary["vehicles"]["1"]["identifier"]
    for channel in ("depth", "pitch"):
        assert identifier[channel]["model"] == model
        assert (identifier[channel]["input_lag_choice"] is not None) == (model == "dynamic")
