"""The service outlives its peers: the vehicle link dropping and returning, the Zenoh router
going away and coming back. Real processes, real UDP and Zenoh on loopback."""

from __future__ import annotations

import itertools
import json
import threading
import time

import pytest

from hil_service.mcap.reader import LogReader
from tests.conftest import free_tcp_port, free_udp_port
from tests.test_service_robustness import FakeVehicle
from tests.zenoh_peer import ZenohProbe
from tests.zenoh_router import first_received, start_router, stop_router

STALE = 1.0
#: m: the largest one-step depth prediction error over the 30 samples after the link
#: returns (measured 0.65 on this rig, disturbed plant under control; a lost or reset
#: identifier is off by metres).
RECOVERED_ERROR = 1.0


def _emulator(processes, udp: int):
    return processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", "50",
        "--duration", "100000", "--scenario", "disturbed", "--seed", "5",
        "--command-timeout", "5",
    )  # fmt: skip


@pytest.mark.timeout(90)
def test_vehicle_link_lost_and_recovered(processes, tmp_path):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
        "--log-dir", str(tmp_path / "logs"), "--stale-timeout", str(STALE), "--burn-in", "100",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)

    def health() -> dict:
        return probe.latest("glider/1/health", {})

    try:
        first = _emulator(processes, udp)
        assert probe.wait_for(lambda: probe.count("glider/1/umodel/depth") > 150, 30)
        depth = probe.payloads("glider/1/telemetry")[-1]["depth"]
        probe.put("glider/1/setpoint/depth", {"value": depth + 1.0})
        probe.put("glider/1/control", {"enabled": True})
        assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 30, 20)

        processes.stop(first)
        # (When exactly health turns stale is tested on a simulated clock in
        # test_service_robustness; here: that it does, and that nothing is sent meanwhile.)
        assert probe.wait_for(
            lambda: health().get("control", {}).get("reason") == "telemetry stale", 30
        ), health().get("control")
        commands_while_down = probe.count("glider/1/command/ballast")
        before = health()["identifier"]["depth"]
        reports = probe.count("glider/1/health")
        assert probe.wait_for(lambda: probe.count("glider/1/health") >= reports + 2, 10)
        assert probe.count("glider/1/command/ballast") == commands_while_down

        _emulator(processes, udp)  # a rebooted autopilot: its clock starts again at 0
        assert probe.wait_for(
            lambda: probe.count("glider/1/command/ballast") > commands_while_down + 20, 30
        ), health().get("control")
        # The identifier kept what it learnt: no second burn-in, its count carried on.
        assert probe.wait_for(
            lambda: (
                health()["identifier"]["depth"]["samples"] > before["samples"]
                and health()["control"]["reason"] == ""
            ),
            5,
        )
        after = health()
        assert after["identifier"]["depth"]["converged"]
        assert after["counters"]["restarts"] == 1
        # Recovered: the estimates since the return are ordinary ones, and small.
        returned = probe.count("glider/1/umodel/depth")
        assert probe.wait_for(lambda: probe.count("glider/1/umodel/depth") >= returned + 30, 20)
        recent = probe.payloads("glider/1/umodel/depth")[-30:]
        assert all(e["status"] == "ok" for e in recent), [e["status"] for e in recent]
        worst = max(abs(e["error"]) for e in recent)
        assert worst < RECOVERED_ERROR, worst
    finally:
        probe.close()
        processes.stop_all()

    [log] = (tmp_path / "logs").glob("*.mcap")
    records = [
        (m.log_time_ns / 1e9, m.json()["t"])
        for m in LogReader(log).messages({"glider/1/telemetry"})
    ]
    # The outage is in the log where the vehicle's clock restarted, and it is the longest
    # silence there.
    [restart] = [i for i in range(1, len(records)) if records[i][1] < records[i - 1][1]]
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(records)]
    assert gaps.index(max(gaps)) == restart - 1


@pytest.mark.timeout(90)
def test_zenoh_router_restart_does_not_stop_mavlink_or_logging(processes, tmp_path):
    zport, udp = free_tcp_port(), free_udp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    router = start_router(endpoint)
    service = None
    stop = threading.Event()
    try:
        assert router.stdout is not None
        assert router.stdout.readline(), "the router did not start"  # its session is open
        service = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-connect", endpoint,
            "--log-dir", str(tmp_path / "logs"),
        )  # fmt: skip
        vehicle = FakeVehicle(udp)

        sent = [0]  # steps sent so far

        def stream() -> None:
            while not stop.is_set():
                k = sent[0]
                vehicle.step(k * 1000, depth=15.0 + 0.01 * (k % 100))
                sent[0] = k + 1
                time.sleep(0.02)

        sender = threading.Thread(target=stream, daemon=True)
        sender.start()
        assert first_received(router, time.monotonic() + 15) > 0, "router never heard the service"

        stop_router(router)
        outage_from = sent[0]
        time.sleep(3.0)  # the outage (what is asserted is counted in steps, not seconds)
        outage_to = sent[0]
        router = start_router(endpoint)
        assert first_received(router, time.monotonic() + 30) > 0, "publications did not resume"
        assert service.poll() is None
    finally:
        stop.set()
        stop_router(router)
        if service is not None:
            out, _ = processes.stop(service)
    vehicle.close()
    summary = json.loads(out.strip().splitlines()[-1])["service"]
    [log] = (tmp_path / "logs").glob("*.mcap")
    logged = {m.json()["t"] for m in LogReader(log).messages({"glider/1/telemetry"})}
    # Every step the vehicle sent while the router was away was decoded and logged.
    assert outage_to - outage_from > 20
    missing = [k for k in range(outage_from, outage_to) if float(k) not in logged]
    assert missing == []
    assert summary["counters"]["samples"] >= outage_to
