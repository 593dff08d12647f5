"""MAVProxy (from PyPI) routing between the vehicle and the real service: `emulate --profile
ardusub` on MAVProxy's master link, `glider-hil serve --profile ardusub --sample-period 0.1`
(a process) on its `--out` link, Zenoh on a loopback endpoint. The service asks for its
streams through the router (and again each time MAVProxy lowers them), identifies, and
controls depth and pitch through DO_SET_SERVO across a wrap of the vehicle's µs clock, to
within a tracking band; its heartbeat (1/191) reaches the vehicle; MAVProxy's tlog of the
run imports, and `info`, `report` and `replay --profile ardusub` work on it."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from hil_service.cli.processes import dies_with_parent, last_json, start_verb
from hil_service.mcap.reader import LogReader
from protocols.mavlink_io import dialect
from tests.conftest import free_tcp_port, free_udp_port
from tests.safe_input import TRIM_DEPTH, depth_error_allowed_after_trip
from tests.zenoh_peer import ZenohProbe

MAVPROXY = Path(sys.executable).with_name("mavproxy.py")
PERIOD = 0.1
SPEED = 5.0
BURN_IN = 400  # samples: 40 simulated s of PRBS
CONTROL = 1200  # samples of a depth and pitch step (the horizon test delays depth commanding)
US32_SPAN = (1 << 32) / 1e6  # SERVO_OUTPUT_RAW.time_usec wraps at this uptime (s)
# The vehicle's µs clock wraps this many simulated s after the emulator starts: after the
# identification's 500 samples (at least 50 s, plus the time the stream requests take: ~20 s
# on a loaded machine) and within the control step's 80 s (asserted below), so the step is
# controlled across the wrap, typically within the second half whose error is asserted.
WRAP_AFTER = 130.0
DEPTH_BAND = 0.4  # m, mean |error| over the step's second half
PITCH_BAND = 0.01  # rad (no control leaves 0.1 rad)
STREAMS = {"SCALED_PRESSURE2", "VFR_HUD", "ATTITUDE", "SERVO_OUTPUT_RAW"}


def _mavproxy(tmp_path: Path, master: int, out: int, tlog: Path, *extra: str):
    console = open(tmp_path / "mavproxy.out", "w")  # noqa: SIM115 - closed by _stop_mavproxy
    process = subprocess.Popen(
        dies_with_parent(
            [
                sys.executable,
                str(MAVPROXY),
                f"--master=udpin:127.0.0.1:{master}",
                f"--out=udpout:127.0.0.1:{out}",
                "--daemon",
                "--non-interactive",
                f"--state-basedir={tmp_path}",
                f"--logfile={tlog}",
                *extra,
            ]
        ),
        cwd=tmp_path,
        stdin=subprocess.DEVNULL,
        # To a file: an undrained pipe fills up and MAVProxy stops routing when it blocks.
        stdout=console,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "HOME": str(tmp_path)},
    )
    return process, console


def _stop_mavproxy(process, console) -> None:
    process.send_signal(signal.SIGTERM)
    try:
        process.wait(timeout=20)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=5)
    console.close()


def _run(*args: str, timeout: float = 120) -> tuple[int, str, str]:
    return _run_together(args, timeout=timeout)[0]


def _run_together(*commands: tuple[str, ...], timeout: float = 120) -> list[tuple[int, str, str]]:
    """Run `glider-hil` verbs at the same time; (returncode, stdout, stderr) of each."""
    processes = [start_verb(*args) for args in commands]
    results = []
    try:
        for process in processes:
            stdout, stderr = process.communicate(timeout=timeout)
            results.append((process.returncode, stdout, stderr))
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()
    return results


@pytest.mark.timeout(400)
def test_serve_identifies_and_controls_through_mavproxy_and_its_tlog_imports(processes, tmp_path):
    if not MAVPROXY.exists():
        pytest.fail(f"MAVProxy is a test dependency (pip install -e '.[dev]'): no {MAVPROXY}")
    master, udp, zport = free_udp_port(), free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    tlog = tmp_path / "router.tlog"
    # MAVProxy at its default stream rate: as a ground station it lowers every stream to
    # 4 Hz with REQUEST_DATA_STREAM (at start and every 15 s); the companion notices each
    # stream falling below the rate it asked for and asks again. Started first, so that it
    # starts up while the service does (it routes nothing before the vehicle is there).
    router, console = _mavproxy(tmp_path, master, udp, tlog)
    probe = None
    try:
        service = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
            "--log-dir", str(tmp_path / "logs"), "--burn-in", str(BURN_IN),
            "--profile", "ardusub", "--sample-period", str(PERIOD), "--sysid", "1",
        )  # fmt: skip
        probe = ZenohProbe(endpoint)
        emulator = processes.start(
            "emulate", "--profile", "ardusub", "--connect", f"udpout:127.0.0.1:{master}",
            "--speed", str(SPEED), "--period", str(PERIOD),
            "--uptime", f"{US32_SPAN - WRAP_AFTER:.3f}", "--excitation", "prbs", "--seed", "3",
            "--command-timeout", "5", "--fallback", "hold", "--trim-depth", str(TRIM_DEPTH),
        )  # fmt: skip

        def requests() -> dict:
            health = probe.latest("glider/1/health") or {}
            return (health.get("companion") or {}).get("stream_requests") or {}

        assert probe.wait_for(lambda: set(requests().values()) == {"accepted"}, 90), requests()
        assert set(requests()) == STREAMS
        steady = probe.count("glider/1/telemetry")  # the streams run at the sample rate
        # By samples, not wall time: on a loaded machine the emulator runs behind its speed.
        assert probe.wait_for(lambda: probe.count("glider/1/umodel/depth") > BURN_IN + 100, 120)

        def identified() -> dict:
            return (probe.latest("glider/1/health") or {}).get("identifier") or {}

        # Health is published once a (wall) second, and pitch can be a few samples behind
        # depth (a repeated reading is not learnt from): wait for both to say converged.
        converged = probe.wait_for(
            lambda: all(identified().get(ch, {}).get("converged") for ch in ("depth", "pitch")),
            120,
        )
        health = identified()
        # Better than persistence over the recent window (the service's own convergence
        # test), through the router. Not `skill`: the skill over every sample after burn-in
        # is null until two such samples are in, and a channel converges at burn-in.
        assert converged, health
        assert all(health[ch]["recent_skill"] > 0 for ch in ("depth", "pitch")), health
        start = probe.count("glider/1/telemetry")
        # Telemetry's `t` is the vehicle's uptime (s since boot; no reboot in this run).
        before_wrap = probe.latest("glider/1/telemetry")["t"]
        assert before_wrap < US32_SPAN, f"the µs clock wrapped before control ({before_wrap})"
        probe.put("glider/1/setpoint/depth", {"value": 16.0})
        probe.put("glider/1/setpoint/pitch", {"value": 0.1})
        probe.put("glider/1/control", {"enabled": True})
        assert probe.wait_for(lambda: probe.count("glider/1/telemetry") > start + CONTROL, 180)
        assert probe.wait_for(lambda: probe.latest("glider/1/telemetry")["t"] > US32_SPAN, 60)
        telemetry = probe.payloads("glider/1/telemetry")
        events = probe.payloads("glider/1/supervisor")
        last_health = probe.latest("glider/1/health")
        companion = last_health["companion"]
    finally:
        if probe is not None:
            probe.close()
        _stop_mavproxy(router, console)
    vehicle = last_json(processes.stop(emulator)[0], "emulator")
    out, err = processes.stop(service)
    assert service.returncode == 0, err
    served = json.loads(out.strip().splitlines()[-1])["service"]
    measured = telemetry[steady:]
    times = [s["t"] for s in measured]
    expected = round((times[-1] - times[0]) / PERIOD) + 1
    tail = telemetry[start + CONTROL // 2 : start + CONTROL]
    # The control sample at which the vehicle's µs clock wrapped.
    wrapped_at = next(i for i, s in enumerate(telemetry[start:]) if s["t"] >= US32_SPAN)
    depth_error = sum(abs(s["depth"] - 16.0) for s in tail) / len(tail)
    pitch_error = sum(abs(s["pitch"] - 0.1) for s in tail) / len(tail)
    print(
        f"\nserve through MAVProxy: {len(measured)}/{expected} samples once the streams were "
        f"accepted, streams asked for again {companion['rerequests']} ({companion['slow_streams']}"
        f" found slow); skill depth {health['depth']['skill']:.3f}, pitch "
        f"{health['pitch']['skill']:.3f}; mean |error| depth {depth_error:.3f} m, pitch "
        f"{pitch_error:.5f} rad; µs clock wrapped at control sample {wrapped_at}; control "
        f"{last_health['control']['reason'] or 'commanding'}, "
        f"{served['vehicles']['1']['commands_sent']} commands sent, vehicle fell back "
        f"{vehicle['fallbacks']} times"
    )
    # MAVProxy lowered the streams at least once after they were accepted, the companion
    # asked again, and sampling kept up anyway.
    assert companion["rerequests"].get("rate", 0) >= 1, companion
    assert len(measured) >= 0.95 * expected
    assert all(b > a for a, b in itertools.pairwise(times))
    # Both steps tracked, across the wrap and MAVProxy's lowerings (each costs a second of
    # samples and a refill of the identifier's lags). The depth step starts where the PRBS
    # left the vehicle (11.5-19.2 m in the runs below), often still moving, so the second
    # half can hold the end of an overshoot. Before the plan's cost saw every move
    # (docs/control.md, "Blocks the cost does not see") depth stalled 0.4-1.2 m short for
    # ~550 samples in 3 of 17 runs (CI failed on one, 0.68 m); after, load 2-6: depth
    # 0.002-0.074 m in 8 runs, pitch below 1e-5 rad.
    depth_trips = [e for e in events if e["channel"] == "depth" and e["event"] == "trip"]
    if depth_trips:  # the safe input's bound (tests/safe_input.py)
        allowed = depth_error_allowed_after_trip(telemetry[start]["depth"], 16.0)
        assert depth_error <= allowed, (depth_error, telemetry[start]["depth"], depth_trips)
        assert pitch_error < PITCH_BAND
    else:
        assert depth_error < DEPTH_BAND and pitch_error < PITCH_BAND
    # Commands as DO_SET_SERVO through the router, from the companion's identity.
    assert vehicle["commands_accepted"] >= 0.9 * served["vehicles"]["1"]["commands_sent"] > 0
    assert vehicle["commands_rejected"] == 0
    sources = vehicle["gcs"]["heartbeat_sources"]
    assert sources.get("1/191", 0) >= 5, sources  # the service's heartbeat, through MAVProxy
    ground = sum(n for source, n in sources.items() if source.startswith("255/"))
    assert ground >= 5, sources  # MAVProxy's own, as a ground station

    # MAVProxy's tlog imports: the vehicle's frames `in`, the companion's and MAVProxy's `out`.
    assert tlog.exists(), (tmp_path / "mavproxy.out").read_text(errors="replace")
    log = tmp_path / "router.mcap"
    code, stdout, stderr = _run(
        "import", str(tlog), "-o", str(log), "--profile", "ardusub", "--json"
    )
    report = json.loads(stdout.strip().splitlines()[-1])["import"]
    assert code == (0 if report["complete"] else 1), stderr
    assert report["vehicle_system_id"] == 1 and report["frames"]["in"] > 1000
    reader = LogReader(log)
    servo = [m.json()["time_usec"] for m in reader.messages({"mavlink/json/in/SERVO_OUTPUT_RAW"})]
    assert reader.config()["profile"]["name"] == "ardusub"  # read after the messages
    assert any(b < a for a, b in itertools.pairwise(servo)), "no µs wrap in the run"
    commands = [m.json() for m in reader.messages({"mavlink/json/out/COMMAND_LONG"})]
    servo_senders = {
        (c["_header"]["system_id"], c["_header"]["component_id"])
        for c in commands
        if c["command"] == dialect.MAV_CMD_DO_SET_SERVO
    }
    assert servo_senders == {(1, 191)}  # MAVProxy sends commands of its own, never these
    # `report` and `replay` side by side (each mostly a process starting up). `info` on an
    # imported MAVProxy tlog: tests/test_mavproxy_gcs.py.
    # `report` identifies from the telemetry: the tlog holds none of the service's estimates.
    # `replay --profile ardusub` samples and identifies the vehicle's streams again.
    (code, stdout, stderr), (replay_code, replay_out, replay_err) = _run_together(
        ("report", str(log), "-o", str(tmp_path / "report")),
        ("replay", str(log), "--profile", "ardusub", "--fast", "--json"),
    )
    assert code == 0 and "identified offline" in stdout, stderr
    assert (tmp_path / "report" / "glider1_depth_identification.png").exists()
    code, stdout, stderr = replay_code, replay_out, replay_err
    assert code == 0, stderr
    replayed = json.loads(stdout.strip().splitlines()[-1])
    assert replayed["samples"] >= 0.9 * len(telemetry)
    identifier = replayed["identifier"]["1"]
    assert all(identifier[ch]["skill"] > 0 for ch in ("depth", "pitch")), identifier
