"""``glider-hil emulate --vehicles N``: N emulated gliders in one process.

System ids run from ``--sysid`` (``sysid … sysid+N-1``), seeds from ``--seed`` (one per
vehicle, so their excitations and disturbances are independent). Each vehicle is an
``Autopilot`` on its own thread, as ``emulate`` runs one; the vehicles of one connection share
its socket, as vehicles behind one radio or MAVLink router do (``SharedLink``; a service on
``udpin`` sends each vehicle's commands to the address that vehicle's frames came from, so
vehicles on sockets of their own work too). One dispatcher thread per shared link hands each
received command to the vehicle it targets, and counts the heartbeats it hears by sender
(``"SYSID/COMPID"``: the service's, one per vehicle it serves, from the vehicle's system id
and component 191). Each autopilot measures telemetry → command latency
(``TimedAutopilot``; printed at the end with the per-vehicle statistics).
``--fleet-connect`` (repeatable) splits the vehicles in contiguous, equal blocks over several
links, e.g. one per service; without it every vehicle uses ``--connect``.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import sys
import threading
import time
from typing import Any

from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.gcs import count_heartbeat
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping, command_target_system, is_ballast_command
from protocols.mavlink_io import Link, MavlinkCodec, MavMessage
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
        "--phase-locked",
        action="store_true",
        help="with --vehicles: step every vehicle at the same instant (default: their steps "
        "are spread evenly over one period, as independent vehicles' clocks are)",
    )
    group.add_argument(
        "--fleet-connect",
        action="append",
        default=[],
        metavar="CONNECTION",
        help="with --vehicles: split the vehicles in contiguous blocks over these links "
        "(repeatable; default: all on --connect)",
    )


class VehiclePort:
    """One vehicle's view of a shared link, with the methods ``Autopilot`` uses of a ``Link``:
    sends go out on the shared socket, receives are the datagrams routed to this vehicle."""

    datagram = True

    def __init__(self, shared: SharedLink):
        self.shared = shared
        self.inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._next: bytes | None = None

    def wait(self, timeout: float) -> bool:
        if self._next is not None:
            return True
        try:
            self._next = self.inbox.get(timeout=max(timeout, 0.0))
        except queue.Empty:
            return False
        return True

    def recv(self) -> bytes:
        data, self._next = self._next, None
        if data is None:
            try:
                data = self.inbox.get_nowait()
            except queue.Empty:
                return b""
        return data

    def send(self, frame: bytes) -> None:
        self.shared.send(frame)

    def close(self) -> None:
        pass


class SharedLink:
    """One ``Link`` for several vehicles; a thread routes each command to its target."""

    def __init__(self, connection: str):
        self.link = Link(connection, source_system=1, source_component=1)
        self.ports: dict[int, VehiclePort] = {}
        self.unrouted = 0  # received messages that target none of our vehicles
        self.heartbeats: dict[str, int] = {}  # by sender, "SYSID/COMPID"
        self._codec = MavlinkCodec(255, 0)  # decoding only (signatures: each vehicle's codec)
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fleet-link", daemon=True)

    def port(self, system_id: int) -> VehiclePort:
        port = self.ports[system_id] = VehiclePort(self)
        return port

    def start(self) -> SharedLink:
        self._thread.start()
        return self

    def send(self, frame: bytes) -> None:
        with self._send_lock:
            self.link.send(frame)

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.link.wait(0.2):
                continue
            data = self.link.recv()
            if not data:
                continue
            for message in self._codec.parse(data, datagram=True):
                if message.get_type() == "HEARTBEAT":
                    count_heartbeat(self.heartbeats, message)
                    continue
                target = command_target_system(message) if is_ballast_command(message) else -1
                port = self.ports.get(target)
                if port is None:
                    self.unrouted += 1
                    continue
                port.inbox.put(bytes(message.get_msgbuf()))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.link.close()


def _merged(counts: list[dict[str, int]]) -> dict[str, int]:
    merged: dict[str, int] = {}
    for count in counts:
        for key, value in count.items():
            merged[key] = merged.get(key, 0) + value
    return merged


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


def _autopilot(args: argparse.Namespace, system_id: int, seed: int, link: VehiclePort) -> Autopilot:
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
    links: dict[str, SharedLink] = {}
    autopilots: list[TimedAutopilot] = []
    try:
        for connection in connections:
            links[connection] = SharedLink(connection)
        for index in range(count):
            system_id = args.sysid + index
            shared = links[connection_for(index, count, connections)]
            autopilot = _autopilot(args, system_id, args.seed + index, shared.port(system_id))
            assert isinstance(autopilot, TimedAutopilot)
            autopilots.append(autopilot)
    except (ValueError, OSError) as error:
        print(f"glider-hil emulate: {error}", file=sys.stderr)
        for shared in links.values():
            shared.link.close()
        return 2
    for shared in links.values():
        shared.start()
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    wall_period = args.period / args.speed

    def run_one(index: int, autopilot: TimedAutopilot) -> None:
        if not args.phase_locked and stop.wait(index * wall_period / count):
            return  # stopped before its first step
        autopilot.run(stop)

    threads = [
        threading.Thread(target=run_one, args=(i, a), name=f"glider-{a.config.system_id}")
        for i, a in enumerate(autopilots)
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
        for shared in links.values():
            shared.close()
    per_vehicle: dict[str, Any] = {
        str(a.config.system_id): a.stats.as_dict(a.codec) for a in autopilots
    }
    steps = sum(v["steps"] for v in per_vehicle.values())
    latency = latency_summary([x for a in autopilots for x in a.latencies])
    summary = {
        "vehicles": count,
        "steps": steps,
        "latency": latency,
        "unrouted": sum(shared.unrouted for shared in links.values()),
        "heartbeats": _merged([shared.heartbeats for shared in links.values()]),
        "per_vehicle": per_vehicle,
    }
    print(json.dumps({"emulator": summary}), flush=True)
    return 0
