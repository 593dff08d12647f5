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
        lost_at = time.monotonic()
        assert probe.wait_for(
            lambda: health().get("control", {}).get("reason") == "telemetry stale",
            STALE + 3,
        ), health().get("control")
        stale_after = time.monotonic() - lost_at
        commands_while_down = probe.count("glider/1/command/ballast")
        before = health()["identifier"]["depth"]
        time.sleep(1.5)
        assert probe.count("glider/1/command/ballast") == commands_while_down
        assert stale_after < STALE + 2.0

        down_for = time.monotonic() - lost_at
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
    finally:
        probe.close()
        processes.stop_all()

    [log] = (tmp_path / "logs").glob("*.mcap")
    times = [m.log_time_ns / 1e9 for m in LogReader(log).messages({"glider/1/telemetry"})]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) > 0.8 * down_for  # the outage is visible in the log
    assert sorted(gaps)[-2] < 1.0  # and it is the only one


@pytest.mark.timeout(90)
def test_zenoh_router_restart_does_not_stop_mavlink_or_logging(processes, tmp_path):
    zport, udp = free_tcp_port(), free_udp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    router = start_router(endpoint)
    service = None
    stop = threading.Event()
    try:
        time.sleep(1.0)
        service = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-connect", endpoint,
            "--log-dir", str(tmp_path / "logs"),
        )  # fmt: skip
        vehicle = FakeVehicle(udp)

        def stream() -> None:
            k = 0
            while not stop.is_set():
                vehicle.step(k * 1000, depth=15.0 + 0.01 * (k % 100))
                k += 1
                time.sleep(0.02)

        sender = threading.Thread(target=stream, daemon=True)
        sender.start()
        assert first_received(router, time.monotonic() + 15) > 0, "router never heard the service"

        stop_router(router)
        outage_start = time.time()
        time.sleep(3.0)
        outage_end = time.time()
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
    during = [
        m
        for m in LogReader(log).messages({"mavlink/raw/in", "glider/1/telemetry"})
        if outage_start + 0.5 < m.log_time_ns / 1e9 < outage_end - 0.5
    ]
    # 2 s of outage at 50 steps/s: MAVLink decoding and logging went on throughout.
    assert sum(m.topic == "glider/1/telemetry" for m in during) > 50
    assert sum(m.topic == "mavlink/raw/in" for m in during) > 150
    assert summary["counters"]["samples"] > 200
