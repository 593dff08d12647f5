"""Emulator → service over real UDP, Zenoh on a real loopback endpoint, MCAP on disk."""

from __future__ import annotations

import json

import pytest

from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

#: 25× real time: a 40 ms deadline per sample. At 50× (20 ms) a machine at load 8 delivered
#: commands one to three samples late, a varying dead time no vehicle at 1× sees, and the
#: depth loop oscillated ±1.6 m about the setpoint; the tracking band is the controller's at a
#: deadline it meets.
SPEED = 25
BURN_IN = 300
#: m: |mean of the last 50 depths − setpoint| after ~300 commands of a 2 m step. Measured
#: 1.18 (the disturbed plant's depth is slow and non-minimum-phase and its identified
#: long-horizon map poor, docs/control.md).
TRACK_BAND = 1.5


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
    assert probe.wait_for(lambda: probe.count("glider/1/umodel/depth") > BURN_IN + 400, 90), {
        k: len(v) for k, v in probe.received.items()
    }

    # A-priori predictions over the 400 samples after burn-in: skill versus persistence of
    # at least 0.5 (measured 0.537 here, 0.436 over the first 200; docs/identification.md's
    # 0.8 is over thousands of samples). The data is the emulator's excitation, so this is exact.
    estimates = probe.payloads("glider/1/umodel/depth")[BURN_IN : BURN_IN + 400]
    model = sum(e["error"] ** 2 for e in estimates)
    persistence = sum((e["y"] - e["baseline_y_hat"]) ** 2 for e in estimates)
    skill = 1.0 - model / persistence
    assert skill >= 0.5, f"skill {skill:.3f} (model SSE {model:.4g}, persistence {persistence:.4g})"
    telemetry = probe.payloads("glider/1/telemetry")
    assert {"t", "depth", "pitch", "u_depth", "u_pitch"} <= set(telemetry[-1])
    assert probe.count("glider/1/command/ballast") == 0, "commands before control enabled"

    # Setpoint + enable → commands that reach the emulator and move depth toward the setpoint.
    start_depth = telemetry[-1]["depth"]
    target = start_depth + 2.0
    probe.put("glider/1/setpoint/depth", {"value": target})
    probe.put("glider/1/control", {"enabled": True})
    assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 300, 60)
    commands = probe.payloads("glider/1/command/ballast")
    assert all(c["setpoints"]["depth"] == target for c in commands)
    assert all(c["u_pitch"] is None for c in commands), "pitch had no setpoint"
    # The emulator reports the input it applied back in ACTUATOR_OUTPUT_STATUS → telemetry:
    # each sample carries the newest command that reached it, the one sent after the sample
    # before, or (real-time pacing on a loaded machine) one sent a sample or two earlier.
    sent_at = {round(c["t"], 3): c["u_depth"] for c in commands}
    window = [s for s in probe.payloads("glider/1/telemetry") if s["t"] > commands[-100]["t"]]
    window = [s for s in window if s["t"] <= commands[-1]["t"]]
    echoed = [
        any(
            sent_at.get(round(s["t"] - lag, 3)) == pytest.approx(s["u_depth"], abs=1e-6)
            for lag in (1.0, 2.0, 3.0)
        )
        for s in window
    ]
    sent_when: dict[float, list[float]] = {}
    for c in commands:
        sent_when.setdefault(round(c["u_depth"], 6), []).append(c["t"])
    bad = [
        (s["t"], sent_when.get(round(s["u_depth"], 6)))  # which command's value it carried
        for s, ok in zip(window, echoed, strict=True)
        if not ok
    ]
    assert len(echoed) > 50 and sum(echoed) >= 0.95 * len(echoed), (sum(echoed), len(echoed), bad)
    recent = [s["depth"] for s in probe.payloads("glider/1/telemetry")[-50:]]
    # Tracking band met today (TRACK_BAND): the last 50 samples' mean near the setpoint.
    error = abs(sum(recent) / len(recent) - target)
    assert error <= TRACK_BAND, (error, start_depth, target, recent[-5:])

    # Disabling control stops the commands.
    probe.put("glider/1/control", {"enabled": False})
    assert probe.wait_for(
        lambda: probe.latest("glider/1/health")["control"]["reason"] == "control disabled", 10
    )
    stopped_at = probe.count("glider/1/command/ballast")
    samples = probe.count("glider/1/telemetry")
    # 50 more samples processed (published before any command would be): none commanded.
    assert probe.wait_for(lambda: probe.count("glider/1/telemetry") > samples + 50, 20)
    assert probe.count("glider/1/command/ballast") == stopped_at

    # Re-enable, then kill the emulator: commands stop and health says telemetry is stale.
    probe.put("glider/1/control", {"enabled": True})
    assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > stopped_at + 20, 20)
    rig["emulator"].kill()
    rig["emulator"].wait(5)
    assert probe.wait_for(
        lambda: probe.payloads("glider/1/health")[-1]["control"]["reason"] == "telemetry stale",
        10,
    )
    # Every command is sent with a sample: once stale, the count is final (two more health
    # reports later it has not moved, and the service's own summary agrees below).
    after_kill = probe.count("glider/1/command/ballast")
    reports = probe.count("glider/1/health")
    assert probe.wait_for(lambda: probe.count("glider/1/health") >= reports + 2, 10)
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
    from hil_service.mcap.reader import LogReader
    from hil_service.sources.lockstep_assembler import SampleAssembler
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


@pytest.mark.timeout(120)
def test_a_short_demo_runs_end_to_end(processes, tmp_path):
    """`glider-hil demo`, short: service and emulator start, identify, control, and stop;
    every command sent is acknowledged, and the log it names is a complete MCAP file."""
    from hil_service.mcap.reader import LogReader

    demo = processes.start(
        "demo", "--duration", "12", "--speed", "50", "--log-dir", str(tmp_path), "--json"
    )  # fmt: skip
    out, err = demo.communicate(timeout=110)
    assert demo.returncode == 0, err
    lines = out.splitlines()
    result = json.loads("\n".join(lines[lines.index("{") :]))  # after its progress lines
    assert result["samples"] > 400
    assert result["commands_sent"] > 0
    # The emulator acknowledges every command it received (the last may be in flight).
    acks = result["acks"]
    assert acks["refused"] == 0
    assert result["commands_sent"] - 1 <= acks["accepted"] <= result["commands_sent"]
    assert result["control_reason_at_end"] == ""
    # Better than persistence on both channels (measured 0.56 depth, 0.40 pitch over this
    # short run, control included; docs/identification.md's figures are for
    # the 60 s default).
    for channel in ("depth", "pitch"):
        assert result["identification"][channel]["skill"] >= 0.25, result["identification"]
        # The multi-step fit beside the one-step figures, at the controller's horizon.
        assert result["identification"][channel]["multistep_horizon"] >= 2
        assert -1e3 < result["identification"][channel]["multistep_fit"] <= 100.0
    reader = LogReader(result["log"])
    # The service also sends its heartbeat as the vehicle's companion: count the commands.
    commands = sum(1 for _ in reader.messages({"mavlink/json/out/COMMAND_LONG"}))
    assert reader.report.complete
    assert commands == result["commands_sent"]
