"""A fleet's per-sample cost in the service alone, and its garbage collector's pauses.

One ``HilService`` wired as ``serve --vehicle-ids link --max-vehicles N`` with ``--links``
UDP links (each a block of system ids numbered from 1), a Zenoh client session to a
``glider-hil router`` on loopback with a subscriber on telemetry, commands and health, control
on with a depth setpoint for every vehicle. Every vehicle's telemetry is generated first (the
emulator's glider, ``paper`` scenario, seeded by vehicle) and then handed to
``process_datagram`` in order, one sample per vehicle per second on the service's own
clock, ``tick()`` after every datagram as ``serve``'s loop calls it; nothing else of ours
runs meanwhile. After ``--from-step`` steps (past the burn-in) it measures:

* CPU per sample: the main thread's and the whole process's (Zenoh's threads included);
* the wall time of one sample's handling: p50, p99, max; and of one step's, summed over
  the vehicles (median, max, which step, how many took over 1 s): at 1 Hz a step that
  takes longer than a second is a stall the wire's queue must absorb;
* one health payload's build time, per vehicle, after the run;
* Python's garbage collections over the same samples (``gc.callbacks``): how many per
  generation, their total and their longest pause; then one full collection: its pause
  and the unreachable objects it found, the reference cycles of the whole run.

``--profile FILE`` writes a cProfile of the measured samples; ``--step-times FILE`` each
measured step's handling summed over the vehicles (JSON, step → s): where in a run the load
rises, e.g. over the structure choices' window from sample 600 on.

Run: .venv/bin/python benchmarks/fleet_inprocess.py [--vehicles 1000] [--links 4]
         [--steps 100] [--from-step 70] [--health-period 5] [--step-times FILE]
"""

from __future__ import annotations

import argparse
import gc
import json
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.process_tuning import single_threaded_blas  # noqa: E402

single_threaded_blas()  # as `serve` runs (before numpy loads)

import zenoh  # noqa: E402

from hil_service.builder import wire  # noqa: E402
from hil_service.cli.processes import start_verb, stop_process, wait_for_line  # noqa: E402
from hil_service.cli.router import ROUTER_READY  # noqa: E402
from hil_service.config import ServiceConfig  # noqa: E402
from hil_service.listeners.zenoh_config import ZenohOptions, open_session  # noqa: E402
from hil_service.pipeline import PipelineSettings  # noqa: E402
from hil_service.process_tuning import tune_for_service  # noqa: E402
from hil_service.vehicle_links import LinkSet  # noqa: E402
from plant_emulator.autopilot import AutopilotConfig  # noqa: E402
from plant_emulator.excitation import build_channel_excitations  # noqa: E402
from plant_emulator.fleet import SharedLink, TimedAutopilot  # noqa: E402
from plant_emulator.plant import GliderPlant, PlantConfig  # noqa: E402
from protocols import compiled, keys  # noqa: E402
from protocols.mapping import TelemetryMapping  # noqa: E402
from protocols.mavlink_io import MavlinkCodec  # noqa: E402


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def block_of(index: int, vehicles: int, links: int) -> tuple[int, int]:
    """Vehicle ``index``'s link (from 1) and its system id on that link (from 1)."""
    link = index * links // vehicles + 1
    return link, index - (link - 1) * vehicles // links + 1


def telemetry(vehicles: int, links: int, steps: int) -> list[tuple[int, int, list[bytes]]]:
    """Every vehicle's datagrams, step by step: (link, system id, datagrams)."""
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    shared = SharedLink(f"udpout:127.0.0.1:{sink.getsockname()[1]}")
    mapping = TelemetryMapping()
    fleet = []
    for index in range(vehicles):
        link, wire_id = block_of(index, vehicles, links)
        plant = GliderPlant(PlantConfig(scenario="paper", seed=index), system_id=wire_id)
        autopilot = TimedAutopilot(
            plant,
            shared.port(),
            build_channel_excitations("steps", seed=index),
            AutopilotConfig(system_id=wire_id, speed=1.0),
        )
        shared.attach(autopilot)
        fleet.append((link, wire_id, autopilot, MavlinkCodec(wire_id, 1)))
    out = []
    for _ in range(steps):
        for link, wire_id, autopilot, codec in fleet:
            sample = autopilot.step()
            heartbeat = codec.pack(mapping.heartbeat(vehicle=True))
            frames = [codec.pack(m) for m in mapping.encode_telemetry(sample)]
            out.append((link, wire_id, [heartbeat, *frames]))
    shared.close()
    sink.close()
    return out


class Collections:
    """Python's garbage collections while ``on``: count per generation, total, longest."""

    def __init__(self) -> None:
        self.on = False
        self.counts = [0, 0, 0]
        self.total = 0.0
        self.longest = 0.0
        self._start = 0.0

    def __call__(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._start = time.perf_counter()
        elif self.on:
            pause = time.perf_counter() - self._start
            self.counts[info["generation"]] += 1
            self.total += pause
            self.longest = max(self.longest, pause)


def client(router: str) -> zenoh.Session:
    """A client session to the router, as ``serve --zenoh-mode client --zenoh-connect``."""
    return open_session(ZenohOptions(mode="client", connect=(router,)))


def horizon_tests_run(service: Any) -> int:
    """The horizon tests the fleet's channels have run so far (each runs its model over
    up to 1,000 samples: what a fleet that converged together would pay on one sample)."""
    return sum(
        channel.horizon_test.evaluations
        for vehicle in service.vehicles.values()
        for channel in vehicle.pipeline.channels.values()
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=1000)
    parser.add_argument("--links", type=int, default=4)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--from-step", type=int, default=70, help="measure from this step on")
    parser.add_argument("--health-period", type=float, default=5.0)
    parser.add_argument("--profile", help="write a cProfile of the measured samples here")
    parser.add_argument(
        "--step-times", help="write each measured step's handling, summed over the vehicles, here"
    )
    args = parser.parse_args()
    if not 0 < args.from_step < args.steps:
        parser.error("--from-step must be within --steps")

    frames = telemetry(args.vehicles, args.links, args.steps)
    router = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    router_process = start_verb("router", "--listen", router)
    try:
        wait_for_line(router_process, ROUTER_READY, 60)
        run(args, frames, router)
    finally:
        stop_process(router_process)


def run(args: argparse.Namespace, frames: list[tuple[int, int, list[bytes]]], router: str) -> None:
    listener = client(router)
    received = {"telemetry": 0, "command": 0, "health": 0}

    def count(kind: str) -> Callable[[object], None]:
        return lambda _sample: received.__setitem__(kind, received[kind] + 1)

    subscribers = [
        listener.declare_subscriber(f"{keys.ROOT}/*/{keys.TELEMETRY}", count("telemetry")),
        listener.declare_subscriber(f"{keys.ROOT}/*/{keys.COMMAND_BALLAST}", count("command")),
        listener.declare_subscriber(f"{keys.ROOT}/*/{keys.HEALTH}", count("health")),
    ]
    links = LinkSet(
        [f"udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}" for _ in range(args.links)], 255, 191
    )
    config = ServiceConfig(
        control_default=True,
        pipeline=PipelineSettings().replace(burn_in=50),
        health_period=args.health_period,
        vehicle_ids="link",
        max_vehicles=args.vehicles,
    )
    wired = wire(config, session=client(router), link=links)
    service = wired.service
    for index in range(args.vehicles):
        link, wire_id = block_of(index, args.vehicles, args.links)
        key = keys.setpoint(keys.vehicle_id(link, wire_id), "depth")
        listener.put(key, json.dumps({"value": 16.0}))
    now = [0.0]
    service.clock = lambda: now[0]
    # Commands go to this socket, which nobody reads: the kernel drops them once it is full.
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sender = sink.getsockname()
    tune_for_service()
    collections = Collections()
    gc.callbacks.append(collections)
    handling: list[float] = []
    steps: dict[int, float] = {}  # a step's handling summed over its vehicles
    profile = None
    cpu = process = 0.0
    horizon_tests: dict[int, int] = {}  # the fleet's horizon tests run in a step
    tests_before = 0
    for index, (link, _wire_id, datagrams) in enumerate(frames):
        step, vehicle = divmod(index, args.vehicles)
        if step == args.from_step and vehicle == 0:
            collections.on = True
            cpu, process = time.thread_time(), time.process_time()
            tests_before = horizon_tests_run(service)
            if args.profile:
                import cProfile

                profile = cProfile.Profile()
                profile.enable()
        now[0] = step + vehicle / args.vehicles
        start = time.perf_counter()
        for datagram in datagrams:
            service.process_datagram(datagram, True, (link, sender))
            service.tick()
        if collections.on:
            handling.append(time.perf_counter() - start)
            steps[step] = steps.get(step, 0.0) + handling[-1]
            if vehicle == args.vehicles - 1:
                tests_run = horizon_tests_run(service)
                horizon_tests[step] = tests_run - tests_before
                tests_before = tests_run
    cpu, process = time.thread_time() - cpu, time.process_time() - process
    if profile is not None:
        profile.disable()
        profile.dump_stats(args.profile)
    gc.callbacks.remove(collections)
    if args.step_times:
        Path(args.step_times).write_text(json.dumps({str(k): v for k, v in steps.items()}))
    # What the hourly collection of a `serve` would cost now, and what it would find: the
    # reference cycles the whole run left (with automatic collection off, none was freed).
    start = time.perf_counter()
    unreachable = gc.collect()
    full_collection_s = time.perf_counter() - start
    # One health payload per vehicle, as the round robin builds them: at 1 Hz and the
    # default --health-period 1, one for every sample.
    start = time.perf_counter()
    for vehicle_id in service.vehicles:
        service.health(vehicle_id)
    health_s = (time.perf_counter() - start) / max(1, len(service.vehicles))
    handling.sort()
    samples = len(handling)
    step_sums = sorted(steps.values())
    longest_step = max(steps, key=steps.__getitem__)
    print(
        json.dumps(
            {
                "kind": compiled.summary(),
                "vehicles": len(service.vehicles),
                "measured_samples": samples,
                "main_thread_cpu_ms_per_sample": round(1000 * cpu / samples, 4),
                "process_cpu_ms_per_sample": round(1000 * process / samples, 4),
                "handling_ms": {
                    "p50": round(1000 * handling[samples // 2], 3),
                    "p99": round(1000 * handling[int(0.99 * samples)], 3),
                    "max": round(1000 * handling[-1], 3),
                },
                "step_handling_s": {
                    "median": round(step_sums[len(step_sums) // 2], 3),
                    "max": round(step_sums[-1], 3),
                    "longest_step": longest_step,
                    "steps_over_1s": sum(1 for v in step_sums if v > 1.0),
                },
                "gc": {
                    "collections_per_generation": collections.counts,
                    "total_s": round(collections.total, 3),
                    "longest_ms": round(1000 * collections.longest, 1),
                    "full_collection_after_the_run_ms": round(1000 * full_collection_s, 1),
                    "unreachable_objects_it_found": unreachable,
                },
                "horizon_tests_per_step": {
                    "median": sorted(horizon_tests.values())[len(horizon_tests) // 2],
                    "max": max(horizon_tests.values()),
                    "at_step": max(horizon_tests, key=horizon_tests.__getitem__),
                },
                "health_payload_us": round(1e6 * health_s, 1),
                "commands_sent": sum(v.commands_sent for v in service.vehicles.values()),
                "received_on_the_router": received,
            }
        )
    )
    wired.close()
    for subscriber in subscribers:
        subscriber.undeclare()
    listener.close()
    sink.close()


if __name__ == "__main__":
    main()
