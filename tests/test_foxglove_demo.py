"""``glider-hil demo --foxglove``: the demo's service serves the live view, and the reference
client (tests/foxglove_client, ``@foxglove/ws-protocol``) sees its telemetry and estimates."""

from __future__ import annotations

import json
import socket
import subprocess
import time

from tests.conftest import free_tcp_port
from tests.test_foxglove_live import _node_client

READY_TIMEOUT = 120.0  # s: the demo starts a service, then an emulator, on a loaded machine


def _wait_for_listener(port: int, process: subprocess.Popen[str], timeout: float) -> None:
    """Until something accepts TCP connections on ``port`` (the service's Foxglove server)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.poll() is None, "the demo ended before its live view opened"
        with socket.socket() as sock:
            sock.settimeout(1.0)
            if sock.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise TimeoutError(f"no live view on port {port} after {timeout:.0f} s")


def test_demo_serves_the_live_view(processes, tmp_path) -> None:
    client = _node_client()
    fox = free_tcp_port()
    demo = processes.start(
        "demo", "--duration", "40", "--speed", "50", "--log-dir", str(tmp_path),
        "--foxglove", f"127.0.0.1:{fox}",
    )  # fmt: skip
    _wait_for_listener(fox, demo, READY_TIMEOUT)
    result = subprocess.run(
        [*client, f"ws://127.0.0.1:{fox}", "20", "60", "telemetry", "umodel"],
        capture_output=True,
        text=True,
        timeout=90,
    )
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["subprotocol"] == "foxglove.sdk.v1"
    assert summary["complete"], summary
    assert summary["kinds"]["telemetry"]["invalid"] == 0 and not summary["errors"], summary
    assert "glider/1/telemetry" in summary["subscribed"]
    out, _ = processes.stop(demo, timeout=60)  # the demo stops its emulator, then its service
    assert f"ws://127.0.0.1:{fox}" in out  # the demo says where the view is
