"""The fleet targets on this machine: N vehicles at 10 samples/s each, two
service processes (half the system ids each, ``--sysid`` ranges), one Zenoh router
(``glider-hil router``), one emulator process (``emulate --vehicles N``), a subscriber on
the router. Printed per fleet size:

* loss: samples the services assembled (their summaries) against telemetry the subscriber
  on the router received, and against the steps the emulator sent;
* fleet coverage: vehicles listed by ``glider-hil fleet --json`` mid-run, of N;
* telemetry → command latency (p50, p99, max): measured in the emulator, from sending a
  step's last telemetry datagram to receiving the command that answers it (control on,
  a depth setpoint for every vehicle, after ``--burn-in`` samples);
* where the time goes: CPU seconds of each of our processes during the run (router,
  services, emulator; per sample in ms), against the machine's CPU pressure over the same
  interval (``/proc/pressure/cpu`` "some": the share of the time some runnable task waited
  for a core) and the load average at the start;
* the largest fleet of the sizes tried whose p99 stays under 20 ms.

``benchmarks/fleet_stages.py`` times the stages inside one process (emulator step, service
sample → command, the health burst) without the other processes competing.

The emulated vehicles step spread evenly over the 100 ms period, as independent vehicles'
clocks are; ``--phase-locked`` makes them all step at once (each service then receives its
whole fleet's telemetry in one burst, and the last vehicle of the burst waits for the others).

``--services 1`` puts the whole fleet on one service (``--sysid 1-N``), ``--rate`` sets the
samples/s of each vehicle (default 10): ``--services 1 --sizes 250 --rate 4`` is the sample
rate of 1,000 gliders at 1 Hz on one service process (a MAVLink link tells 255 system ids
apart, docs/cluster.md), ``--sizes 250 --rate 1`` the largest fleet one link can carry.

``--links L`` (with ``--services 1``) is a fleet beyond one link's 255 system ids: one
service with L ``--mavlink`` links and ``--vehicle-ids link``, the emulator's vehicles in L
blocks numbered from 1 on each (``--sysid-per-link``), a gateway each:
``--services 1 --links 4 --sizes 1000 --rate 1`` is 1,000 gliders at 1 Hz on one service.
``--pin-service CPU`` pins the service process (every thread) to one core, as ``taskset -c``;
with ``--isolate-service`` everything else of the run (this harness and its subscriber, the
router, the emulator, the ``fleet`` listing) runs on the other cores, so that the service
has its core to itself: "one service on one core", not one core shared with the harness.

Run: .venv/bin/python benchmarks/bench_fleet.py [--sizes 100,150,200] [--seconds 40]
         [--rate 10] [--services 2] [--target-ms 20] [--links 4] [--pin-service 0]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from hil_service.cli.processes import (  # noqa: E402
    last_json,
    start_service,
    start_verb,
    stop_process,
    wait_for_line,
)
from hil_service.cli.router import ROUTER_READY  # noqa: E402
from hil_service.listeners.zenoh_shutdown import close_at_exit  # noqa: E402
from plant_emulator.fleet import connection_for, fleet_identities  # noqa: E402
from protocols import keys  # noqa: E402

RATE = 10.0  # samples/s per vehicle (plant period 1 s at speed 10)
TARGET_MS = 20.0
BURN_IN = 50


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a live process (all its threads), s."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_pressure_us() -> int | None:
    """Total µs during which some runnable task waited for a CPU (PSI), None without PSI."""
    try:
        with open("/proc/pressure/cpu") as f:
            some = f.readline().split()
    except OSError:
        return None
    return int(some[-1].partition("=")[2])


def pin(pid: int, cpus: set[int]) -> None:
    """Every thread of ``pid`` on ``cpus`` (threads it starts later inherit it)."""
    for task in os.listdir(f"/proc/{pid}/task"):
        os.sched_setaffinity(int(task), cpus)


def client_session(router: str) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([router]))
    return close_at_exit(zenoh.open(config))


class Counts:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.telemetry: Counter[int] = Counter()
        self.commands: Counter[int] = Counter()
        self.health: list[tuple[float, int]] = []  # (perf_counter at arrival, system id)

    def on_telemetry(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse(str(sample.key_expr))
        if parsed is not None:
            with self.lock:
                self.telemetry[parsed.system_id] += 1

    def total(self) -> int:
        with self.lock:
            return sum(self.telemetry.values())

    def seen(self) -> int:
        with self.lock:
            return len(self.telemetry)

    def on_health(self, sample: zenoh.Sample) -> None:
        arrived = time.perf_counter()
        parsed = keys.parse(str(sample.key_expr))
        if parsed is not None:
            with self.lock:
                self.health.append((arrived, parsed.system_id))

    def on_command(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse(str(sample.key_expr))
        if parsed is not None:
            with self.lock:
                self.commands[parsed.system_id] += 1


def wait_until(
    condition: Callable[[], bool], process: subprocess.Popen[str], timeout: float
) -> None:
    """Poll ``condition`` until true, ``process`` ends or ``timeout`` s pass (then go on: what
    follows measures what there is)."""
    deadline = time.monotonic() + timeout
    while not condition() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)


def bursts(times: list[float], gap: float = 0.05) -> list[tuple[float, float]]:
    """(first, last) of each run of arrival times no more than ``gap`` s apart."""
    out: list[tuple[float, float]] = []
    for t in sorted(times):
        if out and t - out[-1][1] <= gap:
            out[-1] = (out[-1][0], t)
        else:
            out.append((t, t))
    return out


def within(t: float, windows: list[tuple[float, float]]) -> bool:
    return any(first <= t <= last for first, last in windows)


def percentile_ms(values: list[float], q: float) -> float | None:
    ordered = sorted(values)
    if not ordered:
        return None
    return round(1000 * ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)


def tail_attribution(
    trace: list[tuple[float, int, float]],
    holder: dict[int, int],
    health: list[tuple[float, int]],
    listing: tuple[float, float],
) -> dict[str, Any]:
    """When the slowest 1 % of telemetry -> command latencies happened: the share of them
    whose telemetry was sent while the service holding the vehicle (or the other one) was
    publishing its vehicles' health (from 15 ms before the first health message reached the
    subscriber to the last), or while ``fleet --json`` ran; beside each, the share of all
    latencies in the same windows (what chance alone would give). Also how many distinct
    100 ms slots hold them (few slots: stalls that hit many vehicles at once). The health
    windows tell something only of a service that publishes its fleet's health in a burst
    (not round robin): spread over the second, they cover most of the run."""
    if not trace:
        return {}
    ordered = sorted(latency for _, _, latency in trace)
    threshold = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]
    services = sorted(set(holder.values()))
    windows = {
        s: [(a - 0.015, b) for a, b in bursts([t for t, i in health if holder.get(i) == s])]
        for s in services
    }
    slow = [(t, i) for t, i, latency in trace if latency >= threshold]

    def share(rows: list[tuple[float, int]], test: Callable[[float, int], bool]) -> float:
        return round(sum(1 for t, i in rows if test(t, i)) / max(len(rows), 1), 3)

    every = [(t, i) for t, i, _ in trace]
    slots: dict[int, list[int]] = {}  # 100 ms slot -> the service of each slow latency in it
    for t, i in slow:
        slots.setdefault(int(t / 0.1), []).append(holder[i])
    start = min(t for t, _ in every)
    own = lambda t, i: within(t, windows[holder[i]])  # noqa: E731
    other = lambda t, i: any(within(t, w) for s, w in windows.items() if s != holder[i])  # noqa: E731
    fleet = lambda t, i: listing[0] <= t <= listing[1]  # noqa: E731
    return {
        "p99_threshold_ms": round(1000 * threshold, 2),
        "slow": len(slow),
        "health_bursts_per_service": [len(windows[s]) for s in services],
        "health_burst_ms_median": round(
            1000 * statistics.median(b - a - 0.015 for w in windows.values() for a, b in w), 2
        ) if any(windows.values()) else None,
        "slow_in_own_health_burst": share(slow, own),
        "all_in_own_health_burst": share(every, own),
        "slow_in_other_health_burst": share(slow, other),
        "all_in_other_health_burst": share(every, other),
        "slow_during_fleet_listing": share(slow, fleet),
        "all_during_fleet_listing": share(every, fleet),
        # The same latencies without those whose telemetry was sent while `fleet` ran.
        "p99_ms_outside_fleet_listing": percentile_ms(
            [latency for t, _, latency in trace if not listing[0] <= t <= listing[1]], 0.99
        ),
        "slots_100ms_holding_slow": len(slots),
        # A slot whose slow latencies are on vehicles of both services: a stall of the
        # emulator (or the whole machine), not of one service.
        "slots_with_both_services": sum(1 for held in slots.values() if len(set(held)) > 1),
        # When the slow slots were (s since the first telemetry sent) and how many slow
        # latencies each holds: a stall on a schedule (a periodic collection, the listing)
        # shows as its period.
        "slow_slots_s": [
            [round(slot * 0.1 - start, 1), len(slots[slot])] for slot in sorted(slots)
        ],
        "fleet_listing_s": [round(listing[0] - start, 1), round(listing[1] - start, 1)],
    }  # fmt: skip


def run_fleet(
    vehicles: int,
    seconds: float,
    phase_locked: bool = False,
    rate: float = RATE,
    service_count: int = 2,
    link_count: int = 0,
    pin_service: int | None = None,
    health_period: float = 1.0,
    isolate_service: bool = False,
) -> dict[str, Any]:
    """``link_count`` > 0: one service with that many links, a system-id space each."""
    if link_count and service_count != 1:
        raise ValueError("--links needs --services 1")
    others: set[int] | None = None
    own_cpus = os.sched_getaffinity(0)  # given back at the end, for the next fleet size
    if isolate_service:
        if pin_service is None:
            raise ValueError("--isolate-service needs --pin-service")
        others = own_cpus - {pin_service}
        if not others:
            raise ValueError("--isolate-service needs a core besides the service's")
        pin(os.getpid(), others)  # the processes started from here inherit it
    router = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    processes: list[subprocess.Popen[str]] = []
    session = None
    scratch = tempfile.TemporaryDirectory()
    trace_path = str(Path(scratch.name) / "latencies.jsonl")
    try:
        router_process = start_verb("router", "--listen", router)
        processes.append(router_process)
        wait_for_line(router_process, ROUTER_READY, 60)
        # The services' --sysid ranges are the emulator's blocks (connection_for).
        links = list(range(service_count))
        udp = [free_port(socket.SOCK_DGRAM) for _ in links]
        block = [connection_for(i, vehicles, links) for i in range(vehicles)]
        ranges = [f"{block.index(link) + 1}-{vehicles - block[::-1].index(link)}" for link in links]
        services = []
        if link_count:
            udp = [free_port(socket.SOCK_DGRAM) for _ in range(link_count)]
            service = start_service(
                *[arg for port in udp for arg in ("--mavlink", f"udpin:127.0.0.1:{port}")],
                "--vehicle-ids", "link", "--max-vehicles", str(vehicles),
                "--health-period", str(health_period),
                "--zenoh-connect", router, "--zenoh-mode", "client", "--no-log",
                "--burn-in", str(BURN_IN), "--control", timeout=120,
            )  # fmt: skip
            processes.append(service)
            services.append(service)
        for sysids, port in [] if link_count else zip(ranges, udp, strict=True):
            service = start_service(
                "--mavlink", f"udpin:127.0.0.1:{port}", "--sysid", sysids,
                "--zenoh-connect", router, "--zenoh-mode", "client", "--no-log",
                "--burn-in", str(BURN_IN), "--control", timeout=120,
            )  # fmt: skip
            processes.append(service)
            services.append(service)
        if pin_service is not None:
            for service in services:
                pin(service.pid, {pin_service})
        identities = fleet_identities(vehicles, 1, len(udp), per_link=bool(link_count))
        ids = [keys.vehicle_id(n, s) if link_count else s for n, s in identities]
        session = client_session(router)
        counts = Counts()
        subscribers = [
            session.declare_subscriber(f"{keys.ROOT}/*/{keys.TELEMETRY}", counts.on_telemetry),
            session.declare_subscriber(f"{keys.ROOT}/*/{keys.COMMAND_BALLAST}", counts.on_command),
            session.declare_subscriber(f"{keys.ROOT}/*/{keys.HEALTH}", counts.on_health),
        ]
        time.sleep(1.0)  # the subscriptions reach the router and the services
        for system_id in ids:
            session.put(keys.setpoint(system_id, "depth"), json.dumps({"value": 16.0}))
        emulator = start_verb(
            "emulate", "--vehicles", str(vehicles), "--sysid", "1", "--speed", str(rate),
            "--duration", str(seconds * rate), "--scenario", "paper",
            *(["--phase-locked"] if phase_locked else []),
            *(["--sysid-per-link"] if link_count else []),
            "--latency-trace", trace_path,
            *[arg for port in udp for arg in ("--fleet-connect", f"udpout:127.0.0.1:{port}")],
        )  # fmt: skip
        processes.append(emulator)
        # From the first telemetry on (the emulator's start-up, imports included, may take
        # seconds on a loaded machine: a timer started at its launch once listed the fleet
        # before any vehicle had appeared).
        wait_until(lambda: counts.total() > 0, emulator, 180)
        started = time.monotonic()
        load_average = os.getloadavg()[0]
        ours = {"router": router_process}
        ours.update({f"service_{n + 1}": p for n, p in enumerate(services)})
        cpu_before = {name: cpu_seconds(p.pid) for name, p in ours.items()}
        pressure_before = cpu_pressure_us()
        # Mid-run, once every vehicle has appeared: what `fleet` lists.
        wait_until(lambda: counts.seen() >= vehicles, emulator, seconds)
        time.sleep(max(0.0, seconds * 0.6 - (time.monotonic() - started)))
        listing_started = time.perf_counter()
        fleet = subprocess.run(
            [sys.executable, "-m", "hil_service.cli", "fleet", "--zenoh-connect", router,
             "--json", "--wait", "3"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        listing = (listing_started, time.perf_counter())
        listed = json.loads(fleet.stdout)["vehicles"] if fleet.returncode == 0 else []
        emulator_out, emulator_err = emulator.communicate(timeout=seconds * 4 + 120)
        wall = time.monotonic() - started
        cpu = {name: cpu_seconds(p.pid) - cpu_before[name] for name, p in ours.items()}
        pressure_after = cpu_pressure_us()
        time.sleep(1.0)  # the last publications reach the subscriber
        for subscriber in subscribers:
            subscriber.undeclare()
        summaries = []
        for service in services:
            out, _ = stop_process(service)
            summaries.append(last_json(out, "service"))
        emulated = last_json(emulator_out, "emulator")
        if not emulated:
            raise RuntimeError(f"the emulator printed no summary:\n{emulator_err[-2000:]}")
        assembled = sum(s.get("counters", {}).get("samples", 0) for s in summaries)
        with open(trace_path) as f:
            trace = [tuple(json.loads(line)) for line in f]
        holder = {i: connection_for(n, vehicles, links) for n, i in enumerate(ids)}
        with counts.lock:
            tail = tail_attribution(trace, holder, list(counts.health), listing)  # type: ignore[arg-type]
            received = sum(counts.telemetry.values())
            seen = len(counts.telemetry)
            commands = sum(counts.commands.values())
        return {
            "vehicles": vehicles,
            "services": service_count,
            "links": link_count or service_count,
            "service_pinned_to_cpu": pin_service,
            "others_on_cpus": None if others is None else sorted(others),
            "health_period_s": health_period,
            "rate_per_vehicle": rate,
            "samples_per_s_per_service": round(vehicles * rate / service_count, 1),
            "phase_locked": phase_locked,
            "wall_s": round(wall, 1),
            "steps_sent": emulated["steps"],
            "samples_assembled_by_services": assembled,
            "telemetry_received_on_router": received,
            "loss_services_to_subscriber": round(1 - received / assembled, 6)
            if assembled
            else None,
            "loss_emulator_to_services": round(1 - assembled / emulated["steps"], 6),
            "samples_lost": emulated["steps"] - assembled,
            "vehicles_seen_by_subscriber": seen,
            "fleet_listed": len(listed),
            "fleet_coverage": round(len(listed) / vehicles, 3),
            **(
                {}
                if fleet.returncode == 0
                else {"fleet_failed": [fleet.returncode, fleet.stderr[-500:]]}
            ),
            "commands_published": commands,
            "latency": emulated["latency"],
            "late_steps": emulated.get("late_steps"),
            "tail": tail,
            "load_average_1min_at_start": round(load_average, 2),
            "cpu_pressure_some": None
            if pressure_before is None or pressure_after is None
            else round((pressure_after - pressure_before) / 1e6 / wall, 3),
            "cpu_s": {
                **{name: round(value, 2) for name, value in cpu.items()},
                "emulator": emulated.get("cpu_s"),
            },
            "cores_per_service": [
                round(cpu[f"service_{n + 1}"] / wall, 3) for n in range(service_count)
            ],
            "cpu_ms_per_sample": {
                "each_service": round(
                    1000 * sum(cpu[f"service_{n + 1}"] for n in links) / max(assembled, 1), 3
                ),
                "router": round(1000 * cpu["router"] / max(assembled, 1), 3),
                "emulator_per_step": round(
                    1000 * (emulated.get("cpu_s") or 0.0) / max(emulated["steps"], 1), 3
                ),
            },
            "cores_used_by_the_fleet": round(
                (sum(cpu.values()) + (emulated.get("cpu_s") or 0.0)) / wall, 2
            ),
        }
    finally:
        scratch.cleanup()
        if session is not None:
            session.close()
        for process in reversed(processes):
            if process.poll() is None:
                stop_process(process)
        if isolate_service:
            pin(os.getpid(), own_cpus)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sizes", default="100,150,200", help="fleet sizes, comma separated")
    parser.add_argument("--seconds", type=float, default=40.0, help="wall s per fleet size")
    parser.add_argument(
        "--phase-locked",
        action="store_true",
        help="all vehicles step at the same instant (default: spread over the period)",
    )
    parser.add_argument(
        "--rate", type=float, default=RATE, help="samples/s per vehicle (default %(default)s)"
    )
    parser.add_argument(
        "--services",
        type=int,
        choices=(1, 2),
        default=2,
        help="service processes sharing the fleet in --sysid ranges (default 2)",
    )
    parser.add_argument(
        "--links",
        type=int,
        default=0,
        help="with --services 1: that many links, a system-id space each (--vehicle-ids link)",
    )
    parser.add_argument(
        "--pin-service", type=int, default=None, metavar="CPU", help="run the service on one core"
    )
    parser.add_argument(
        "--isolate-service",
        action="store_true",
        help="with --pin-service: everything else of the run on the other cores",
    )
    parser.add_argument(
        "--health-period", type=float, default=1.0, help="with --links: serve --health-period"
    )
    parser.add_argument(
        "--target-ms", type=float, default=TARGET_MS, help="p99 target (default %(default)s)"
    )
    args = parser.parse_args()
    results = []
    for size in (int(s) for s in args.sizes.split(",")):
        result = run_fleet(
            size, args.seconds, args.phase_locked, args.rate, args.services, args.links,
            args.pin_service, args.health_period, args.isolate_service,
        )  # fmt: skip
        print(json.dumps(result), flush=True)
        results.append(result)
    meeting = [
        r["vehicles"]
        for r in results
        if r["latency"].get("count") and r["latency"]["p99_ms"] < args.target_ms
    ]
    print(
        json.dumps(
            {
                "target_p99_ms": args.target_ms,
                "largest_fleet_meeting_target": max(meeting) if meeting else None,
                "sizes_tried": [r["vehicles"] for r in results],
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
