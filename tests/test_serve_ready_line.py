"""``serve`` on a listening link given port 0 says, in its ready line, the port the system gave
it, so a vehicle or a script can be pointed at it (the way to run several services without
choosing ports)."""

from __future__ import annotations

import json
import re
import socket
import subprocess

from hil_service.cli.processes import SERVICE_READY, wait_for_line
from tests.conftest import free_tcp_port


def _served_on_port_0(processes, scheme: str) -> tuple[subprocess.Popen[str], int]:
    """``serve`` on ``SCHEME:127.0.0.1:0``, and the port its ready line announces."""
    zenoh = f"tcp/127.0.0.1:{free_tcp_port()}"
    service = processes.start(
        "serve", "--mavlink", f"{scheme}:127.0.0.1:0", "--zenoh-listen", zenoh, "--no-log"
    )
    line = wait_for_line(service, SERVICE_READY)
    match = re.search(rf"ready on {scheme}:127\.0\.0\.1:(\d+),", line)
    assert match, line
    port = int(match.group(1))
    assert port != 0
    return service, port


def test_a_udp_link_on_port_0_is_announced_with_its_port_and_hears_on_it(processes) -> None:
    service, port = _served_on_port_0(processes, "udpin")
    vehicle = processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{port}", "--duration", "20", "--speed", "20"
    )
    out, err = vehicle.communicate(timeout=120)
    assert vehicle.returncode == 0, err
    heard = json.loads(out.strip().splitlines()[-1])["emulator"]
    assert heard["rx_frames"] > 0  # the service answered on the port it announced
    out, _ = processes.stop(service)
    assert json.loads(out.strip().splitlines()[-1])["service"]["counters"]["samples"] > 0


def test_a_tcp_link_on_port_0_is_announced_with_its_port(processes) -> None:
    service, port = _served_on_port_0(processes, "tcpin")
    with socket.create_connection(("127.0.0.1", port), timeout=10):
        pass  # something listens there
    processes.stop(service)
