"""``FleetScheduler``: every emulated vehicle on one thread, its commands routed by target.

A peer on a loopback socket plays the service: it answers each ATTITUDE of vehicle 6 with a
ballast command for vehicle 6, so only that vehicle may accept commands and measure latency.
"""

from __future__ import annotations

import socket
import threading
import time
from itertools import pairwise

from plant_emulator.autopilot import AutopilotConfig
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.fleet import FleetScheduler, SharedLink, TimedAutopilot
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import SERVICE_COMPONENT, TelemetryMapping
from protocols.mavlink_io import MavlinkCodec
from protocols.samples import BallastCommand

SYSTEM_IDS = (5, 6, 7)
STEPS = 40  # per vehicle: --duration 40 s of a 1 s plant period
COMMANDED = 6


def _service(sock: socket.socket, stop: threading.Event) -> None:
    """Answer vehicle 6's ATTITUDE with a command for vehicle 6, until ``stop``."""
    codec, mapping = MavlinkCodec(255, SERVICE_COMPONENT), TelemetryMapping()
    sock.settimeout(0.2)
    while not stop.is_set():
        try:
            data, address = sock.recvfrom(65535)
        except TimeoutError:
            continue
        for message in codec.parse(data, datagram=True):
            if message.get_type() == "ATTITUDE" and message.get_srcSystem() == COMMANDED:
                command = mapping.ballast_command(BallastCommand(0.1, -0.1), COMMANDED)
                sock.sendto(codec.pack(command), address)


def test_one_thread_steps_every_vehicle_and_routes_each_command() -> None:
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    shared = SharedLink(f"udpout:127.0.0.1:{peer.getsockname()[1]}")
    autopilots = []
    for index, system_id in enumerate(SYSTEM_IDS):
        autopilot = TimedAutopilot(
            GliderPlant(PlantConfig(seed=index), system_id=system_id),
            shared.port(),
            build_channel_excitations("steps", seed=index),
            AutopilotConfig(system_id=system_id, speed=100.0, duration=float(STEPS)),
        )
        shared.attach(autopilot)
        autopilots.append(autopilot)
    period = 1.0 / 100.0
    offsets = [i * period / len(SYSTEM_IDS) for i in range(len(SYSTEM_IDS))]
    stop = threading.Event()
    service = threading.Thread(target=_service, args=(peer, stop), daemon=True)
    service.start()
    try:
        timer = threading.Timer(60.0, stop.set)  # a bound, never reached on a sane machine
        timer.start()
        FleetScheduler(autopilots, [shared], offsets).run(stop)
        timer.cancel()
    finally:
        stop.set()
        service.join(5.0)
        shared.close()
        peer.close()
    by_id = {a.config.system_id: a for a in autopilots}
    for system_id, autopilot in by_id.items():
        assert autopilot.stats.steps == STEPS, (system_id, autopilot.stats)
        assert autopilot.stats.heartbeats >= 1
    commanded = by_id[COMMANDED]
    # Answers to the last steps may still be in flight when the fleet stops.
    assert commanded.stats.commands_accepted >= STEPS // 2, commanded.stats
    assert len(commanded.latencies) >= STEPS // 2 and all(x > 0 for x in commanded.latencies)
    for system_id in set(SYSTEM_IDS) - {COMMANDED}:
        assert by_id[system_id].stats.commands_accepted == 0
        assert by_id[system_id].latencies == []
    assert shared.unrouted == 0


STALL_STEP = 20  # the host stalls after the first vehicle's this many steps
STALL_PERIODS = 20  # for this many step periods
SPEED = 25.0  # a step every 40 ms: a loaded machine's own delays stay below a slip
STALL_IDS = (1, 2)  # two vehicles, half a period apart


def _stalled_fleet(max_lag_steps: int) -> list[tuple[TimedAutopilot, list[float]]]:
    """Two vehicles at SPEED whose scheduler's clock jumps by STALL_PERIODS step periods
    after the first one's step STALL_STEP (a host that stalled the emulator); each vehicle
    with the clock at each of its steps."""
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    shared = SharedLink(f"udpout:127.0.0.1:{peer.getsockname()[1]}")
    steps = 45
    jump = [0.0]

    def clock() -> float:
        return time.perf_counter() + jump[0]

    fleet: list[tuple[TimedAutopilot, list[float]]] = []
    for index, system_id in enumerate(STALL_IDS):
        autopilot = TimedAutopilot(
            GliderPlant(PlantConfig(seed=index), system_id=system_id),
            shared.port(),
            build_channel_excitations("steps", seed=index),
            AutopilotConfig(
                system_id=system_id,
                speed=SPEED,
                duration=float(steps),
                max_lag_steps=max_lag_steps,
            ),
        )
        shared.attach(autopilot)
        stepped_at: list[float] = []

        def on_step(
            sample: object, autopilot: TimedAutopilot = autopilot, at: list[float] = stepped_at
        ) -> None:
            at.append(clock())
            if autopilot is fleet[0][0] and autopilot.stats.steps == STALL_STEP:
                jump[0] += STALL_PERIODS / SPEED

        autopilot.on_step = on_step
        fleet.append((autopilot, stepped_at))
    stop = threading.Event()
    timer = threading.Timer(30.0, stop.set)  # a bound, never reached on a sane machine
    timer.start()
    offsets = [i * 0.5 / SPEED for i in range(len(fleet))]
    try:
        FleetScheduler([a for a, _ in fleet], [shared], offsets, clock=clock).run(stop)
    finally:
        timer.cancel()
        shared.close()
        peer.close()
    for autopilot, _ in fleet:
        assert autopilot.stats.steps == steps
    return fleet


def _steps_in_a_burst(stepped_at: list[float], period: float) -> int:
    """Steps taken less than half a period after the one before."""
    return sum(b - a < period / 2 for a, b in pairwise(stepped_at))


def test_a_stalled_fleet_slips_each_vehicles_schedule_instead_of_bursting() -> None:
    for autopilot, stepped_at in _stalled_fleet(max_lag_steps=3):
        # Each vehicle's time paused for the stall, less the part of a period that was
        # left before its next step fell due (simulated s: a plant period of 1 s).
        assert autopilot.stats.slips >= 1
        assert autopilot.stats.slipped_s >= STALL_PERIODS - 1
        # At most the few steps a loaded machine's own delays can leave to catch up.
        assert _steps_in_a_burst(stepped_at, 1.0 / SPEED) < STALL_PERIODS // 2


def test_without_slipping_a_stalled_fleet_steps_in_a_burst() -> None:
    for autopilot, stepped_at in _stalled_fleet(max_lag_steps=1000):
        assert autopilot.stats.slips == 0
        assert _steps_in_a_burst(stepped_at, 1.0 / SPEED) >= STALL_PERIODS - 2
