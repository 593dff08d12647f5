"""A fleet over a Zenoh router, on real processes: ``router``, two ``serve`` (one vehicle
each, ``--sysid`` ranges), one emulator per vehicle, a subscriber on the router, ``fleet``."""

from __future__ import annotations

import json
import time

import pytest

from hil_service.cli.processes import run_verb, wait_for_line
from hil_service.cli.router import ROUTER_READY
from hil_service.config import parse_system_ids
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

SPEED = 50
BURN_IN = 300
#: Zenoh's default lease is 10 s: a killed session's tokens go when the router notices.
LIVELINESS_TIMEOUT = 15.0


def test_sysid_ranges() -> None:
    assert parse_system_ids("7") == (7,)
    assert parse_system_ids("1-4") == (1, 2, 3, 4)
    assert parse_system_ids("1-3,9,2") == (1, 2, 3, 9)
    for bad in ("0", "5-2", "1-300", "x", "1-", ""):
        with pytest.raises(ValueError, match="--sysid"):
            parse_system_ids(bad)


def fleet_snapshot(router: str) -> dict[int, dict]:
    result = run_verb("fleet", "--zenoh-connect", router, "--json", timeout=60)
    assert result.returncode == 0, result.stderr
    return {row["system_id"]: row for row in json.loads(result.stdout)["vehicles"]}


def client_config(tmp_path) -> str:
    """A Zenoh client configuration (what joins a router; a peer would wait for gossip)."""
    path = tmp_path / "client.json5"
    scouting = {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    path.write_text(json.dumps({"mode": "client", "scouting": scouting}))
    return str(path)


@pytest.fixture
def fleet_rig(processes, tmp_path):
    router = f"tcp/127.0.0.1:{free_tcp_port()}"
    router_process = processes.start("router", "--listen", router)
    wait_for_line(router_process, ROUTER_READY, 30)
    services = {}
    for sysid in (1, 2):
        udp = free_udp_port()
        services[sysid] = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp}", "--sysid", f"{sysid}-{sysid}",
            "--zenoh-connect", router, "--zenoh-mode", "client", "--no-log",
            "--burn-in", str(BURN_IN),
        )  # fmt: skip
        processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--sysid", str(sysid),
            "--speed", str(SPEED), "--duration", "100000", "--scenario", "disturbed",
            "--seed", str(sysid), "--command-timeout", "5",
        )  # fmt: skip
    probe = ZenohProbe(router, config_file=client_config(tmp_path))
    try:
        yield router, services, probe, processes
    finally:
        probe.close()


def test_two_services_one_router(fleet_rig) -> None:
    router, services, probe, _ = fleet_rig
    # A subscriber on the router sees every vehicle's estimates.
    for sysid in (1, 2):
        for channel in ("depth", "pitch"):
            key = f"glider/{sysid}/umodel/{channel}"
            assert probe.wait_for(lambda key=key: probe.count(key) > 20, 90), key

    # Both vehicles are in the fleet table, each with its health.
    assert probe.wait_for(lambda: probe.count("glider/2/health") > 0, 10)
    rows = fleet_snapshot(router)
    assert set(rows) == {1, 2}, rows
    assert all(rows[s]["link_rate"] and rows[s]["link_rate"] > 0 for s in rows), rows

    # A setpoint for vehicle 2 (held by the second service) reaches it through the router:
    # commands for 2 only, and vehicle 2 applies them (its telemetry echoes the input).
    target = probe.latest("glider/2/telemetry")["depth"] + 2.0
    probe.put("glider/2/setpoint/depth", {"value": target})
    probe.put("glider/2/control", {"enabled": True})
    assert probe.wait_for(lambda: probe.count("glider/2/command/ballast") > 100, 120)
    commands = probe.payloads("glider/2/command/ballast")
    assert all(c["setpoints"]["depth"] == target for c in commands)
    assert probe.count("glider/1/command/ballast") == 0
    by_time = {round(s["t"], 3): s for s in probe.payloads("glider/2/telemetry")}
    echoed = [
        by_time[round(c["t"] + 1.0, 3)]["u_depth"] == pytest.approx(c["u_depth"], abs=1e-6)
        for c in commands[-50:]
        if round(c["t"] + 1.0, 3) in by_time
    ]
    assert echoed and sum(echoed) >= 0.9 * len(echoed), echoed
    rows = fleet_snapshot(router)
    assert rows[2]["last_command"] is not None and rows[1]["last_command"] is None

    # Killing the second service drops vehicle 2 out of the fleet within the lease.
    services[2].kill()
    services[2].wait(10)
    killed_at = time.monotonic()
    while 2 in fleet_snapshot(router):
        assert time.monotonic() - killed_at < LIVELINESS_TIMEOUT, "vehicle 2 still listed"
    assert 1 in fleet_snapshot(router)


def test_an_explicit_sysid_list_is_served_whole() -> None:
    """``--sysid 1-50``: every listed vehicle is assembled, beyond the open-link cap of 32."""
    from hil_service.sources.lockstep_assembler import SampleAssembler
    from plant_emulator.plant import GliderPlant, PlantConfig
    from protocols.mapping import TelemetryMapping
    from protocols.mavlink_io import MavlinkCodec

    mapping = TelemetryMapping()
    listed = SampleAssembler(None, parse_system_ids("1-50"))
    open_link = SampleAssembler()
    reader = MavlinkCodec(255, 0)
    for system_id in range(1, 51):
        sample = GliderPlant(PlantConfig(), system_id=system_id).step(0.0, 0.0)
        codec = MavlinkCodec(system_id, 1)
        for message in mapping.encode_telemetry(sample):
            for parsed in reader.parse(codec.pack(message), datagram=True):
                listed.add(parsed)
                open_link.add(parsed)
    assert listed.counters.samples == 50 and listed.counters.unknown_system == 0
    assert open_link.counters.samples == 32  # the cap still guards a link without a list


def test_the_table_shows_each_served_vehicle() -> None:
    from hil_service.cli.fleet import render

    rows = [
        {
            "system_id": 3,
            "link_rate": 10.0,
            "packet_loss": 0.01,
            "fit": {"depth": 0.72, "pitch": None},
            "control": {"enabled": True, "commanding": True, "reason": ""},
            "last_command": {"u_depth": 0.5, "u_pitch": None},
            "command_age_s": 0.1,
        },
        {
            "system_id": 12,
            "link_rate": None,
            "packet_loss": None,
            "fit": {},
            "control": {"enabled": False, "commanding": False, "reason": "control disabled"},
            "last_command": None,
            "command_age_s": None,
        },
    ]
    lines = render(rows).splitlines()
    assert lines[0] == "glider-hil fleet: 2 vehicles served"
    assert lines[2].split()[:5] == ["3", "10.0", "1.00%", "0.72", "-"]
    assert "commanding" in lines[2] and "0.5, -" in lines[2]
    assert lines[3].split()[0] == "12" and "off: control disabled" in lines[3]
