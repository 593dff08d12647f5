"""A full disk mid-run: the service keeps controlling, says so in health, and logs again
into a new file once space returns. The "full disk" is the running service's file-size
limit (RLIMIT_FSIZE, set from outside with prlimit), so writes really fail with EFBIG."""

from __future__ import annotations

import resource
import sys

import pytest

from hil_service.mcap.reader import LogReader
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="prlimit on another process is Linux-only"
)


@pytest.mark.timeout(90)
def test_disk_full_mid_run_keeps_control_and_logging_resumes(processes, tmp_path):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    logs = tmp_path / "logs"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
        "--log-dir", str(logs), "--burn-in", "100",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)

    def health() -> dict:
        return probe.latest("glider/1/health", {})

    try:
        processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", "50",
            "--duration", "100000", "--scenario", "disturbed", "--seed", "2",
        )  # fmt: skip
        assert probe.wait_for(lambda: probe.count("glider/1/umodel/depth") > 150, 30)
        depth = probe.payloads("glider/1/telemetry")[-1]["depth"]
        probe.put("glider/1/setpoint/depth", {"value": depth - 1.0})
        probe.put("glider/1/control", {"enabled": True})
        assert probe.wait_for(lambda: probe.count("glider/1/command/ballast") > 20, 20)

        # The disk fills up: no file of the service may grow any more.
        _, hard = resource.prlimit(service.pid, resource.RLIMIT_FSIZE)
        resource.prlimit(service.pid, resource.RLIMIT_FSIZE, (1, hard))
        assert probe.wait_for(
            lambda: health().get("logging", {}).get("state") == "failed",
            10,
        ), health().get("logging")
        failed = health()["logging"]
        assert "File too large" in failed["error"] or "EFBIG" in failed["error"], failed
        commands = probe.count("glider/1/command/ballast")
        assert probe.wait_for(
            lambda: probe.count("glider/1/command/ballast") > commands + 30, 20
        ), "control stopped"
        assert probe.wait_for(lambda: health()["logging"]["dropped"] > failed["dropped"], 10)
        assert health()["control"]["reason"] == ""

        # Space again: within the retry period a new file takes the records.
        resource.prlimit(service.pid, resource.RLIMIT_FSIZE, (hard, hard))
        restored_t = probe.payloads("glider/1/telemetry")[-1]["t"]
        assert probe.wait_for(
            lambda: (
                health().get("logging", {}).get("state") == "ok"
                and health()["logging"]["files"] > failed["files"]
            ),
            10,
        ), health().get("logging")
        seen = probe.count("glider/1/telemetry")
        assert probe.wait_for(lambda: probe.count("glider/1/telemetry") > seen + 50, 20)
        last_t = probe.payloads("glider/1/telemetry")[-1]["t"]
    finally:
        probe.close()
        processes.stop_all()
    assert service.returncode == 0
    files = sorted(logs.glob("*.mcap"))
    assert len(files) >= 2
    newest = LogReader(files[-1])
    telemetry = [m for m in newest.messages({"glider/1/telemetry"})]
    assert newest.report.complete
    # The new file holds the samples from about the restoration on (the chunk still open
    # then, at most a flush interval's worth, goes into it too) up to the stop.
    times = [m.json()["t"] for m in telemetry]
    assert times == sorted(times)
    assert times[0] > restored_t - 60 and times[-1] >= last_t
    commands = list(newest.messages({"glider/1/command/ballast"}))
    assert commands, "commands after the disk recovered are missing from the new file"
