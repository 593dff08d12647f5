"""Fleets beyond the default vehicle limit, on real processes: ``serve --max-vehicles`` on a
link without a ``--sysid`` list, and two services each taking a range of system ids behind
one Zenoh router, one emulator (``emulate --vehicles N --fleet-connect …``), ``fleet``."""

from __future__ import annotations

import json
import time

import pytest

from hil_service.cli.processes import last_json, run_verb, wait_for_line
from hil_service.cli.router import ROUTER_READY
from hil_service.config import DEFAULT_MAX_VEHICLES, ServiceConfig
from tests.conftest import free_tcp_port, free_udp_port

pytestmark = pytest.mark.wire

VEHICLES = 40  # beyond the default limit of 32
SPEED = 5  # samples/s per vehicle


def fleet_ids(router: str) -> set[int]:
    result = run_verb("fleet", "--zenoh-connect", router, "--json", timeout=60)
    assert result.returncode == 0, result.stderr
    return {row["system_id"] for row in json.loads(result.stdout)["vehicles"]}


def wait_for_fleet(router: str, expected: set[int], timeout: float = 90.0) -> set[int]:
    """What ``fleet`` lists, once it is ``expected`` or ``timeout`` s have passed."""
    deadline = time.monotonic() + timeout
    listed = fleet_ids(router)
    while listed != expected and time.monotonic() < deadline:
        listed = fleet_ids(router)  # each listing takes about a second: no sleep needed
    return listed


def start_router(processes) -> str:
    router = f"tcp/127.0.0.1:{free_tcp_port()}"
    wait_for_line(processes.start("router", "--listen", router), ROUTER_READY, 30)
    return router


def start_emulator(processes, *links: str) -> None:
    processes.start(
        "emulate", "--vehicles", str(VEHICLES), "--sysid", "1", "--speed", str(SPEED),
        "--duration", "100000", "--scenario", "disturbed",
        *[arg for link in links for arg in ("--fleet-connect", link)],
    )  # fmt: skip


def serve(processes, router: str, udp: int, *args: str):
    return processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-connect", router,
        "--zenoh-mode", "client", "--no-log", *args,
    )  # fmt: skip


def test_the_vehicle_limit_is_a_setting_stored_with_the_configuration() -> None:
    assert ServiceConfig().max_vehicles == DEFAULT_MAX_VEHICLES == 32
    stored = ServiceConfig(max_vehicles=200).stored()
    assert stored["service"]["max_vehicles"] == 200
    assert ServiceConfig.from_stored(stored).max_vehicles == 200
    older = ServiceConfig().stored()
    del older["service"]["max_vehicles"]  # a log written before the setting
    assert ServiceConfig.from_stored(older).max_vehicles == 32
    for bad in (0, 256):
        with pytest.raises(ValueError, match="--max-vehicles"):
            ServiceConfig(max_vehicles=bad)
    refused = run_verb("serve", "--max-vehicles", "0", "--no-log", timeout=60)
    assert refused.returncode == 2 and "--max-vehicles must be 1..255" in refused.stderr


def test_max_vehicles_lets_one_open_link_serve_more_than_32(processes) -> None:
    router = start_router(processes)
    udp = free_udp_port()
    service = serve(processes, router, udp, "--max-vehicles", str(VEHICLES))
    start_emulator(processes, f"udpout:127.0.0.1:{udp}")
    expected = set(range(1, VEHICLES + 1))
    assert wait_for_fleet(router, expected) == expected
    out, _ = processes.stop(service)
    counters = last_json(out, "service")["counters"]
    assert counters["unknown_system"] == 0 and counters["samples"] > VEHICLES


def test_two_services_each_take_a_range_and_fleet_lists_both(processes) -> None:
    router = start_router(processes)
    ports = [free_udp_port(), free_udp_port()]
    half = VEHICLES // 2
    ranges = [f"1-{half}", f"{half + 1}-{VEHICLES}"]
    services = [
        serve(processes, router, port, "--sysid", ids)
        for port, ids in zip(ports, ranges, strict=True)
    ]
    # The emulator splits its vehicles in contiguous blocks, one per link: 1-20, 21-40.
    start_emulator(processes, *(f"udpout:127.0.0.1:{port}" for port in ports))
    expected = set(range(1, VEHICLES + 1))
    assert wait_for_fleet(router, expected) == expected
    for service in services:  # each service held its own range, and only it
        out, _ = processes.stop(service)
        summary = last_json(out, "service")
        assert summary["counters"]["unknown_system"] == 0
        assert len(summary["vehicles"]) == half
