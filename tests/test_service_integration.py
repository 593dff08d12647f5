"""Emulator → service over real UDP, Zenoh on a real loopback endpoint, MCAP on disk."""

from __future__ import annotations

import json
import math
import time

import pytest

from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

SPEED = 50
BURN_IN = 300


@pytest.fixture
def rig(processes, tmp_path):
    """A running service (no control yet) and emulator, and a Zenoh probe connected to both."""
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
        "--log-dir", str(tmp_path / "logs"), "--burn-in", str(BURN_IN),
        "--stale-timeout", "1.0",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    emulator = processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", str(SPEED),
        "--duration", "100000", "--scenario", "disturbed", "--seed", "1",
        "--command-timeout", "5",
    )  # fmt: skip
    rig = {
        "service": service,
        "emulator": emulator,
        "probe": probe,
        "logs": tmp_path / "logs",
        "endpoint": endpoint,
    }
    try:
        yield rig
    finally:
        probe.close()


def test_identify_command_disable_and_stale(rig, processes):
    probe: ZenohProbe = rig["probe"]
    assert probe.wait_for(lambda: probe.count("glider/1/umodel/depth") > BURN_IN + 200, 40), {
        k: len(v) for k, v in probe.received.items()
    }

    # A-priori predictions beat persistence on depth after burn-in.
    estimates = probe.payloads("glider/1/umodel/depth")[BURN_IN:]
    model = sum(e["error"] ** 2 for e in estimates)
    persistence = sum((e["y"] - e["baseline_y_hat"]) ** 2 for e in estimates)
    assert model < persistence, f"model SSE {model:.4g} vs persistence {persistence:.4g}"
    telemetry = probe.payloads("glider/1/telemetry")
    assert {"t", "depth", "pitch", "u_depth", "u_pitch"} <= set(telemetry[-1])
    assert probe.count("glider/1/command/ballast") == 0, "commands before control enabled"

    # Setpoint + enable → commands that reach the emulator and move depth toward the setpoint.
    start_depth = telemetry[-1]["depth"]
    target = start_depth + 2.0
    probe.put("glider/1/setpoint/depth", {"value": target})
    probe.put("glider/1/control", {"enabled": True})
    assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 300, 30)
    commands = probe.payloads("glider/1/command/ballast")
    assert all(c["setpoints"]["depth"] == target for c in commands)
    assert all(c["u_pitch"] is None for c in commands), "pitch had no setpoint"
    # The emulator reports the commanded input back in ACTUATOR_OUTPUT_STATUS → telemetry.
    by_time = {round(s["t"], 3): s for s in probe.payloads("glider/1/telemetry")}
    echoed = [
        by_time[round(c["t"] + 1.0, 3)]["u_depth"] == pytest.approx(c["u_depth"], abs=1e-6)
        for c in commands[-100:]
        if round(c["t"] + 1.0, 3) in by_time
    ]
    assert len(echoed) > 50 and sum(echoed) >= 0.95 * len(echoed)
    recent = [s["depth"] for s in probe.payloads("glider/1/telemetry")[-50:]]
    # Depth has moved toward the setpoint by at least half the step (it may overshoot: the
    # disturbed plant's depth channel is slow and non-minimum-phase, see the README).
    moved = (sum(recent) / len(recent) - start_depth) * math.copysign(1.0, target - start_depth)
    assert moved >= 0.5 * abs(target - start_depth), (start_depth, target, recent[-5:])

    # Disabling control stops the commands.
    probe.put("glider/1/control", {"enabled": False})
    time.sleep(0.5)
    stopped_at = probe.count("glider/1/command/ballast")
    time.sleep(1.5)
    assert probe.count("glider/1/command/ballast") == stopped_at
    assert probe.payloads("glider/1/health")[-1]["control"]["reason"] == "control disabled"

    # Re-enable, then kill the emulator: commands stop and health says telemetry is stale.
    probe.put("glider/1/control", {"enabled": True})
    assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > stopped_at + 20, 10)
    rig["emulator"].kill()
    rig["emulator"].wait(5)
    time.sleep(0.5)
    after_kill = probe.count("glider/1/command/ballast")
    assert probe.wait_for(
        lambda: probe.payloads("glider/1/health")[-1]["control"]["reason"] == "telemetry stale",
        5,
    )
    assert probe.count("glider/1/command/ballast") == after_kill
    health = probe.payloads("glider/1/health")[-1]
    assert health["control"]["commanding"] is False
    assert health["identifier"]["depth"]["converged"] is True

    out, err = processes.stop(rig["service"])
    assert rig["service"].returncode == 0, err
    summary = json.loads(out.strip().splitlines()[-1])["service"]
    assert summary["vehicles"]["1"]["commands_sent"] == after_kill
    check_log(rig["logs"], probe.payloads("glider/1/telemetry"))


def check_log(log_dir, probe_telemetry):
    """Every channel of docs/mcap.md with schemas; raw frames decode to the same samples."""
    from hil_service.assembler import SampleAssembler
    from hil_service.mcap.reader import LogReader
    from protocols.mavlink_io import MavlinkCodec

    files = sorted(log_dir.glob("*.mcap"))
    assert len(files) == 1
    reader = LogReader(files[0])
    raw_in, logged_telemetry = [], []
    for message in reader.messages():
        if message.topic == "mavlink/raw/in":
            raw_in.append(message.data)
        elif message.topic == "glider/1/telemetry":
            logged_telemetry.append(message.json())
    report = reader.report
    assert report.complete, report.describe()
    channels = report.channels
    for topic in ("mavlink/raw/in", "mavlink/raw/out"):
        assert channels[topic]["encoding"] == "mavlink2"
        assert channels[topic]["metadata"]["dialect"] == "common"
    for topic in (
        "mavlink/json/in/ATTITUDE", "mavlink/json/in/SCALED_PRESSURE2", "mavlink/json/in/VFR_HUD",
        "mavlink/json/in/ACTUATOR_OUTPUT_STATUS", "mavlink/json/in/HEARTBEAT",
        "mavlink/json/in/COMMAND_ACK", "mavlink/json/out/COMMAND_LONG",
        "glider/1/telemetry", "glider/1/umodel/depth", "glider/1/umodel/pitch",
        "glider/1/command/ballast", "glider/1/health", "glider/1/setpoint/depth",
        "glider/1/control",
    ):  # fmt: skip
        assert topic in channels, f"no channel {topic}"
        assert channels[topic]["encoding"] == "json"
        assert channels[topic]["schema_encoding"] == "jsonschema", topic
        assert channels[topic]["count"] > 0
    assert "glider-hil.config" in report.metadata
    # Decoding the raw frames again gives exactly the samples the service published.
    codec, assembler = MavlinkCodec(255, 191), SampleAssembler()
    decoded = []
    for frame in raw_in:
        for mav in codec.parse(frame, datagram=True):
            sample = assembler.add(mav)
            if sample is not None:
                decoded.append(sample.to_payload())
    assert decoded == logged_telemetry
    assert decoded[: len(probe_telemetry)] == probe_telemetry[: len(decoded)]
    assert len(decoded) >= len(probe_telemetry) - 5
