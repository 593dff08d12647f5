"""``glider-hil emulate --vehicles N``: N emulated gliders in one process.

System ids run from ``--sysid`` (``sysid … sysid+N-1``), seeds from ``--seed`` (one per
vehicle, so their excitations and disturbances are independent). Each vehicle is an
``Autopilot`` on its own link (its own UDP socket) and thread, exactly as ``emulate`` runs
one, and measures telemetry → command latency (``TimedAutopilot``; printed at the end with
the per-vehicle statistics). ``--fleet-connect`` (repeatable) splits the vehicles in
contiguous, equal blocks over several links, e.g. one per service; without it every vehicle
uses ``--connect``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from typing import Any

from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import Link, MavMessage
from protocols.signing import load_key
from protocols.units import InputScale, PressureDepth


def add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("fleet")
    group.add_argument(
        "--vehicles",
        type=int,
        default=1,
        help="emulate N gliders in this process, system ids from --sysid (default 1)",
    )
    group.add_argument(
        "--fleet-connect",
        action="append",
        default=[],
        metavar="CONNECTION",
        help="with --vehicles: split the vehicles in contiguous blocks over these links "
        "(repeatable; default: all on --connect)",
    )


def connection_for(index: int, vehicles: int, connections: list[str]) -> str:
    """The link of vehicle ``index`` (0-based): contiguous, equal blocks in order."""
    return connections[index * len(connections) // vehicles]


class TimedAutopilot(Autopilot):
    """An autopilot that also measures telemetry → command latency: from sending a step's
    last telemetry datagram to receiving the first accepted command after it (the service
    answers each complete sample with at most one command)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.latencies: list[float] = []  # s
        self._sent_at: float | None = None

    def step(self) -> Any:
        sample = super().step()
        self._sent_at = time.perf_counter()
        return sample

    def handle_message(self, message: MavMessage) -> None:
        accepted = self.stats.commands_accepted
        super().handle_message(message)
        if self.stats.commands_accepted > accepted and self._sent_at is not None:
            self.latencies.append(time.perf_counter() - self._sent_at)
            self._sent_at = None


def latency_summary(latencies: list[float]) -> dict[str, Any]:
    """Count and percentiles (ms) of telemetry → command latencies."""
    if not latencies:
        return {"count": 0}
    ordered = sorted(latencies)

    def pct(q: float) -> float:
        return round(1000 * ordered[min(len(ordered) - 1, int(q * len(ordered)))], 3)

    return {"count": len(ordered), "p50_ms": pct(0.5), "p99_ms": pct(0.99), "max_ms": pct(1.0)}


def _autopilot(args: argparse.Namespace, system_id: int, seed: int, link: Link) -> Autopilot:
    plant = GliderPlant(
        PlantConfig(
            scenario=args.scenario,
            period=args.period,
            seed=seed,
            trim_depth=args.trim_depth,
            rate_limit=args.rate_limit,
        ),
        system_id=system_id,
    )
    config = AutopilotConfig(
        system_id=system_id,
        speed=args.speed,
        duration=args.duration,
        command_timeout=args.command_timeout,
        fallback=args.fallback,
        signing_key=None if args.signing_key is None else load_key(args.signing_key),
        accept_unsigned_non_commands=args.accept_unsigned_non_commands,
    )
    mapping = TelemetryMapping(
        pressure=PressureDepth(args.water_density, args.surface_pressure),
        inputs=InputScale(args.full_scale),
    )
    return TimedAutopilot(
        plant, link, build_channel_excitations(args.excitation, seed=seed), config, mapping
    )


def run_fleet(args: argparse.Namespace) -> int:
    count = args.vehicles
    last = args.sysid + count - 1
    if count < 1 or args.sysid < 1 or last > 255:
        print(
            f"glider-hil emulate: --vehicles {count} from --sysid {args.sysid} leaves 1..255",
            file=sys.stderr,
        )
        return 2
    connections = list(args.fleet_connect) or [args.connect]
    links: list[Link] = []
    autopilots: list[TimedAutopilot] = []
    try:
        for index in range(count):
            system_id = args.sysid + index
            link = Link(
                connection_for(index, count, connections), source_system=system_id,
                source_component=1,
            )  # fmt: skip
            links.append(link)
            autopilot = _autopilot(args, system_id, args.seed + index, link)
            assert isinstance(autopilot, TimedAutopilot)
            autopilots.append(autopilot)
    except (ValueError, OSError) as error:
        print(f"glider-hil emulate: {error}", file=sys.stderr)
        for link in links:
            link.close()
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    threads = [
        threading.Thread(target=a.run, args=(stop,), name=f"glider-{a.config.system_id}")
        for a in autopilots
    ]
    print(
        f"emulating {count} gliders, sysid {args.sysid}-{last} ({args.scenario}, "
        f"{args.excitation}) on {', '.join(connections)} at {args.speed:g}x",
        file=sys.stderr,
        flush=True,
    )
    for thread in threads:
        thread.start()
    try:
        while any(t.is_alive() for t in threads) and not stop.wait(0.2):
            pass
    finally:
        stop.set()
        for thread in threads:
            thread.join(10)
        for link in links:
            link.close()
    per_vehicle: dict[str, Any] = {
        str(a.config.system_id): a.stats.as_dict(a.codec) for a in autopilots
    }
    steps = sum(v["steps"] for v in per_vehicle.values())
    latency = latency_summary([x for a in autopilots for x in a.latencies])
    summary = {"vehicles": count, "steps": steps, "latency": latency, "per_vehicle": per_vehicle}
    print(json.dumps({"emulator": summary}), flush=True)
    return 0
