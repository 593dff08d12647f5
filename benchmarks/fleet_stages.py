"""Where a fleet's telemetry → command time goes, stage by stage, in one process (no other
process of ours competing for the cores): the per-stage budget behind
``benchmarks/bench_fleet.py``.

* emulator: one vehicle's step (plant, four telemetry frames packed and sent on UDP) as
  ``emulate --vehicles`` runs it (``TimedAutopilot`` on a shared link);
* service: one sample's datagrams handed to ``HilService.process_datagram`` until it returns
  (decode, assemble, identify, decide, command packed and sent on UDP, telemetry, estimates
  and command published on a Zenoh session) for a fleet of ``--vehicles`` served by one
  service, control on with a depth setpoint each, after the burn-in;
* health: a ``tick()`` that publishes health (one vehicle's at a time, round robin, each
  vehicle once a second, so that no burst of every vehicle's keeps the samples arriving
  meanwhile waiting). The service runs on the fleet's clock: a sample every
  0.1 s / vehicles, ``tick()`` after every datagram as ``serve``'s loop calls it.

Printed: p50 / p99 / max in ms per stage, and the CPU one service and the emulator need for
``--vehicles`` at ``--rate`` samples/s per vehicle.

Run: .venv/bin/python benchmarks/fleet_stages.py [--vehicles 50] [--steps 300]
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.builder import wire  # noqa: E402
from hil_service.config import ServiceConfig  # noqa: E402
from hil_service.listeners.zenoh_config import ZenohOptions, open_session  # noqa: E402
from hil_service.pipeline import PipelineSettings  # noqa: E402
from hil_service.process_tuning import tune_for_service  # noqa: E402
from plant_emulator.autopilot import AutopilotConfig  # noqa: E402
from plant_emulator.excitation import build_channel_excitations  # noqa: E402
from plant_emulator.fleet import SharedLink, TimedAutopilot  # noqa: E402
from plant_emulator.plant import GliderPlant, PlantConfig  # noqa: E402
from protocols import keys  # noqa: E402
from protocols.mapping import TelemetryMapping  # noqa: E402
from protocols.mavlink_io import Link, MavlinkCodec  # noqa: E402

BURN_IN = 50


def percentiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)

    def pct(q: float) -> float:
        return round(1000 * ordered[min(len(ordered) - 1, int(q * len(ordered)))], 3)

    return {"count": len(ordered), "p50_ms": pct(0.5), "p99_ms": pct(0.99), "max_ms": pct(1.0)}


def sink_port() -> tuple[socket.socket, int]:
    """A UDP socket nobody reads (datagrams are dropped once its buffer is full)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock, sock.getsockname()[1]


def emulator_steps(vehicles: int, steps: int, port: int) -> tuple[list[float], list[list[bytes]]]:
    """Step ``vehicles`` autopilots ``steps`` times; the time of each step, and each step's
    frames per vehicle (what the service will be fed)."""
    shared = SharedLink(f"udpout:127.0.0.1:{port}")
    autopilots = []
    for index in range(vehicles):
        system_id = index + 1
        plant = GliderPlant(PlantConfig(scenario="paper", seed=index), system_id=system_id)
        autopilot = TimedAutopilot(
            plant,
            shared.port(),
            build_channel_excitations("steps", seed=index),
            AutopilotConfig(system_id=system_id, speed=10.0),
        )
        shared.attach(autopilot)
        autopilots.append(autopilot)
    mapping = TelemetryMapping()
    codecs = {a.config.system_id: MavlinkCodec(a.config.system_id, 1) for a in autopilots}
    times: list[float] = []
    frames: list[list[bytes]] = []
    for _ in range(steps):
        for autopilot in autopilots:
            started = time.perf_counter()
            sample = autopilot.step()
            times.append(time.perf_counter() - started)
            codec = codecs[autopilot.config.system_id]
            frames.append([codec.pack(m) for m in mapping.encode_telemetry(sample)])
    shared.close()
    return times, frames


def service_stages(frames: list[list[bytes]], vehicles: int, port: int) -> dict[str, object]:
    settings = PipelineSettings().replace(burn_in=BURN_IN)
    config = ServiceConfig(control_default=True, pipeline=settings)
    session = open_session(ZenohOptions())  # no peers: puts cost encoding and the call
    link = Link(f"udpout:127.0.0.1:{port}", source_system=255, source_component=191)
    wired = wire(config, session=session, link=link)
    service = wired.service
    for system_id in range(1, vehicles + 1):
        wired.inbox.accept(keys.setpoint(system_id, "depth"), json.dumps({"value": 16.0}).encode())
    tune_for_service()
    per_sample: list[float] = []
    health: list[float] = []
    wall = [0.0]
    service.clock = lambda: wall[0]  # the fleet's time: a sample every 0.1 s / vehicles
    for index, datagrams in enumerate(frames):
        wall[0] = index * 0.1 / vehicles
        started = time.perf_counter()
        for datagram in datagrams:
            service.process_datagram(datagram)
            service.tick()  # as serve's loop: after every datagram (health, companions)
        elapsed = time.perf_counter() - started
        if index >= BURN_IN * vehicles * 2:
            per_sample.append(elapsed)
        published = service._health_turn
        started = time.perf_counter()
        wall[0] += 0.05 / vehicles  # between two vehicles' steps: health may be due
        service.tick()
        if service._health_turn != published:
            health.append(time.perf_counter() - started)
    commands = sum(v.commands_sent for v in service.vehicles.values())
    wired.close()
    return {"sample_to_command": percentiles(per_sample), "health_tick": percentiles(health),
            "commands": commands}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--vehicles", type=int, default=50, help="vehicles of one service")
    parser.add_argument("--steps", type=int, default=300, help="steps per vehicle")
    parser.add_argument("--rate", type=float, default=10.0, help="samples/s per vehicle")
    args = parser.parse_args()
    sink, port = sink_port()
    try:
        step_times, frames = emulator_steps(args.vehicles, args.steps, port)
        stages = service_stages(frames, args.vehicles, port)
    finally:
        sink.close()
    emulator = percentiles(step_times)
    service = stages["sample_to_command"]
    assert isinstance(service, dict)
    rate = args.vehicles * args.rate
    print(json.dumps({
        "vehicles": args.vehicles,
        "emulator_step": emulator,
        **stages,
        "cores_for_one_service_at_rate": round(rate * service["p50_ms"] / 1000, 3),
        "cores_for_the_emulator_at_rate": round(rate * emulator["p50_ms"] / 1000, 3),
    }))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
