"""MAVProxy (from PyPI) routing between the vehicle and the companion: `emulate --profile
ardusub` on MAVProxy's master link, the in-process companion (what `serve --profile ardusub`
will do: tests/ardusub_client.py) on its `--out` link, all on loopback UDP. Identification
and depth/pitch control through DO_SET_SERVO across a µs-clock wrap; the companion's
heartbeat reaches the vehicle through the router; MAVProxy's tlog of the run imports, and
its vehicle frames sample and identify again offline."""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from hil_service.cli.processes import free_port, last_json, start_verb, stop_process
from hil_service.mcap.reader import LogReader
from hil_service.pipeline import PipelineSettings, VehiclePipeline
from hil_service.profile_assembler import ProfileAssembler
from protocols.mavlink_io import MavlinkCodec
from protocols.profiles import load_profile
from tests.ardusub_client import ArduSubClient

MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
PROFILE = load_profile("ardusub")
PERIOD = 0.1
SPEED = 3.0
IDENTIFY = 60.0  # simulated s
CONTROL = 150.0
US32_SPAN = (1 << 32) / 1e6


@pytest.mark.timeout(400)
def test_identify_and_control_through_mavproxy_and_import_its_tlog(tmp_path):
    if not MAVPROXY.exists():
        pytest.fail(f"MAVProxy is a test dependency (pip install -e '.[dev]'): no {MAVPROXY}")
    burn_in = int(0.8 * IDENTIFY / PERIOD)
    client = ArduSubClient(PROFILE, PERIOD, PipelineSettings(burn_in=burn_in))
    master = free_port(socket.SOCK_DGRAM)
    tlog = tmp_path / "router.tlog"
    console = open(tmp_path / "mavproxy.out", "w")  # noqa: SIM115 - closed below
    router = subprocess.Popen(
        [
            sys.executable,
            str(MAVPROXY),
            f"--master=udpin:127.0.0.1:{master}",
            f"--out=udpout:127.0.0.1:{client.port}",
            "--daemon",
            "--non-interactive",
            # A ground station's own stream-rate requests would override the companion's.
            "--streamrate=-1",
            f"--state-basedir={tmp_path}",
            f"--logfile={tlog}",
        ],
        cwd=tmp_path,
        stdin=subprocess.DEVNULL,
        # To a file: an undrained pipe fills up and MAVProxy stops routing when it blocks.
        stdout=console,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "HOME": str(tmp_path)},
    )
    emulator = start_verb(
        "emulate",
        "--profile",
        "ardusub",
        "--connect",
        f"udpout:127.0.0.1:{master}",
        "--speed",
        str(SPEED),
        "--period",
        str(PERIOD),
        "--uptime",
        f"{US32_SPAN - IDENTIFY:.3f}",
        "--excitation",
        "prbs",
        "--seed",
        "3",
        "--command-timeout",
        "5",
        "--fallback",
        "hold",
        "--trim-depth",
        "15",
    )
    emulator_out = router_out = ""
    try:
        client.run(60.0, lambda: set(client.companion.states.values()) == {"accepted"})
        assert set(client.companion.states.values()) == {"accepted"}, client.companion.states
        client.run(0.5)  # the requested rates take effect within a message interval
        steady = len(client.samples)
        # By samples, not wall time: on a loaded machine the emulator runs behind its speed.
        goal = len(client.samples) + round(IDENTIFY / PERIOD)
        client.run(6 * IDENTIFY / SPEED, lambda: len(client.samples) >= goal)
        health = client.pipeline.identifier_health()
        # Better than persistence (the service's own convergence test), through the router.
        assert all(health[ch]["converged"] and health[ch]["skill"] > 0 for ch in health), {
            ch: (h["converged"], h["skill"], h["skipped"]) for ch, h in health.items()
        }
        start = len(client.samples)
        client.setpoints = {"depth": 16.0, "pitch": 0.1}
        goal = start + round(CONTROL / PERIOD)
        client.run(6 * CONTROL / SPEED, lambda: len(client.samples) >= goal)
    finally:
        router.send_signal(signal.SIGTERM)
        try:
            router.wait(timeout=20)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait(timeout=5)
        emulator_out, _ = stop_process(emulator)
        console.close()
        router_out = (tmp_path / "mavproxy.out").read_text(errors="replace")
        client.close()
    samples = client.samples
    measured = samples[steady:]  # once every stream runs at the sample rate
    expected = round((measured[-1].t - measured[0].t) / PERIOD) + 1
    assert len(measured) / expected >= 0.95, (len(measured), expected)
    assert any(b < a for a, b in itertools.pairwise(client.servo_usec)), "no µs wrap seen"
    tail = samples[start + (len(samples) - start) // 2 :]
    depth_error = sum(abs(s.depth - 16.0) for s in tail) / len(tail)
    pitch_error = sum(abs(s.pitch - 0.1) for s in tail) / len(tail)
    print(
        f"\nthrough MAVProxy: {len(measured)}/{expected} samples; skill depth "
        f"{health['depth']['skill']}, pitch {health['pitch']['skill']}; mean |error| depth "
        f"{depth_error:.3f} m, pitch {pitch_error:.5f} rad; blocked {client.decisions_blocked}"
        f"; depth every 3 s of the second half {[round(s.depth, 2) for s in tail[::30]]}"
    )
    # No worse than no control (which leaves the 1 m step's 1 m), pitch on target. The IMC
    # inverse on this 10 Hz profile is erratic on depth (0.66 m in one loaded `make test`, as
    # tests/test_ardusub_link.py measured); issue 15 is where that has to improve.
    assert depth_error < 1.0 and pitch_error < 0.01
    emulator_summary = last_json(emulator_out, "emulator")
    assert emulator_summary["commands_accepted"] >= 0.95 * client.commands_sent > 0
    # The companion's heartbeat reached the vehicle through the router, beside MAVProxy's.
    heartbeats = emulator_summary["gcs"]["heartbeats"]
    assert heartbeats.get("MAV_TYPE_ONBOARD_CONTROLLER", 0) >= 5, heartbeats
    assert heartbeats.get("MAV_TYPE_GCS", 0) >= 5, heartbeats

    # MAVProxy's tlog of the run imports; the companion's frames are `out`.
    assert tlog.exists(), router_out
    log = tmp_path / "router.mcap"
    importer = start_verb("import", str(tlog), "-o", str(log), "--profile", "ardusub", "--json")
    stdout, stderr = importer.communicate(timeout=120)
    report = json.loads(stdout.strip().splitlines()[-1])["import"]
    assert importer.returncode == (0 if report["complete"] else 1), stderr
    assert report["vehicle_system_id"] == 1 and report["frames"]["in"] > 1000
    reader = LogReader(log)
    codec = MavlinkCodec(0, 0)
    assembler = ProfileAssembler(PROFILE, PERIOD)
    pipeline = VehiclePipeline(PipelineSettings(burn_in=burn_in))
    offline = 0
    companions = 0
    for message in reader.messages({"mavlink/raw/in", "mavlink/raw/out"}):
        for decoded in codec.parse(message.data, datagram=True):
            if message.topic.endswith("/out"):
                companions += decoded.get_srcComponent() == 191
                continue
            for sample in assembler.add_all(decoded):
                pipeline.observe(sample)
                offline += 1
    assert reader.config()["profile"]["name"] == "ardusub"
    assert companions > 0  # what the companion sent, as MAVProxy logged it
    # The vehicle's streams as MAVProxy received them sample again, and identify again.
    assert offline >= 0.9 * len(samples)
    assert all(h["skill"] > 0 for h in pipeline.identifier_health().values())
    # And `glider-hil replay` replays the imported log with the profile it stores.
    replayer = start_verb("replay", str(log), "--fast", "--json")
    stdout, stderr = replayer.communicate(timeout=120)
    assert replayer.returncode == 0, stderr
    replayed = json.loads(stdout.strip().splitlines()[-1])
    assert replayed["samples"] >= 0.9 * len(samples)
    identifier = replayed["identifier"]["1"]
    assert all(identifier[ch]["skill"] > 0 for ch in ("depth", "pitch")), identifier
