"""A log in which the vehicle rebooted: its report covers every segment, and every JSON
channel of it has a JSON Schema that each payload matches."""

from __future__ import annotations

import json
import re
import socket
import time
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners.zenoh import ZenohPublisher
from hil_service.listeners.zenoh_config import ZenohOptions, open_session
from hil_service.mcap.reader import LogReader
from hil_service.mcap.recorder import McapRecorder
from hil_service.offline.report import write_report
from hil_service.service import HilService
from protocols.mavlink_io import Link
from tests.conftest import DATA, free_tcp_port

SOURCE = DATA / "disturbed.mcap"  # a closed-loop run of the emulator, 1 step per second
FIRST_RUN = 800  # samples before the vehicle reboots (control starts after 500)
SECOND_RUN = 300  # samples after it, its clock starting again from 0
SETPOINTS = {"depth": 17.0, "pitch": 0.15}


def _source_frames() -> tuple[list[bytes], dict]:
    reader = LogReader(SOURCE)
    frames = [m.data for m in reader.messages({"mavlink/raw/in"})]
    return frames, reader.config()


def _send_inputs(endpoint: str, inbox: Inbox) -> None:
    """An operator's setpoints and control flag, through Zenoh, until the service has them."""
    operator = open_session(ZenohOptions(connect=(endpoint,)))
    try:
        puts = [(f"glider/1/setpoint/{ch}", {"value": v}) for ch, v in SETPOINTS.items()]
        puts.append(("glider/1/control", {"enabled": True}))
        # Refused inputs first (not JSON, against its schema, outside the limits): kept in
        # the log apart from the setpoint and control channels, whose schemas they fail.
        refused = [
            ("glider/1/setpoint/depth", b"deep"),
            ("glider/1/setpoint/pitch", b'{"value": "steep"}'),
            ("glider/1/control", b'{"enabled": 1}'),
        ]
        for key, raw in refused:
            operator.put(key, raw)
        deadline = time.monotonic() + 10
        while inbox.rejected < len(refused) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert inbox.rejected == len(refused), inbox.last_rejection
        while time.monotonic() < deadline:
            for key, payload in puts:
                operator.put(key, json.dumps(payload))
            inputs = inbox.get(1)
            if inputs.enabled and inputs.setpoints == SETPOINTS:
                return
            time.sleep(0.05)
        raise AssertionError(f"the inputs never arrived: {inbox.get(1)}")
    finally:
        operator.close()


@pytest.fixture(scope="module")
def rebooted_log(tmp_path_factory) -> Path:
    """The live service path (real Zenoh session, real recorder) fed a vehicle that runs
    FIRST_RUN steps, reboots, and runs SECOND_RUN more from time 0."""
    directory = tmp_path_factory.mktemp("rebooted")
    frames, stored = _source_frames()
    config = ServiceConfig.from_stored(stored)
    assert config is not None
    recorder = McapRecorder(
        directory,
        metadata={
            "service": json.dumps(config.to_json()),
            "mapping": json.dumps(stored["mapping"]),
        },
    ).start()
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    session = open_session(ZenohOptions(listen=(endpoint,)))
    inbox = Inbox()
    bus = ZenohPublisher(session, inbox, recorder.on_record)
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # where commands go
    vehicle.bind(("127.0.0.1", 0))
    link = Link(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}")
    wall = [0.0]  # a clock advancing with the data: health every few samples, never stale
    service = HilService(config, bus, inbox, link=link, recorder=recorder, clock=lambda: wall[0])
    try:
        _send_inputs(endpoint, inbox)
        for run in (FIRST_RUN, SECOND_RUN):
            counted = service.source.assembler.counters
            before = counted.samples + counted.out_of_order
            for frame in frames:
                service.process_datagram(frame)
                wall[0] += 0.05
                service.tick()
                counted = service.source.assembler.counters
                if counted.samples + counted.out_of_order - before >= run:
                    break
    finally:
        bus.stop()
        session.close()
        recorder.close()
        link.close()
        vehicle.close()
    assert service.source.assembler.counters.restarts == 1
    [log] = directory.glob("*.mcap")
    return log


def _segments_from_log(log: Path) -> list[dict[str, float]]:
    """Samples and commands per run of the vehicle clock, counted straight from the log."""
    runs: list[dict[str, float]] = []
    last_t = None
    for message in LogReader(log).messages({"glider/1/telemetry", "glider/1/command/ballast"}):
        if message.topic.endswith("telemetry"):
            t = message.json()["t"]
            if last_t is None or t <= last_t:
                runs.append({"samples": 0, "commands": 0, "first_t": t})
            runs[-1]["samples"] += 1
            last_t = t
        else:
            runs[-1]["commands"] += 1
    return runs


def test_report_of_a_rebooted_vehicle_covers_every_segment(rebooted_log, tmp_path):
    runs = _segments_from_log(rebooted_log)
    assert len(runs) == 2 and all(run["commands"] > 0 for run in runs), runs
    report = write_report(rebooted_log, tmp_path)  # IndexError before the fix
    assert sorted(p.name for p in report.figures) == [
        "glider1_depth_control.png",
        "glider1_depth_identification.png",
        "glider1_pitch_control.png",
        "glider1_pitch_identification.png",
    ]
    estimates = {
        ch: sum(1 for _ in LogReader(rebooted_log).messages({f"glider/1/umodel/{ch}"}))
        for ch in ("depth", "pitch")
    }
    # A channel's commands: the command records that set it (a channel held back by its
    # horizon test or supervisor is null in the record while the other channel commands).
    commands = {
        ch: sum(
            1
            for m in LogReader(rebooted_log).messages({"glider/1/command/ballast"})
            if m.json()[f"u_{ch}"] is not None
        )
        for ch in ("depth", "pitch")
    }
    assert all(commands.values()), commands
    for summary in report.summaries:
        assert summary.segments == 2
        assert summary.samples == estimates[summary.channel]  # both segments scored
        assert summary.commands == commands[summary.channel]
        assert summary.tracking_mae is not None
    text = report.markdown.read_text()
    assert "restarted 1 time" in text
    rows = re.findall(r"^\| (\d) \| ([\d.]+) – ([\d.]+) s \| (\d+) \| (\d+) \|$", text, re.M)
    assert [(int(r[3]), int(r[4])) for r in rows] == [
        (run["samples"], run["commands"]) for run in runs
    ]
    assert [float(r[1]) for r in rows] == [run["first_t"] for run in runs]
    assert runs[1]["first_t"] < runs[0]["first_t"] + 5  # the clock did start again


def test_report_tracks_each_command_against_its_own_segment(rebooted_log, tmp_path):
    """Tracking pairs a command with the output of the sample it answered, by position: the
    same time in the other segment would be another sample."""
    expected: dict[str, list[float]] = {"depth": [], "pitch": []}
    outputs: dict[str, dict[float, float]] = {"depth": {}, "pitch": {}}
    topics = {"glider/1/telemetry", "glider/1/umodel/depth", "glider/1/umodel/pitch",
              "glider/1/command/ballast"}  # fmt: skip
    last_t = None
    for message in LogReader(rebooted_log).messages(topics):
        payload = message.json()
        if message.topic.endswith("telemetry"):
            if last_t is not None and payload["t"] <= last_t:
                outputs = {"depth": {}, "pitch": {}}  # a new run: earlier times are gone
            last_t = payload["t"]
        elif "/umodel/" in message.topic:
            outputs[message.topic.rsplit("/", 1)[1]][payload["t"]] = payload["y"]
        else:
            for ch in ("depth", "pitch"):
                y = outputs[ch].get(payload["t"])
                if y is not None:
                    expected[ch].append(abs(y - payload["setpoints"][ch]))
    report = write_report(rebooted_log, tmp_path)
    for summary in report.summaries:
        gaps = expected[summary.channel]
        assert summary.tracking_mae == pytest.approx(sum(gaps) / len(gaps), rel=1e-9)


def test_every_json_channel_has_a_schema_that_its_payloads_match(rebooted_log):
    seen: dict[str, int] = {}
    refused: list[dict] = []
    validators: dict[int, jsonschema.protocols.Validator] = {}
    with open(rebooted_log, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages():
            if channel.message_encoding != "json":
                continue
            assert schema is not None, f"{channel.topic} has no schema"
            assert schema.encoding == "jsonschema", channel.topic
            validator = validators.get(schema.id)
            if validator is None:
                document = json.loads(schema.data)
                cls = jsonschema.validators.validator_for(document)
                cls.check_schema(document)
                validator = validators[schema.id] = cls(document)
            errors = [e.message for e in validator.iter_errors(json.loads(message.data))]
            assert not errors, f"{channel.topic}: {errors[0]}"
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "glider-hil/rejected-inputs":
                refused.append(json.loads(message.data))
    for topic in (
        "glider-hil/1/decision-inputs",
        "glider/1/telemetry",
        "glider/1/umodel/depth",
        "glider/1/command/ballast",
        "glider/1/health",
        "glider/1/setpoint/depth",
        "glider/1/control",
        "glider-hil/rejected-inputs",
        "mavlink/json/in/ATTITUDE",
        "mavlink/json/out/COMMAND_LONG",
    ):
        assert seen.get(topic, 0) > 0, f"no {topic} in the log: {sorted(seen)}"
    assert sorted((r["key"], r["text"]) for r in refused) == [
        ("glider/1/control", '{"enabled": 1}'),
        ("glider/1/setpoint/depth", "deep"),
        ("glider/1/setpoint/pitch", '{"value": "steep"}'),
    ]
    assert all(r["reason"].startswith(r["key"] + ": ") for r in refused), refused
