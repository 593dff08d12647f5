"""``glider-hil emulate --vehicles N``: N emulated gliders in one process.

System ids run from ``--sysid`` (``sysid … sysid+N-1``), seeds from ``--seed`` (one per
vehicle, so their excitations and disturbances are independent). Each vehicle is an
``Autopilot`` on its own link (its own UDP socket) and thread, exactly as ``emulate`` runs
one. ``--fleet-connect`` (repeatable) splits the vehicles in contiguous, equal blocks over
several links, e.g. one per service; without it every vehicle uses ``--connect``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from typing import Any

from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import Link
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
    return Autopilot(
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
    autopilots: list[Autopilot] = []
    try:
        for index in range(count):
            system_id = args.sysid + index
            link = Link(
                connection_for(index, count, connections), source_system=system_id,
                source_component=1,
            )  # fmt: skip
            links.append(link)
            autopilots.append(_autopilot(args, system_id, args.seed + index, link))
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
    print(
        json.dumps({"emulator": {"vehicles": count, "steps": steps, "per_vehicle": per_vehicle}}),
        flush=True,
    )
    return 0
