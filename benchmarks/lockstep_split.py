"""Where a lockstep step's time goes: each process's CPU in lockstep beside the same work
done warm, and the round trip of two bare processes (docs/benchmarks.md, "What a lockstep
step costs on one core").

1. One lockstep mission as the campaign runs it (``hil_run.run_hil``: the emulator in this
   process, the service forked, its MCAP log written): steps/s, and each process's CPU µs
   per step (this process's CPU over the emulator's run; the service's from its rusage).
   The emulator's datagrams and the service's replies are recorded on the way.
2. The same work warm, each side alone in this process, with nothing to wait for:
   * the emulator: the same vehicle stepped and flushed to a socket nobody reads, each
     step handed the service's recorded reply;
   * the service: wired as the mission's (``hil_run.service_config``, its log written),
     fed the emulator's recorded datagrams, sending its commands and releases to a socket
     nobody reads.
3. Two bare processes bouncing a datagram over loopback UDP (``select`` then ``recvfrom``,
   as both sides of lockstep wait): the least a step's two wake-ups cost.
4. The same mission with no second process: the service driven in the emulator's thread,
   each flushed datagram handed to it over the same loopback sockets (its reply read back
   by the emulator as in lockstep). No context switch at all: what a step costs when the
   two sides' work alternates on one core with nothing but the caches between them.

``--round-trips E,S [--spin-wait US]`` prints only the bare round trips: on core E, across
cores E and S with both processes asleep in ``select``, and across them polling (docs/
lockstep.md, "Two cores").

Run it on one core, as ``bench_lockstep.py``:

    taskset -c 0 .venv/bin/python benchmarks/lockstep_split.py [--steps 3600] [--repeats 3]

Prints one JSON object: the best of ``--repeats`` for each figure.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.campaign import hil_run  # noqa: E402
from hil_service.campaign.mission import Mission  # noqa: E402
from plant_emulator.autopilot import Autopilot, AutopilotConfig  # noqa: E402
from plant_emulator.lockstep import LockstepRunner  # noqa: E402
from protocols import lockstep as lockstep_protocol  # noqa: E402
from protocols.flag_types import spin_wait_us  # noqa: E402
from protocols.mavlink_io import Link, readable  # noqa: E402


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def lockstep_mission(mission: Mission) -> tuple[dict[str, float], list[bytes], list[bytes]]:
    """One mission: its figures, the emulator's datagrams and the service's replies."""
    sent: list[bytes] = []
    received: list[bytes] = []
    batched = lockstep_protocol.BatchedLink
    flush, recv = batched.flush, batched.recv
    run_emulator = hil_run._run_emulator
    emulator_cpu: list[float] = []

    def recording_flush(self: lockstep_protocol.BatchedLink) -> None:
        held = getattr(self, "_held", None)
        if held:
            sent.append(b"".join(held))
        flush(self)

    def recording_recv(self: lockstep_protocol.BatchedLink) -> bytes:
        data = recv(self)
        if data:
            received.append(data)
        return data

    def timed_emulator(*args: object, **kwargs: object) -> object:
        started = time.process_time()
        try:
            return run_emulator(*args, **kwargs)  # type: ignore[arg-type]
        finally:
            emulator_cpu.append(time.process_time() - started)

    batched.flush, batched.recv = recording_flush, recording_recv  # type: ignore[method-assign]
    hil_run._run_emulator = timed_emulator  # type: ignore[assignment]
    children = _children_cpu()
    try:
        with tempfile.TemporaryDirectory() as directory:
            outcome = hil_run.run_hil(mission, Path(directory), log=True)
    finally:
        batched.flush, batched.recv = flush, recv  # type: ignore[method-assign]
        hil_run._run_emulator = run_emulator  # type: ignore[assignment]
    if outcome.failure is not None:
        raise RuntimeError(outcome.failure)
    service_cpu = _children_cpu() - children
    steps = mission.steps
    figures = {
        "steps_per_s": steps / outcome.wall_s,
        "emulator_cpu_us_per_step": 1e6 * emulator_cpu[0] / steps,
        # Its whole life: forked with everything imported, so this is the mission's share
        # but for closing the log.
        "service_cpu_us_per_step": 1e6 * service_cpu / steps,
    }
    return figures, sent, received


def _sink() -> socket.socket:
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 16)
    return sink


def _vehicle(mission: Mission, port: int) -> tuple[Link, Autopilot, LockstepRunner]:
    """The mission's vehicle as the campaign runs it, sending to ``port`` on loopback."""
    link = Link(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    autopilot = Autopilot(
        mission.plant(),  # type: ignore[arg-type]
        link,
        mission.excitations(),
        AutopilotConfig(system_id=1, duration=mission.steps * mission.period),
    )
    return link, autopilot, LockstepRunner(autopilot, 1.0)


def warm_emulator(mission: Mission, replies: list[bytes]) -> float:
    """CPU µs per step of the emulator alone: step, flush, handle the recorded reply."""
    sink = _sink()
    link, autopilot, runner = _vehicle(mission, sink.getsockname()[1])
    batched = runner.link
    steps = min(mission.steps, len(replies))
    started = time.process_time()
    for k in range(steps):
        autopilot.send_periodic(runner.clock())
        autopilot.step()
        batched.flush()
        autopilot.handle_bytes(replies[k])
    used = time.process_time() - started
    link.close()
    sink.close()
    return 1e6 * used / steps


def warm_service(mission: Mission, datagrams: list[bytes]) -> float:
    """CPU µs per step of the mission's service alone, fed the emulator's datagrams (its
    log's writer thread included: ``process_time`` counts every thread)."""
    sink = _sink()
    source = sink.getsockname()
    with tempfile.TemporaryDirectory() as directory:
        link = Link("udpin:127.0.0.1:0", source_system=255, source_component=191)
        wired = hil_run.wire_mission_service(mission, link, Path(directory))
        service = wired.service
        started = time.process_time()
        for data in datagrams:
            service.process_datagram(data, datagram=True, source=source)
        wired.close()  # the log drained: its compression and writes are counted
        used = time.process_time() - started
    sink.close()
    return 1e6 * used / len(datagrams)


def inline_mission(mission: Mission) -> dict[str, float]:
    """Steps/s and CPU µs per step of the mission with the service driven in this thread
    (point 4 of the module docstring); its log written, as the forked service's is."""
    with tempfile.TemporaryDirectory() as directory:
        link = Link("udpin:127.0.0.1:0", source_system=255, source_component=191)
        with socket.socket(fileno=os.dup(link.fileno())) as bound:
            port = bound.getsockname()[1]
        wired = hil_run.wire_mission_service(mission, link, Path(directory))
        service = wired.service
        vehicle_link, _, runner = _vehicle(mission, port)
        batched = runner.link
        flush = batched.flush

        def flush_and_serve() -> None:
            flush()
            while link.wait(0.0):
                data, source = link.recv_from()
                if not data:
                    break
                service.process_datagram(data, link.datagram, source)
            service.tick()

        batched.flush = flush_and_serve  # type: ignore[method-assign]
        started, cpu = time.perf_counter(), time.process_time()
        runner.run()
        elapsed = time.perf_counter() - started
        wired.close()  # the log drained: its compression and writes are counted
        used = time.process_time() - cpu
        vehicle_link.close()
    if runner.stats.timeouts:
        raise RuntimeError(f"the inline mission timed out {runner.stats.timeouts} times")
    return {
        "inline_steps_per_s": mission.steps / elapsed,
        "inline_cpu_us_per_step": 1e6 * used / mission.steps,
    }


def bare_round_trip(
    count: int = 20_000, cores: tuple[int, int] | None = None, spin: float = 0.0
) -> float:
    """µs per round trip of a datagram between two processes that wait as lockstep's two
    sides do (``protocols.mavlink_io.readable``: ``select``, polled first for ``spin`` s);
    ``cores``: this process on the first, the bouncing one on the second."""
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    a.bind(("127.0.0.1", 0))
    b.bind(("127.0.0.1", 0))
    telemetry, reply = b"t" * 200, b"c" * 40  # about a step's datagram and its answer
    affinity = os.sched_getaffinity(0)
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            if cores is not None:
                os.sched_setaffinity(0, {cores[1]})
            for _ in range(count):
                if not readable([b.fileno()], 5.0, spin):
                    break
                b.recvfrom(65536)
                b.sendto(reply, a.getsockname())
            code = 0
        finally:
            os._exit(code)
    if cores is not None:
        os.sched_setaffinity(0, {cores[0]})
    try:
        started = time.perf_counter()
        for _ in range(count):
            a.sendto(telemetry, b.getsockname())
            if not readable([a.fileno()], 5.0, spin):
                raise RuntimeError("the bouncing process stopped answering")
            a.recvfrom(65536)
        elapsed = time.perf_counter() - started
    finally:
        os.sched_setaffinity(0, affinity)
        os.waitpid(pid, 0)
        a.close()
        b.close()
    return 1e6 * elapsed / count


def round_trips(cores: tuple[int, int], spin: float) -> dict[str, float]:
    """The bare round trip on one core, across ``cores`` asleep, and across them polling
    ``spin`` s (docs/lockstep.md, "Two cores")."""
    return {
        "round_trip_one_core_us": round(bare_round_trip(cores=(cores[0], cores[0])), 1),
        "round_trip_two_cores_asleep_us": round(bare_round_trip(cores=cores), 1),
        "round_trip_two_cores_polling_us": round(bare_round_trip(cores=cores, spin=spin), 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3600)
    parser.add_argument("--scenario", default="disturbed")
    parser.add_argument("--repeats", type=int, default=3, help="best of N (a shared machine)")
    parser.add_argument(
        "--round-trips",
        default=None,
        metavar="E,S",
        help="only the bare round trips: on core E, across cores E and S asleep, and across "
        "them polling --spin-wait µs",
    )
    parser.add_argument("--spin-wait", type=spin_wait_us, default=300e-6, metavar="US")
    args = parser.parse_args()
    if args.round_trips:
        first, second = (int(core) for core in args.round_trips.split(","))
        print(json.dumps(round_trips((first, second), args.spin_wait)))
        return 0
    mission = Mission(args.scenario, 0, args.steps)
    runs = []
    for _ in range(args.repeats):
        figures, sent, received = lockstep_mission(mission)
        figures["warm_emulator_cpu_us_per_step"] = warm_emulator(mission, received)
        figures["warm_service_cpu_us_per_step"] = warm_service(mission, sent)
        figures["bare_round_trip_us"] = bare_round_trip()
        figures.update(inline_mission(mission))
        runs.append(figures)
    best = {
        key: (max if key.endswith("steps_per_s") else min)(run[key] for run in runs)
        for key in runs[0]
    }
    lockstep_us = best["emulator_cpu_us_per_step"] + best["service_cpu_us_per_step"]
    warm_us = best["warm_emulator_cpu_us_per_step"] + best["warm_service_cpu_us_per_step"]
    round_trip = best["bare_round_trip_us"]
    result = {
        "cores": sorted(os.sched_getaffinity(0)),
        "steps": args.steps,
        "scenario": args.scenario,
        **{key: round(value, 1) for key, value in best.items()},
        "lockstep_cpu_us_per_step": round(lockstep_us, 1),
        "warm_cpu_us_per_step": round(warm_us, 1),
        # What the two processes cost beyond their warm work and a bare round trip:
        # caches and TLBs refilled after each switch, the waits' own syscalls.
        "switching_penalty_us_per_step": round(lockstep_us - warm_us - round_trip, 1),
        "steps_per_s_if_warm": round(1e6 / (warm_us + round_trip)),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
