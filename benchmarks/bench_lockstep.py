"""Lockstep HIL throughput, printed (not a timed test).

1. Closed-loop steps/s of one vehicle in lockstep over loopback UDP (the campaign's mission:
   forked service with its MCAP log, emulator in this process), beside the in-process
   closed loop of ``experiment --closed-loop`` (``inverse_run``: the same pipeline on the
   same plant, no link) measured in the same run. Run it on one core:

       taskset -c 0 .venv/bin/python benchmarks/bench_lockstep.py --steps 3600

   ``--two-cores E,S --spin-wait US``: the same lockstep missions again in the same run,
   the emulator on core E and the service on core S, each link polling US µs before it
   sleeps (docs/lockstep.md, "Two cores"). ``steady_steps_per_s``: the steps alone,
   without the service's start-up and the plant's build.

2. ``--campaign N``: wall time of a campaign of N seeds x the scenarios (default
   disturbed,nonlinear) with ``--jobs``, start-up included (the ``glider-hil campaign``
   process, as a user runs it):

       .venv/bin/python benchmarks/bench_lockstep.py --campaign 50 --jobs 2

   With the oracle, as ``campaign`` runs by default (``--no-oracle``: without).
   ``--scheduler tcp://HOST:PORT``: the same campaign on a Dask cluster (docs/cluster.md);
   the median CPU s per mission (``cpu_s`` of runs.csv: worker, service, scoring) either way.

3. ``--mission-cpu N``: a mission's CPU s by part (emulator, service, reference-only, oracle,
   scoring), the median of seeds 0..N-1 of each scenario; run it on one core.

4. ``--oracle-cpu N``: the known-model oracle's CPU s per mission alone, seeds 0..N-1 of the
   scenarios (``oracle_trace``, as the campaign runs it).

Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.campaign.hil_run import SHARED_CORES, Placement, run_hil  # noqa: E402
from hil_service.campaign.metrics import score  # noqa: E402
from hil_service.campaign.mission import Mission, oracle_trace, reference_only_trace  # noqa: E402
from hil_service.experiment.closed_loop import inverse_run  # noqa: E402
from protocols.flag_types import spin_wait_us  # noqa: E402


def cpu_seconds() -> float:
    """CPU time of this process and of its reaped children (the forked service)."""
    return sum(_own_and_children())


def _own_and_children() -> tuple[float, float]:
    """CPU time of this process, and of its reaped children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime, children.ru_utime + children.ru_stime


def in_process_rate(mission: Mission) -> dict[str, float]:
    settings = mission.settings()
    started, cpu = time.perf_counter(), cpu_seconds()
    run = inverse_run(settings, mission.plant(), mission.schedule(), None)
    elapsed, used = time.perf_counter() - started, cpu_seconds() - cpu
    assert run.trace.y["depth"].size == mission.steps
    return {"steps_per_s": round(mission.steps / elapsed),
            "steps_per_cpu_s": round(mission.steps / used)}  # fmt: skip


def lockstep_rate(
    mission: Mission, log: bool, placement: Placement = SHARED_CORES
) -> dict[str, object]:
    cpu = cpu_seconds()
    with tempfile.TemporaryDirectory() as directory:
        outcome = run_hil(mission, Path(directory), log=log, placement=placement)
    used = cpu_seconds() - cpu
    if outcome.failure is not None:
        raise RuntimeError(outcome.failure)
    commands = outcome.service["vehicles"]["1"]["commands_sent"]
    return {
        "steps_per_s": round(mission.steps / outcome.wall_s),
        # The steps alone, without the service's start-up and the plant's build.
        "steady_steps_per_s": round(mission.steps / outcome.steps_wall_s),
        # Both processes' CPU time: what the loop costs, whatever else the machine runs.
        "steps_per_cpu_s": round(mission.steps / used),
        "wall_s": round(outcome.wall_s, 3),
        "commands_sent": commands,
        "timeouts": outcome.lockstep["timeouts"],
    }


def campaign_wall(
    seeds: int, scenarios: str, steps: int, jobs: int, oracle: bool, scheduler: str | None = None
) -> dict[str, object]:
    load_before = os.getloadavg()
    cluster = [] if scheduler is None else ["--scheduler", scheduler]
    with tempfile.TemporaryDirectory() as directory:
        started = time.monotonic()
        done = subprocess.run(
            [sys.executable, "-m", "hil_service.cli", "campaign", "--scenarios", scenarios,
             "--seeds", f"0-{seeds - 1}", "--steps", str(steps), "--jobs", str(jobs),
             "--oracle" if oracle else "--no-oracle", "--no-figures",
             "-o", str(Path(directory) / "c"), *cluster],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        wall = time.monotonic() - started
        rows = json.loads((Path(directory) / "c" / "runs.json").read_text())
    cpu = sorted(r["cpu_s"] for r in rows if isinstance(r.get("cpu_s"), (int, float)))
    per_scenario = {
        s: round(statistics.median(r["cpu_s"] for r in rows if r["scenario"] == s), 3)
        for s in scenarios.split(",")
        if any(r["scenario"] == s and isinstance(r.get("cpu_s"), (int, float)) for r in rows)
    }
    result = json.loads(done.stdout.strip().splitlines()[-1])["campaign"]
    # The 1-minute load average before and after (after: this run's own share included).
    load = [round(load_before[0], 2), round(os.getloadavg()[0], 2)]
    return {"missions": result["runs"], "ok": result["ok"], "wall_s": round(wall, 1),
            "jobs": jobs, "steps": steps, "scenarios": scenarios, "oracle": oracle,
            "scheduler": scheduler,
            "median_cpu_s_per_mission": round(statistics.median(cpu), 3) if cpu else None,
            "median_cpu_s_by_scenario": per_scenario,
            "load_average_1min": load}  # fmt: skip


def oracle_cpu(seeds: int, scenarios: str, steps: int) -> dict[str, object]:
    """CPU s of the known-model oracle per mission (``oracle_trace``, as a campaign runs it)."""
    per: dict[str, list[float]] = {}
    for scenario in scenarios.split(","):
        for seed in range(seeds):
            mission = Mission(scenario, seed, steps)
            started = time.process_time()
            oracle_trace(mission)
            per.setdefault(scenario, []).append(time.process_time() - started)
    return {
        scenario: {
            "missions": len(values),
            "mean_cpu_s": round(sum(values) / len(values), 3),
            "max_cpu_s": round(max(values), 3),
        }
        for scenario, values in per.items()
    }


def mission_cpu(seeds: int, scenarios: str, steps: int) -> dict[str, object]:
    """A campaign mission's CPU s by part, median over seeds 0..N-1 per scenario, each part
    as the campaign's worker runs it (``runner.execute``): the lockstep run's emulator (this
    process) and service (its forked child), reference-only, the oracle, the scoring."""
    per: dict[str, dict[str, list[float]]] = {}
    for scenario in scenarios.split(","):
        parts = per.setdefault(scenario, {})
        for seed in range(seeds):
            mission = Mission(scenario, seed, steps)
            own, children = _own_and_children()
            with tempfile.TemporaryDirectory() as directory:
                outcome = run_hil(mission, Path(directory))
            if outcome.failure is not None:
                raise RuntimeError(outcome.failure)
            after_own, after_children = _own_and_children()
            timed = {"emulator": after_own - own, "service": after_children - children}
            started = time.process_time()
            reference = reference_only_trace(mission)
            timed["reference_only"] = time.process_time() - started
            started = time.process_time()
            oracle, _ = oracle_trace(mission)
            timed["oracle"] = time.process_time() - started
            started = time.process_time()
            score(mission, outcome.trace, reference, oracle, {})
            timed["scoring"] = time.process_time() - started
            timed["total"] = sum(timed.values())
            for part, seconds in timed.items():
                parts.setdefault(part, []).append(seconds)
    return {
        scenario: {part: round(statistics.median(values), 3) for part, values in parts.items()}
        for scenario, parts in per.items()
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=3600)
    parser.add_argument("--scenario", default="disturbed")
    parser.add_argument("--repeats", type=int, default=3, help="best of N (a shared machine)")
    parser.add_argument("--campaign", type=int, default=0, metavar="SEEDS")
    parser.add_argument("--scenarios", default="disturbed,nonlinear")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--oracle",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="--campaign: with the known-model oracle (default, as campaign)",
    )
    parser.add_argument("--scheduler", default=None, help="--campaign: on this Dask scheduler")
    parser.add_argument(
        "--oracle-cpu",
        type=int,
        default=0,
        metavar="SEEDS",
        help="CPU s of the oracle alone per mission, seeds 0..SEEDS-1",
    )
    parser.add_argument("--mission-cpu", type=int, default=0, metavar="SEEDS",
                        help="a mission's CPU s by part, median of seeds 0..SEEDS-1")  # fmt: skip
    parser.add_argument(
        "--two-cores",
        default=None,
        metavar="E,S",
        help="also run the lockstep missions with the emulator on core E and "
        "the service on core S, each polling --spin-wait µs",
    )
    parser.add_argument("--spin-wait", type=spin_wait_us, default=0.0, metavar="US",
                        help="with --two-cores: each side's poll before it sleeps")  # fmt: skip
    args = parser.parse_args()
    if args.campaign:
        print(json.dumps({"campaign": campaign_wall(args.campaign, args.scenarios, args.steps,
                                                    args.jobs, args.oracle,
                                                    args.scheduler)}))  # fmt: skip
        return 0
    if args.mission_cpu:
        figures = mission_cpu(args.mission_cpu, args.scenarios, args.steps)
        print(json.dumps({"mission_cpu_s": figures}))
        return 0
    if args.oracle_cpu:
        print(json.dumps({"oracle_cpu": oracle_cpu(args.oracle_cpu, args.scenarios, args.steps)}))
        return 0
    mission = Mission(args.scenario, 0, args.steps, args.steps // 3, max(2, args.steps // 6))
    in_process = [in_process_rate(mission) for _ in range(args.repeats)]
    logged = [lockstep_rate(mission, log=True) for _ in range(args.repeats)]
    unlogged = [lockstep_rate(mission, log=False) for _ in range(args.repeats)]
    affinity = sorted(os.sched_getaffinity(0))
    figures = {
        "cores": affinity,
        "steps": args.steps,
        "scenario": args.scenario,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "in_process": max(in_process, key=lambda r: r["steps_per_s"]),
        "lockstep_udp_logged": max(logged, key=lambda r: r["steps_per_s"]),
        "lockstep_udp_no_log": max(unlogged, key=lambda r: r["steps_per_s"]),
    }
    if args.two_cores:
        figures.update(two_cores(mission, args.two_cores, args.spin_wait, args.repeats))
    print(json.dumps(figures))
    return 0


def two_cores(mission: Mission, cores: str, spin_wait: float, repeats: int) -> dict[str, object]:
    """The lockstep missions again with a core each (docs/lockstep.md, "Two cores"): this
    process (the emulator) on core E, the service on core S, both polling ``spin_wait`` s."""
    emulator_core, service_core = (int(core) for core in cores.split(","))
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {emulator_core})
    placement = Placement(spin_wait, frozenset({service_core}))
    try:
        logged = [lockstep_rate(mission, True, placement) for _ in range(repeats)]
        unlogged = [lockstep_rate(mission, False, placement) for _ in range(repeats)]
    finally:
        os.sched_setaffinity(0, before)
    return {
        "two_cores": {"emulator": emulator_core, "service": service_core,
                      "spin_wait_us": round(spin_wait * 1e6)},
        "lockstep_two_cores_logged": max(logged, key=lambda r: r["steps_per_s"]),
        "lockstep_two_cores_no_log": max(unlogged, key=lambda r: r["steps_per_s"]),
    }  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
