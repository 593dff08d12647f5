"""MAVProxy (from PyPI) as the ground station of `glider-hil emulate --profile ardusub`, on
loopback UDP: read back from its telemetry log, no request is left unanswered; the tlog it
wrote imports into an MCAP log that `glider-hil info` reads."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from hil_service.cli.processes import dies_with_parent, start_verb, stop_process
from hil_service.offline.tlog_import import TlogReport, read_tlog
from hil_service.sources.sampler import SamplerConfig, StreamSampler
from protocols.mavlink_io import MavlinkCodec, dialect
from protocols.profiles import load_profile, message_clock
from tests.conftest import free_udp_port

MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
VEHICLE = 1
#: Messages a ground station sends that are not requests (nothing to answer).
NOT_REQUESTS = {"HEARTBEAT", "SYSTEM_TIME", "RC_CHANNELS_OVERRIDE", "MANUAL_CONTROL"}
#: REQUEST_DATA_STREAM groups → the emulator's messages in them.
GROUPS = {
    dialect.MAV_DATA_STREAM_ALL: {"ATTITUDE", "SCALED_PRESSURE2", "VFR_HUD", "SERVO_OUTPUT_RAW"},
    dialect.MAV_DATA_STREAM_RAW_SENSORS: {"SCALED_PRESSURE2"},
    dialect.MAV_DATA_STREAM_RC_CHANNELS: {"SERVO_OUTPUT_RAW"},
    dialect.MAV_DATA_STREAM_EXTRA1: {"ATTITUDE"},
    dialect.MAV_DATA_STREAM_EXTRA2: {"VFR_HUD"},
}


def decode(path: Path) -> list[tuple[float, object]]:
    """(seconds, message) of every frame in a tlog that decodes."""
    codec = MavlinkCodec(0, 0)
    out = []
    for record in read_tlog(path, TlogReport(str(path))):
        for message in codec.parse(record.frame, datagram=True):
            out.append((record.t_us / 1e6, message))
    return out


def everything_seen(messages: list[tuple[float, object]]) -> bool:
    """MAVProxy has asked for, and been given, each thing this test checks."""
    kinds = Counter(m.get_type() for _, m in messages)
    params = [m for _, m in messages if m.get_type() == "PARAM_VALUE"]
    acks = {m.command for _, m in messages if m.get_type() == "COMMAND_ACK"}
    set_at = [
        t
        for t, p in messages
        if p.get_type() == "PARAM_VALUE" and p.param_id == "SR0_EXTRA2" and p.param_value == 2.0
    ]
    changed = (
        bool(set_at)
        and sum(m.get_type() == "VFR_HUD" and t > set_at[0] + 0.5 for t, m in messages) >= 6
    )
    return (
        bool(params)
        and len({p.param_index for p in params}) >= params[0].param_count
        and kinds["MISSION_COUNT"] > 0
        and kinds["AUTOPILOT_VERSION"] > 0
        # Home: streamed by the vehicle, or answered when MAVProxy asks before it came.
        and (kinds["HOME_POSITION"] > 0 or dialect.MAV_CMD_GET_HOME_POSITION in acks)
        and changed
        and kinds["REQUEST_DATA_STREAM"] > 0
    )


@pytest.fixture(scope="module")
def mavproxy_tlog(tmp_path_factory) -> tuple[Path, dict]:
    """Run MAVProxy against the emulator until it has what it asked for; its tlog."""
    if not MAVPROXY.exists():
        pytest.fail(f"MAVProxy is a test dependency (pip install -e '.[dev]'): no {MAVPROXY}")
    base = tmp_path_factory.mktemp("mavproxy")
    tlog = base / "gcs.tlog"
    port = free_udp_port()
    command = [
        sys.executable,
        str(MAVPROXY),
        f"--master=udpin:127.0.0.1:{port}",
        "--daemon",
        "--non-interactive",
        f"--state-basedir={base}",
        f"--logfile={tlog}",
        "--cmd=repeat add 2 wp list; repeat add 2 version; repeat add 2 param set SR0_EXTRA2 2",
    ]
    console = open(base / "mavproxy.out", "w")  # noqa: SIM115 - closed below
    gcs = subprocess.Popen(
        dies_with_parent(command),
        cwd=base,
        stdin=subprocess.DEVNULL,
        # To a file: an undrained pipe fills up and MAVProxy stops routing when it blocks.
        stdout=console,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "HOME": str(base)},  # no ~/.mavinit.scr of the user's
    )
    emulator = start_verb(
        "emulate",
        "--profile",
        "ardusub",
        "--connect",
        f"udpout:127.0.0.1:{port}",
        "--duration",
        "600",
        "--seed",
        "5",
    )
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            if tlog.exists() and everything_seen(decode(tlog)):
                break
            if gcs.poll() is not None or emulator.poll() is not None:
                break
            time.sleep(0.5)  # polling the file MAVProxy writes; the loop waits for content
    finally:
        # The ground station first: requests it sends to a stopped vehicle go unanswered.
        gcs.send_signal(signal.SIGTERM)
        try:
            gcs.wait(timeout=20)
        except subprocess.TimeoutExpired:
            gcs.kill()
            gcs.wait(timeout=5)
        emulator_out, _ = stop_process(emulator)
        console.close()
        gcs_out = (base / "mavproxy.out").read_text(errors="replace")
    summary = next(
        (
            json.loads(line)["emulator"]
            for line in reversed(emulator_out.splitlines())
            if line.startswith('{"emulator"')
        ),
        {},
    )
    assert tlog.exists(), gcs_out
    assert everything_seen(decode(tlog)), f"MAVProxy did not get everything:\n{gcs_out}"
    return tlog, summary


def answered(request, later: list) -> bool:
    kind = request.get_type()
    from_vehicle = [m for m in later if m.get_srcSystem() == VEHICLE]
    if kind == "COMMAND_LONG":
        return any(
            m.get_type() == "COMMAND_ACK" and m.command == request.command for m in from_vehicle
        )
    if kind == "PARAM_REQUEST_LIST":
        return any(m.get_type() == "PARAM_VALUE" for m in from_vehicle)
    if kind in ("PARAM_REQUEST_READ", "PARAM_SET"):
        name = request.param_id
        return any(m.get_type() == "PARAM_VALUE" and m.param_id == name for m in from_vehicle)
    if kind == "MISSION_REQUEST_LIST":
        return any(
            m.get_type() == "MISSION_COUNT" and m.mission_type == request.mission_type
            for m in from_vehicle
        )
    if kind == "FILE_TRANSFER_PROTOCOL":
        seq = (request.payload[0] | request.payload[1] << 8) + 1
        return any(
            m.get_type() == "FILE_TRANSFER_PROTOCOL"
            and (m.payload[0] | m.payload[1] << 8) == seq & 0xFFFF
            for m in from_vehicle
        )
    if kind == "REQUEST_DATA_STREAM":
        wanted = GROUPS.get(request.req_stream_id, set())
        if not (request.start_stop and request.req_message_rate):
            return True  # a stop: answered by silence
        return any(m.get_type() in wanted for m in from_vehicle)
    if kind == "TIMESYNC":
        return request.tc1 != 0 or any(
            m.get_type() == "TIMESYNC" and m.ts1 == request.ts1 for m in from_vehicle
        )
    raise AssertionError(f"a request this test does not know: {kind}")


def test_mavproxy_leaves_no_request_unanswered(mavproxy_tlog):
    tlog, summary = mavproxy_tlog
    messages = decode(tlog)
    end = messages[-1][0]
    # MAVProxy logs what it sends before the vehicle's first datagram too: on `udpin` it has
    # no peer yet, so those requests reach no one and are not the vehicle's to answer.
    first = next(t for t, m in messages if m.get_srcSystem() == VEHICLE)
    requests = [
        (i, t, m)
        for i, (t, m) in enumerate(messages)
        if m.get_srcSystem() != VEHICLE and m.get_type() not in NOT_REQUESTS and t >= first
    ]
    kinds = Counter(m.get_type() for _, _, m in requests)
    # What MAVProxy asks of an autopilot on its own, and what the test had it ask.
    assert {
        "PARAM_REQUEST_LIST",
        "COMMAND_LONG",
        "MISSION_REQUEST_LIST",
        "PARAM_SET",
        "REQUEST_DATA_STREAM",
    } <= set(kinds), kinds
    unanswered = [
        (round(t - messages[0][0], 2), m.get_type(), getattr(m, "command", None))
        for i, t, m in requests
        if t < end - 1.0 and not answered(m, [later for _, later in messages[i + 1 :]])
    ]
    assert unanswered == []
    # Answered, so not repeated forever: the parameter list was asked for at most twice.
    assert kinds["PARAM_REQUEST_LIST"] <= 2
    params = {m.param_id for _, m in messages if m.get_type() == "PARAM_VALUE"}
    assert {"SR0_EXTRA1", "CMD_TIMEOUT", "SERVO9_MIN"} <= params
    # The emulator saw MAVProxy's heartbeats, as a ground station's.
    assert summary["gcs"]["heartbeats"].get("MAV_TYPE_GCS", 0) > 0
    # The parameter change took effect: VFR_HUD (4 Hz by default) now arrives at 2 Hz.
    set_at = next(
        t
        for t, m in messages
        if m.get_type() == "PARAM_VALUE" and m.param_id == "SR0_EXTRA2" and m.param_value == 2
    )
    hud = [t for t, m in messages if m.get_type() == "VFR_HUD" and t > set_at + 0.5]
    assert len(hud) >= 6
    assert (len(hud) - 1) / (hud[-1] - hud[0]) == pytest.approx(2.0, rel=0.35)


def test_mavproxy_tlog_imports_and_info_reads_it(mavproxy_tlog, tmp_path):
    tlog, _ = mavproxy_tlog
    out = tmp_path / "dive.mcap"
    process = start_verb("import", str(tlog), "-o", str(out), "--profile", "ardusub", "--json")
    stdout, stderr = process.communicate(timeout=120)
    # MAVProxy may be stopped mid-record: then the import reads up to there and exits 1.
    report = json.loads(stdout.strip().splitlines()[-1])["import"]
    assert process.returncode == (0 if report["complete"] else 1), stderr
    assert report["vehicle_system_id"] == VEHICLE
    assert report["frames"]["in"] > 0 and report["frames"]["out"] > 0
    info = start_verb("info", str(out), "--json")
    stdout, stderr = info.communicate(timeout=120)
    assert info.returncode == 0, stderr
    summary = json.loads(stdout)
    channels = summary["channels"]
    assert channels["mavlink/raw/in"]["count"] == report["frames"]["in"]
    assert channels["mavlink/raw/out"]["count"] == report["frames"]["out"]
    assert channels["mavlink/json/in/ATTITUDE"]["schema"] == "mavlink.ATTITUDE"
    assert channels["mavlink/json/out/PARAM_REQUEST_LIST"]["count"] >= 1
    assert summary["config"]["profile"]["name"] == "ardusub"
    assert summary["config"]["profile"]["text"] == load_profile("ardusub").text


def test_mavproxy_tlog_samples_with_the_ardusub_profile(mavproxy_tlog):
    """The vehicle's streams in a real ground station's log form periodic samples."""
    tlog, _ = mavproxy_tlog
    profile = load_profile("ardusub")
    period = 0.25  # the emulator's default rates (4 Hz) without a service asking for more
    sampler = StreamSampler(
        SamplerConfig(period, profile.staleness(period), profile.optional_signals())
    )
    ticks = []
    for _, message in decode(tlog):
        if message.get_srcSystem() == VEHICLE:
            ticks += sampler.observe(profile.readings(message), message_clock(message))
    assert len(ticks) > 10
    assert sampler.counters.samples >= 0.9 * len(ticks), sampler.counters.as_dict()
