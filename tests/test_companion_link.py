"""The service as each vehicle's companion on every profile, on real loopback sockets.

It sends HEARTBEAT at 1 Hz from the vehicle's system id and component 191, one per vehicle
it serves, and its commands from that identity; on a `udpin` port shared by vehicles on
sockets of their own, each vehicle's commands (and heartbeats) go to the address its frames
came from, never to another vehicle's.
"""

from __future__ import annotations

import json

from hil_service.mcap.reader import LogReader
from tests.conftest import free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe

SPEED = 20  # plant steps (samples) per wall second, glider profile
BURN_IN = 40


def _emulate(processes, udp: int, system_id: int):
    return processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--sysid", str(system_id),
        "--speed", str(SPEED), "--seed", str(system_id),
    )  # fmt: skip


def _summary(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])["emulator"]


def test_glider_profile_heartbeat_and_commands_from_the_vehicles_companion(processes, tmp_path):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint,
        "--log-dir", str(tmp_path / "logs"), "--burn-in", str(BURN_IN), "--control",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    try:
        emulator = processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--sysid", "3",
            "--speed", str(SPEED), "--seed", "2",
        )  # fmt: skip
        assert probe.wait_for(lambda: probe.count("glider/3/telemetry") >= 10, 60)
        probe.put("glider/3/setpoint/depth", {"value": 15.5})
        # 100 samples are 5 s at SPEED: at least 4 heartbeats at 1 Hz, however loaded.
        assert probe.wait_for(
            lambda: (
                probe.count("glider/3/command/ballast") >= 20
                and probe.count("glider/3/telemetry") >= 100
            ),
            90,
        ), probe.latest("glider/3/health")
        health = probe.latest("glider/3/health")
        assert health["companion"]["heartbeats"] >= 1, health["companion"]
        assert health["companion"]["stream_requests"] == {}  # lockstep: nothing to ask for
    finally:
        probe.close()
    vehicle = _summary(processes.stop(emulator)[0])
    processes.stop(service)
    sources = vehicle["gcs"]["heartbeat_sources"]
    assert sources.get("3/191", 0) >= 4, sources
    assert set(sources) == {"3/191"}, sources  # nothing from a ground station's 255
    assert vehicle["gcs"]["heartbeats"] == {"MAV_TYPE_ONBOARD_CONTROLLER": sources["3/191"]}
    assert vehicle["commands_accepted"] >= 20 and vehicle["commands_rejected"] == 0
    # Every frame the service sent, as its log has it: the vehicle's id, component 191.
    (log,) = sorted((tmp_path / "logs").glob("*.mcap"))
    sent = {}
    for message in LogReader(log).messages():
        if message.topic.startswith("mavlink/json/out/"):
            header = message.json()["_header"]
            key = (message.topic.rsplit("/", 1)[1], header["system_id"], header["component_id"])
            sent[key] = sent.get(key, 0) + 1
    assert {k[1:] for k in sent} == {(3, 191)}, sent
    assert {k[0] for k in sent} == {"HEARTBEAT", "COMMAND_LONG"}, sent


def test_one_heartbeat_per_vehicle_served_on_a_shared_link(processes):
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    try:
        emulator = processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--vehicles", "2",
            "--sysid", "7", "--speed", str(SPEED), "--seed", "1",
        )  # fmt: skip
        # 80 samples each are 4 s at SPEED: at least 3 heartbeats per vehicle.
        assert probe.wait_for(
            lambda: all(probe.count(f"glider/{i}/telemetry") >= 80 for i in (7, 8)), 90
        )
    finally:
        probe.close()
    fleet = _summary(processes.stop(emulator)[0])
    heartbeats = fleet["heartbeats"]
    assert set(heartbeats) == {"7/191", "8/191"}, heartbeats
    assert min(heartbeats.values()) >= 3, heartbeats
    assert fleet["unrouted"] == 0


def test_each_vehicle_on_its_own_socket_gets_only_its_own_commands(processes):
    """Two emulators, two sockets, one `udpin` port: pymavlink alone would send every
    command to every peer it heard (or to the last one); the service routes by system id."""
    udp, zport = free_udp_port(), free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{zport}"
    service = processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-listen", endpoint, "--no-log",
        "--burn-in", str(BURN_IN), "--control",
    )  # fmt: skip
    probe = ZenohProbe(endpoint)
    ids = (1, 2)
    try:
        emulators = {i: _emulate(processes, udp, i) for i in ids}
        assert probe.wait_for(lambda: all(probe.count(f"glider/{i}/telemetry") for i in ids), 60)
        for i in ids:
            probe.put(f"glider/{i}/setpoint/depth", {"value": 15.5})
        assert probe.wait_for(
            lambda: all(probe.count(f"glider/{i}/command/ballast") >= 30 for i in ids), 90
        ), {i: probe.latest(f"glider/{i}/health") for i in ids}
    finally:
        probe.close()
    vehicles = {i: _summary(processes.stop(emulators[i])[0]) for i in ids}
    out, _ = processes.stop(service)
    sent = json.loads(out.strip().splitlines()[-1])["service"]["vehicles"]
    for i, vehicle in vehicles.items():
        assert vehicle["commands_for_other_systems"] == 0, (i, vehicle)
        assert vehicle["commands_accepted"] >= 30, (i, vehicle)
        # Accepted ≤ sent to it: the command in flight as a vehicle stops may be lost.
        assert vehicle["commands_accepted"] <= sent[str(i)]["commands_sent"]
        assert set(vehicle["gcs"]["heartbeat_sources"]) == {f"{i}/191"}, (i, vehicle["gcs"])
