"""``serve`` on a listening link given port 0 says, in its ready line, the port the system gave
it, so a vehicle or a script can be pointed at it (the way to run several services without
choosing ports)."""

from __future__ import annotations

import json
import re
import socket

from hil_service.cli.processes import SERVICE_READY, wait_for_line
from tests.conftest import free_tcp_port


def test_a_udp_link_on_port_0_is_announced_with_its_port_and_hears_on_it(processes) -> None:
    zenoh = f"tcp/127.0.0.1:{free_tcp_port()}"
    service = processes.start(
        "serve", "--mavlink", "udpin:127.0.0.1:0", "--zenoh-listen", zenoh, "--no-log"
    )
    line = wait_for_line(service, SERVICE_READY)
    match = re.search(r"ready on udpin:127\.0\.0\.1:(\d+),", line)
    assert match, line
    port = int(match.group(1))
    assert port != 0
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
    zenoh = f"tcp/127.0.0.1:{free_tcp_port()}"
    service = processes.start(
        "serve", "--mavlink", "tcpin:127.0.0.1:0", "--zenoh-listen", zenoh, "--no-log"
    )
    line = wait_for_line(service, SERVICE_READY)
    match = re.search(r"ready on tcpin:127\.0\.0\.1:(\d+),", line)
    assert match, line
    with socket.create_connection(("127.0.0.1", int(match.group(1))), timeout=10):
        pass  # something listens there
    processes.stop(service)
