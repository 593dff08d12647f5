"""A viewer that subscribes to everything and stops reading: the live view's loss is counted
in health (``service_wide.live_viewer_overflows``), and the control path keeps its rate (the
service assembles the emulator's steps and keeps commanding while the viewer is stalled)."""

from __future__ import annotations

from hil_service.cli.processes import last_json
from tests.conftest import free_tcp_port, free_udp_port
from tests.foxglove_stalled import StalledViewer
from tests.zenoh_peer import ZenohProbe

SPEED = 100  # samples/s: about 15 live messages each (publications and MAVLink frames)
BURN_IN = 100
STALLED_SAMPLES = 1000  # samples the service must handle while the viewer is stalled


def _service_wide(probe: ZenohProbe) -> dict[str, int]:
    healths = probe.payloads("glider/1/health")
    return healths[-1]["service_wide"] if healths else {}


def test_stalled_viewer_is_counted_and_control_keeps_its_rate(processes) -> None:
    udp, zport, fox = free_udp_port(), free_tcp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
        "--burn-in", str(BURN_IN), "--control", "--foxglove", f"127.0.0.1:{fox}",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    viewer = None
    try:
        probe.put("glider/1/setpoint/depth", {"value": 17.0})
        emulator = processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", str(SPEED),
            "--duration", "1000000", "--scenario", "paper", "--seed", "3",
        )  # fmt: skip
        assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 0, 90)
        assert probe.wait_for(lambda: "live_offered" in _service_wide(probe), 60)
        before = _service_wide(probe)
        assert before["live_viewer_overflows"] == 0, before  # nobody watches yet
        viewer = StalledViewer("127.0.0.1", fox)
        viewer.subscribe_until("", 6)  # telemetry, estimates, commands, MAVLink frames...
        assert probe.wait_for(
            lambda: _service_wide(probe).get("live_viewer_overflows", 0) >= 1, 120
        ), _service_wide(probe)
        # Stalled from here on: the service keeps assembling and commanding, paced by samples.
        telemetry, commands = (
            probe.count("glider/1/telemetry"),
            probe.count("glider/1/command/ballast"),
        )
        assert probe.wait_for(
            lambda: probe.count("glider/1/telemetry") >= telemetry + STALLED_SAMPLES, 120
        )
        assert probe.count("glider/1/command/ballast") > commands + STALLED_SAMPLES // 2
        counters = _service_wide(probe)
        assert counters["live_sent"] > 0  # a MAVLink entry is sent twice: raw and decoded
        assert counters["live_dropped"] == 0, counters  # our hand-off never fills
        emulator_out, _ = processes.stop(emulator)
    finally:
        if viewer is not None:
            viewer.close()
        probe.close()
    service_out, _ = processes.stop(service)
    steps = last_json(emulator_out, "emulator")["steps"]
    summary = last_json(service_out, "service")
    assert summary["foxglove"]["viewer_overflows"] >= 1
    # Every step the emulator sent was assembled, but for a few datagrams a loaded machine
    # may lose on loopback: the viewer never held the service back.
    assert summary["counters"]["samples"] >= 0.98 * steps, (summary["counters"], steps)
