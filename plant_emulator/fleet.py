"""``glider-hil emulate --vehicles N``: N emulated gliders in one process.

System ids run from ``--sysid`` (``sysid … sysid+N-1``), seeds from ``--seed`` (one per
vehicle, so their excitations and disturbances are independent). Each vehicle is an
``Autopilot``; the vehicles of one connection share its socket, as vehicles behind one radio
or MAVLink router do (``SharedLink``): a service on ``udpin`` sends each vehicle's commands
to the address that vehicle's frames came from, so vehicles on sockets of their own work too.
Heartbeats heard are counted by sender (``"SYSID/COMPID"``: the service's, one per vehicle
it serves, from the vehicle's system id and component 191).

One thread runs the whole fleet (``FleetScheduler``): a heap of step and heartbeat deadlines,
and one ``select`` over the shared sockets between them; a received command is parsed and
handed to the vehicle it targets at once. Why not a thread per vehicle: that puts 100+
threads under one GIL, where a command waits for a dispatcher thread, then for its
vehicle's thread, each behind whichever of the others holds the GIL; measured at 100
vehicles, the median telemetry → command latency is 1.8-8 ms that way, about 0.5 ms this
way. Each autopilot
measures telemetry → command latency (``TimedAutopilot``: from sending a step's last
telemetry datagram to the arrival of the datagram holding the command; printed at the end
with the per-vehicle statistics).
``--fleet-connect`` (repeatable) splits the vehicles in contiguous, equal blocks over several
links, e.g. one per service; without it every vehicle uses ``--connect``. More links than
vehicles, or one link given twice, are refused (``check_links``): a link would carry none.
``--sysid-per-link`` numbers each link's block from ``--sysid`` again, as a fleet of more than
255 gliders is numbered: each gateway (a link) has a system-id space of its own, and a
service with ``--vehicle-ids link`` tells its vehicles apart by (link, system id). Such a
vehicle's name in the summary is its key id ``{link}-{sysid}`` (``protocols.keys.key_id``),
link n being the n-th ``--fleet-connect``; the latency trace gives its vehicle id, the
number ``protocols.keys.vehicle_id`` makes of the two.
"""

from __future__ import annotations

import argparse
import errno
import heapq
import json
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

from plant_emulator.arguments import autopilot_config, telemetry_mapping
from plant_emulator.autopilot import HEARTBEAT_PERIOD, Autopilot, run_steps
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.gcs import count_heartbeat
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols import keys
from protocols.link_address import normalized
from protocols.mapping import command_target_system, is_ballast_command
from protocols.mavlink_io import Link, MavlinkCodec, MavMessage


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
    group.add_argument(
        "--sysid-per-link",
        action="store_true",
        help="with --fleet-connect: number each link's vehicles from --sysid again (more than "
        "255 gliders: a system-id space per link, serve --vehicle-ids link)",
    )
    group.add_argument(
        "--latency-trace",
        metavar="FILE",
        help="with --vehicles: write every telemetry -> command latency to FILE at the end, "
        "one JSON line [sent (time.perf_counter s), system id, latency s] each (benchmarks; "
        "a FILE that cannot be written is refused before the run)",
    )


class VehiclePort:
    """One vehicle's view of a shared link, with what ``Autopilot`` uses of a ``Link`` for
    sending; receiving is the scheduler's (``SharedLink.receive``)."""

    datagram = True

    def __init__(self, shared: SharedLink):
        self.shared = shared

    def send(self, frame: bytes) -> None:
        self.shared.link.send(frame)

    def close(self) -> None:
        pass


class SharedLink:
    """One ``Link`` for several vehicles; ``receive`` routes each command to its target."""

    def __init__(self, connection: str):
        self.link = Link(connection, source_system=1, source_component=1)
        self.autopilots: dict[int, TimedAutopilot] = {}
        self.unrouted = 0  # received messages that target none of our vehicles
        self.heartbeats: dict[str, int] = {}  # by sender, "SYSID/COMPID"
        self._codec = MavlinkCodec(255, 0)  # decoding only (signatures: each vehicle's codec)

    def port(self) -> VehiclePort:
        return VehiclePort(self)

    def attach(self, autopilot: TimedAutopilot) -> None:
        self.autopilots[autopilot.config.system_id] = autopilot

    def fileno(self) -> int:
        return self.link.fileno()

    def receive(self, clock: Callable[[], float]) -> int:
        """Every datagram waiting now, each message handed to the vehicle it targets (whose
        codec checks it again: signatures are per vehicle); the number of datagrams."""
        count = 0
        while True:
            data = self.link.recv()
            if not data:
                return count
            count += 1
            arrived = clock()
            for message in self._codec.parse(data, datagram=True):
                if message.get_type() == "HEARTBEAT":
                    count_heartbeat(self.heartbeats, message)
                    continue
                target = command_target_system(message) if is_ballast_command(message) else -1
                autopilot = self.autopilots.get(target)
                if autopilot is None:
                    self.unrouted += 1
                    continue
                autopilot.receive(bytes(message.get_msgbuf()), arrived)

    def close(self) -> None:
        self.link.close()


class FleetScheduler:
    """Every vehicle's steps and heartbeats on one thread, to absolute deadlines as
    ``Autopilot.run`` keeps them (start + offset + k·period/speed, heartbeats at 1 Hz), and
    the shared sockets read between them.

    A vehicle more than its ``max_lag_steps`` behind its schedule (a stalled host) slips
    it, as ``Autopilot.run`` does: its deadlines move on by the time it is behind, and its
    ``slips``/``slipped_s`` count it, instead of a burst of steps that no command could
    follow."""

    STEP, HEARTBEAT = 0, 1

    def __init__(
        self,
        autopilots: list[TimedAutopilot],
        links: list[SharedLink],
        offsets: list[float],
        clock: Callable[[], float] = time.perf_counter,
    ):
        self.autopilots = autopilots
        self.links = links
        self.offsets = offsets
        self.clock = clock
        self.late_steps = 0  # steps started more than one period after their deadline

    def _total_steps(self, autopilot: Autopilot) -> int | None:
        return run_steps(autopilot.config.duration, autopilot.plant.config.period)

    def run(self, stop: threading.Event) -> None:
        clock = self.clock
        start = clock()
        heap: list[tuple[float, int, int]] = []
        for index, offset in enumerate(self.offsets):
            heap.append((start + offset, self.HEARTBEAT, index))
            heap.append((start + offset, self.STEP, index))
        heapq.heapify(heap)
        totals = [self._total_steps(a) for a in self.autopilots]
        periods = [a.plant.config.period / a.config.speed for a in self.autopilots]
        finished = [False] * len(self.autopilots)
        slipped = [0.0] * len(self.autopilots)  # wall s each vehicle's schedule has slipped
        stepping = len(self.autopilots)
        by_fd = {link.fileno(): link for link in self.links}
        while stepping and not stop.is_set():
            now = clock()
            while heap and heap[0][0] <= now:
                deadline, kind, index = heapq.heappop(heap)
                if finished[index]:
                    continue
                autopilot = self.autopilots[index]
                if kind == self.HEARTBEAT:
                    autopilot.heartbeat()
                    # Missed beats are skipped, not sent in a burst (as Autopilot.run).
                    beat = max(deadline + HEARTBEAT_PERIOD, now)
                    heapq.heappush(heap, (beat, kind, index))
                    continue
                total = totals[index]
                if total is not None and autopilot.stats.steps >= total:
                    finished[index] = True
                    stepping -= 1
                    continue
                behind = now - deadline
                if behind > periods[index]:
                    self.late_steps += 1
                if behind > autopilot.config.max_lag_steps * periods[index]:
                    slipped[index] += behind
                    autopilot.stats.slips += 1
                    autopilot.stats.slipped_s += behind * autopilot.config.speed
                autopilot.step()
                steps = autopilot.stats.steps
                origin = start + self.offsets[index] + slipped[index]
                next_deadline = origin + steps * periods[index]
                heapq.heappush(heap, (next_deadline, kind, index))
                now = clock()
            timeout = min(max(heap[0][0] - clock(), 0.0), 0.2) if heap else 0.2
            try:
                ready, _, _ = select.select(list(by_fd), [], [], timeout)
            except (OSError, ValueError):
                ready = []
            for fd in ready:
                by_fd[fd].receive(clock)
        for link in self.links:  # what has arrived by the end, as Autopilot.run does
            link.receive(clock)


def _merged(counts: list[dict[str, int]]) -> dict[str, int]:
    merged: dict[str, int] = {}
    for count in counts:
        for key, value in count.items():
            merged[key] = merged.get(key, 0) + value
    return merged


def check_links(vehicles: int, connections: list[str]) -> None:
    """Raise ValueError, naming ``--fleet-connect``, for links a fleet would leave unused:
    more links than vehicles (the blocks of ``connection_for`` give each link a vehicle only
    while there are at least as many vehicles), or one link given twice (``_open_fleet``
    opens a socket per string and keys them by it: both blocks would go out on the last,
    the other left open and unused). ``vehicles`` < 1 is ``run_fleet``'s to refuse."""
    if vehicles >= 1 and len(connections) > vehicles:
        raise ValueError(
            f"--fleet-connect gives {len(connections)} links for --vehicles {vehicles}: "
            f"{len(connections) - vehicles} would carry no vehicle (each link needs one)"
        )
    as_opened = [normalized(connection) for connection in connections]
    for connection in dict.fromkeys(as_opened):
        if as_opened.count(connection) > 1:
            raise ValueError(
                f"--fleet-connect {connection} is given more than once: each link is one "
                "socket with one block of vehicles"
            )


def connection_for(index: int, vehicles: int, connections: list[str]) -> str:
    """The link of vehicle ``index`` (0-based): contiguous, equal blocks in order."""
    return connections[index * len(connections) // vehicles]


class TimedAutopilot(Autopilot):
    """An autopilot that also measures telemetry → command latency: from sending a step's
    last telemetry datagram to the arrival of the first accepted command after it (the
    service answers each complete sample with at most one command)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        #: Its vehicle id (``protocols.keys``): the system id, or link * 256 + system id.
        self.vehicle = self.config.system_id
        self.latencies: list[float] = []  # s
        self.sent_times: list[float] = []  # perf_counter at each latency's telemetry
        self._sent_at: float | None = None
        self._arrived_at: float | None = None

    def heartbeat(self) -> None:
        self._send(self.mapping.heartbeat(vehicle=True))
        self.stats.heartbeats += 1

    def step(self) -> Any:
        sample = super().step()
        self._sent_at = time.perf_counter()
        return sample

    def receive(self, frame: bytes, arrived: float) -> None:
        """A frame routed to this vehicle, with the time its datagram was read."""
        self._arrived_at = arrived
        try:
            self.handle_bytes(frame)
        finally:
            self._arrived_at = None

    def handle_message(self, message: MavMessage) -> None:
        accepted = self.stats.commands_accepted
        super().handle_message(message)
        if self.stats.commands_accepted > accepted and self._sent_at is not None:
            arrived = time.perf_counter() if self._arrived_at is None else self._arrived_at
            self.latencies.append(arrived - self._sent_at)
            self.sent_times.append(self._sent_at)
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
    config = autopilot_config(args, system_id)
    mapping = telemetry_mapping(args)
    return TimedAutopilot(
        plant, link, build_channel_excitations(args.excitation, seed=seed), config, mapping
    )


def fleet_identities(count: int, first: int, links: int, per_link: bool) -> list[tuple[int, int]]:
    """(link number from 1, system id) of each vehicle: contiguous blocks (``connection_for``),
    system ids from ``first`` on, again on each link with ``per_link``."""
    out: list[tuple[int, int]] = []
    block_start: dict[int, int] = {}
    for index in range(count):
        link = index * links // count
        start = block_start.setdefault(link, index)
        out.append((link + 1, first + (index - start if per_link else index)))
    return out


def run_fleet(args: argparse.Namespace) -> int:
    count = args.vehicles
    connections = list(args.fleet_connect) or [args.connect]
    per_link = bool(args.sysid_per_link)
    identities = fleet_identities(count, args.sysid, len(connections), per_link) if count else []
    last = max((system_id for _, system_id in identities), default=args.sysid)
    refused = ""
    if count < 1:
        refused = f"--vehicles must be at least 1, got {count}"
    elif not 1 <= args.sysid <= 255:
        refused = f"--sysid must be 1..255, got {args.sysid}"
    if refused:
        print(f"glider-hil emulate: {refused}", file=sys.stderr)
        return 2
    if last > 255:
        hint = "" if per_link else " (--sysid-per-link: a system-id space per --fleet-connect)"
        print(
            f"glider-hil emulate: --vehicles {count} from --sysid {args.sysid} leaves 1..255"
            + hint,
            file=sys.stderr,
        )
        return 2
    try:
        if args.latency_trace:
            check_latency_trace(args.latency_trace)
        links, autopilots = _open_fleet(args, connections, identities, per_link)
    except (ValueError, OSError) as error:
        print(f"glider-hil emulate: {error}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    wall_period = args.period / args.speed
    offsets = [0.0 if args.phase_locked else i * wall_period / count for i in range(count)]
    scheduler = FleetScheduler(autopilots, list(links.values()), offsets)
    print(
        f"emulating {count} gliders, sysid {args.sysid}-{last}"
        f"{' on each link' if per_link else ''} ({args.scenario}, "
        f"{args.excitation}) on {', '.join(connections)} at {args.speed:g}x",
        file=sys.stderr,
        flush=True,
    )
    cpu_at_start = time.process_time()
    try:
        scheduler.run(stop)
    finally:
        for shared in links.values():
            shared.close()
    summary = _fleet_summary(links, connections, autopilots, scheduler, cpu_at_start)
    print(json.dumps({"emulator": summary}), flush=True)
    if args.latency_trace:
        try:
            write_latency_trace(args.latency_trace, autopilots)
        except OSError as error:  # e.g. its directory removed or the disk full during the run
            print(
                f"glider-hil emulate: --latency-trace {args.latency_trace}: cannot write "
                f"({error.strerror or error})",
                file=sys.stderr,
            )
            return 1
    return 0


def _open_fleet(
    args: argparse.Namespace,
    connections: list[str],
    identities: list[tuple[int, int]],
    per_link: bool,
) -> tuple[dict[str, SharedLink], list[TimedAutopilot]]:
    """One ``SharedLink`` per connection and every vehicle's autopilot attached to its link;
    on ValueError or OSError the links opened so far are closed first."""
    links: dict[str, SharedLink] = {}
    autopilots: list[TimedAutopilot] = []
    try:
        for connection in connections:
            links[connection] = SharedLink(connection)
        for index, (link_number, system_id) in enumerate(identities):
            shared = links[connections[link_number - 1]]
            autopilot = _autopilot(args, system_id, args.seed + index, shared.port())
            assert isinstance(autopilot, TimedAutopilot)
            if per_link:
                autopilot.vehicle = keys.vehicle_id(link_number, system_id)
            if system_id in shared.autopilots:
                raise ValueError(f"system id {system_id} twice on {connections[link_number - 1]}")
            shared.attach(autopilot)
            autopilots.append(autopilot)
    except (ValueError, OSError):
        for shared in links.values():
            shared.link.close()
        raise
    return links, autopilots


def _fleet_summary(
    links: dict[str, SharedLink],
    connections: list[str],
    autopilots: list[TimedAutopilot],
    scheduler: FleetScheduler,
    cpu_at_start: float,
) -> dict[str, Any]:
    per_vehicle: dict[str, Any] = {
        keys.key_id(a.vehicle): a.stats.as_dict(a.codec) for a in autopilots
    }
    steps = sum(v["steps"] for v in per_vehicle.values())
    latency = latency_summary([x for a in autopilots for x in a.latencies])
    return {
        "vehicles": len(autopilots),
        "steps": steps,
        "latency": latency,
        "unrouted": sum(shared.unrouted for shared in links.values()),
        "late_steps": scheduler.late_steps,
        "cpu_s": round(time.process_time() - cpu_at_start, 3),  # while the fleet ran
        "heartbeats": _merged([shared.heartbeats for shared in links.values()]),
        # Each link's own (link n: the n-th --fleet-connect): a service answering every
        # vehicle on its own link is heard on that link only.
        "heartbeats_by_link": {
            str(n + 1): dict(links[connection].heartbeats)
            for n, connection in enumerate(dict.fromkeys(connections))
        },
        "per_vehicle": per_vehicle,
    }


def check_latency_trace(path: str) -> None:
    """Raise ValueError, naming the flag, if ``--latency-trace FILE`` cannot be written: the
    trace is written after the run, and a typo must not cost the run. Nothing is created."""
    directory = os.path.dirname(path) or "."
    if os.path.isdir(path):
        raise ValueError(f"--latency-trace {path}: is a directory")
    if not os.path.isdir(directory):
        raise ValueError(f"--latency-trace {path}: the directory {directory} does not exist")
    if os.path.exists(path):
        if not os.access(path, os.W_OK):
            raise ValueError(f"--latency-trace {path}: the file is not writable")
    elif not os.access(directory, os.W_OK | os.X_OK):
        raise ValueError(f"--latency-trace {path}: the directory {directory} is not writable")


def write_latency_trace(path: str, autopilots: list[TimedAutopilot]) -> None:
    """Every latency with its telemetry's send time (CLOCK_MONOTONIC, comparable across the
    processes of one machine) and vehicle (its vehicle id, ``TimedAutopilot.vehicle``), for a
    benchmark to find when the slow ones were."""
    with _open_trace(path) as f:
        for autopilot in autopilots:
            system_id = autopilot.vehicle
            for sent, latency in zip(autopilot.sent_times, autopilot.latencies, strict=True):
                f.write(f"[{sent:.6f}, {system_id}, {latency:.6f}]\n")


def _open_trace(path: str) -> TextIO:
    """The trace's file for writing. Opened without waiting (``O_NONBLOCK``, which a regular
    file ignores): a named pipe nobody reads would otherwise block the emulator after its
    run for ever."""
    try:
        descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK, 0o666)
    except OSError as error:
        if error.errno == errno.ENXIO:
            raise OSError(errno.ENXIO, "a named pipe no process reads") from None
        raise
    os.set_blocking(descriptor, True)
    return os.fdopen(descriptor, "w")
