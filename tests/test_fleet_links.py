"""More than 255 gliders on one service: a vehicle is (link, system id), each link (one
``serve --mavlink`` endpoint, a gateway) with a system-id space of its own
(``--vehicle-ids link``, hil_service/vehicle_links.py, docs/fleet.md)."""

from __future__ import annotations

import json
import time

import pytest

from hil_service.cli.processes import last_json, run_verb, wait_for_line
from hil_service.cli.router import ROUTER_READY
from hil_service.config import ServiceConfig
from hil_service.vehicle_links import LinkIdentity, LinkSet
from plant_emulator.fleet import fleet_identities
from protocols import keys
from protocols.mavlink_io import Link, MavlinkCodec, dialect
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe


def test_key_ids_name_a_link_only_when_the_vehicle_id_holds_one() -> None:
    assert keys.vehicle_id(0, 7) == 7 and keys.key_id(7) == "7"
    assert keys.telemetry(7) == "glider/7/telemetry"  # plain system ids: keys as they were
    vehicle = keys.vehicle_id(2, 7)
    assert vehicle == 2 * 256 + 7 and keys.split_vehicle_id(vehicle) == (2, 7)
    assert keys.key_id(vehicle) == "2-7"
    assert keys.setpoint(vehicle, "depth") == "glider/2-7/setpoint/depth"
    assert keys.parse("glider/2-7/setpoint/depth") == keys.ParsedKey(vehicle, "setpoint", "depth")
    assert keys.parse("glider-hil/255-255/decision-inputs").system_id == 255 * 256 + 255
    for bad in ("0-7", "2-0", "02-7", "2-07", "256-7", "2-256", "-7", "2--7", "1-2-7", "2-"):
        assert keys.parse_key_id(bad) is None, bad
        assert keys.parse(f"glider/{bad}/telemetry") is None, bad
    for bad_id in (0, 256, 512, 256 * 256 + 1):
        with pytest.raises(ValueError):
            keys.telemetry(bad_id)
    with pytest.raises(ValueError):
        keys.vehicle_id(1, 0)


def test_the_setting_is_checked_and_stored_only_when_not_the_default() -> None:
    assert "vehicle_ids" not in ServiceConfig().stored()["service"]  # logs as before
    stored = ServiceConfig(vehicle_ids="link", max_vehicles=1000).stored()
    assert stored["service"]["vehicle_ids"] == "link"
    restored = ServiceConfig.from_stored(stored)
    assert restored.vehicle_ids == "link" and restored.max_vehicles == 1000
    with pytest.raises(ValueError, match="--vehicle-ids"):
        ServiceConfig(vehicle_ids="names")
    with pytest.raises(ValueError, match="--sysid"):
        ServiceConfig(vehicle_ids="link", system_ids=(1, 2))
    with pytest.raises(ValueError, match=r"--max-vehicles must be 1\.\.255"):
        ServiceConfig(max_vehicles=1000)  # one id space
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="--health-period"):
            ServiceConfig(health_period=bad)


def _ack(system_id: int) -> object:
    """A vehicle's COMMAND_ACK to its companion, decoded from the wire."""
    codec = MavlinkCodec(system_id, 1)
    message = dialect.MAVLink_command_ack_message(
        dialect.MAV_CMD_DO_SET_SERVO, 0, 0, 0, system_id, 191
    )
    frame = codec.pack(message)
    return MavlinkCodec(255, 191).parse(frame, datagram=True)[0]


def test_link_identity_renumbers_what_comes_in_and_what_goes_out() -> None:
    identity = LinkIdentity()
    message = _ack(7)
    identity.admit([message], (2, ("127.0.0.1", 5000)))
    vehicle = keys.vehicle_id(2, 7)
    assert message.get_srcSystem() == vehicle and message.target_system == vehicle
    unlinked = _ack(7)
    identity.admit([unlinked], None)  # no link number: left alone, counted
    assert unlinked.get_srcSystem() == 7 and identity.unlinked == 1
    command = dialect.MAVLink_command_long_message(
        vehicle, 1, dialect.MAV_CMD_DO_SET_SERVO, 0, 9, 1500, 0, 0, 0, 0, 0
    )
    assert identity.outgoing(command, vehicle) == 7 and command.target_system == 7
    frame = MavlinkCodec(7, 191).pack(command)  # packs: the wire ids are bytes again
    assert MavlinkCodec(255, 0).parse(frame, datagram=True)[0].target_system == 7


def test_a_link_set_answers_each_peer_on_its_own_link() -> None:
    ports = [free_udp_port(), free_udp_port()]
    links = LinkSet([f"udpin:127.0.0.1:{port}" for port in ports])
    peers = [Link(f"udpout:127.0.0.1:{port}") for port in ports]
    try:
        for n, peer in enumerate(peers):
            peer.send(b"from %d" % n)
        got = {}
        deadline = time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            if links.wait(0.5):
                data, address = links.recv_from()
                if data:
                    got[data] = address
        assert sorted(address[0] for address in got.values()) == [1, 2]
        for data, address in got.items():
            links.send_to(b"reply to " + data, address)
        for n, peer in enumerate(peers):
            assert peer.wait(5)
            assert peer.recv() == b"reply to from %d" % n
        # A burst on one link is read after one wait, datagram by datagram, then nothing.
        for n in range(3):
            peers[1].send(b"burst %d" % n)
        assert links.wait(5)
        burst = []
        deadline = time.monotonic() + 5
        while len(burst) < 3 and time.monotonic() < deadline:
            data, address = links.recv_from()
            if data:
                burst.append((data, address[0]))
            else:
                links.wait(0.5)
        assert burst == [(b"burst %d" % n, 2) for n in range(3)]
        assert links.recv_from() == (b"", None) and not links.wait(0.0)
    finally:
        links.close()
        for peer in peers:
            peer.close()
    with pytest.raises(ValueError, match="UDP"):
        LinkSet([f"udpin:127.0.0.1:{free_udp_port()}", f"tcpin:127.0.0.1:{free_tcp_port()}"])


def test_the_emulator_numbers_each_link_from_the_first_id_again() -> None:
    assert fleet_identities(4, 1, 2, per_link=False) == [(1, 1), (1, 2), (2, 3), (2, 4)]
    assert fleet_identities(4, 1, 2, per_link=True) == [(1, 1), (1, 2), (2, 1), (2, 2)]
    per_link = fleet_identities(1000, 1, 4, per_link=True)
    assert max(s for _, s in per_link) == 250 and len(set(per_link)) == 1000


LINKS = 2
PER_LINK = 150  # 300 vehicles: beyond one link's 255 system ids
SPEED = 2  # samples/s per vehicle: 600 samples/s on the service
STEPS = 100


@pytest.mark.wire
def test_more_than_255_vehicles_over_two_links_on_one_service(processes) -> None:
    router = f"tcp/127.0.0.1:{free_tcp_port()}"
    wait_for_line(processes.start("router", "--listen", router), ROUTER_READY, 30)
    ports = [free_udp_port() for _ in range(LINKS)]
    service = processes.start_service(
        *[arg for port in ports for arg in ("--mavlink", f"udpin:127.0.0.1:{port}")],
        "--vehicle-ids", "link", "--max-vehicles", str(LINKS * PER_LINK),
        "--zenoh-connect", router, "--zenoh-mode", "client", "--no-log",
        "--control", "--burn-in", "8",
    )  # fmt: skip
    vehicles = [keys.vehicle_id(link, s) for link in (1, 2) for s in range(1, PER_LINK + 1)]
    probe = ZenohProbe(router, key=f"{keys.ROOT}/*/{keys.COMMAND_BALLAST}")
    try:
        for vehicle in vehicles:
            probe.put(keys.setpoint(vehicle, "depth"), {"value": 12.0})
        emulator = processes.start(
            "emulate", "--vehicles", str(LINKS * PER_LINK), "--sysid", "1", "--sysid-per-link",
            "--speed", str(SPEED), "--duration", str(STEPS), "--scenario", "paper",
            *[arg for port in ports for arg in ("--fleet-connect", f"udpout:127.0.0.1:{port}")],
        )  # fmt: skip
        started = time.monotonic()
        emulated_out, emulated_err = emulator.communicate(timeout=STEPS / SPEED * 4 + 120)
        wall = time.monotonic() - started
        emulated = last_json(emulated_out, "emulator")
        assert emulated, emulated_err[-2000:]
        listed = run_verb("fleet", "--zenoh-connect", router, "--json", timeout=120)
        assert listed.returncode == 0, listed.stderr
        rows = json.loads(listed.stdout)["vehicles"]
        commanded_on_zenoh = {
            k: probe.count(k) for k in (keys.command_ballast(v) for v in vehicles)
        }
    finally:
        probe.close()
    out, _ = processes.stop(service)
    summary = last_json(out, "service")
    # Every vehicle identified: fleet lists all 300, each by link and system id.
    assert {row["vehicle"] for row in rows} == {keys.key_id(v) for v in vehicles}
    assert {(row["link"], row["system_id"]) for row in rows} == {
        keys.split_vehicle_id(v) for v in vehicles
    }
    assert set(summary["vehicles"]) == {str(v) for v in vehicles}
    assert summary["counters"]["unknown_system"] == 0
    # Every vehicle answered on its own link: its companion's heartbeats (system id, 191)
    # are heard on that link, about once a second, not twice (one misrouted from the other
    # link's vehicle with the same system id) nor never.
    for link in ("1", "2"):
        heard = emulated["heartbeats_by_link"][link]
        assert set(heard) == {f"{s}/191" for s in range(1, PER_LINK + 1)}, link
        assert all(0 < n <= wall + 5 for n in heard.values()), (link, heard)
    # Commands, each on its own link: what an emulated vehicle accepted is at most what the
    # service sent that vehicle (a command misrouted to the other link's vehicle with the
    # same system id would be accepted there). The horizon test holds a vehicle's commands
    # back until its model passes (15 to over 100 samples here): a third commanded in one run.
    per_vehicle = emulated["per_vehicle"]
    assert set(per_vehicle) == {keys.key_id(v) for v in vehicles}
    commanded = 0
    for vehicle in vehicles:
        sent = summary["vehicles"][str(vehicle)]["commands_sent"]
        accepted = per_vehicle[keys.key_id(vehicle)]["commands_accepted"]
        assert accepted <= sent, (keys.key_id(vehicle), accepted, sent)
        assert commanded_on_zenoh[keys.command_ballast(vehicle)] <= sent
        if accepted > 0:
            commanded += 1
            assert commanded_on_zenoh[keys.command_ballast(vehicle)] > 0
    assert commanded >= len(vehicles) // 10, commanded
    assert emulated["unrouted"] == 0
    assert emulated["steps"] == LINKS * PER_LINK * STEPS
    # Every vehicle's samples assembled under its own id (how many reach a loaded machine's
    # service is the benchmark's figure, bench_fleet.py --links: not asserted here).
    for vehicle in vehicles:
        assert summary["vehicles"][str(vehicle)]["counters"]["samples"] >= STEPS // 2, vehicle
