"""Where a campaign mission's CPU time goes: cProfile in each of its processes.

One lockstep mission as the campaign runs it (``hil_run.run_hil``: the emulator in this
process, the service forked), each process under its own ``cProfile``, then the mission's
scoring (reference-only run, oracle, metrics) profiled in this process. Prints, per part,
its CPU seconds and the functions with the most own time (``--top``), and one JSON line
of the CPU split at the end.

    .venv/bin/python benchmarks/profile_mission.py --scenario disturbed --steps 3600 [--top 25]
    .venv/bin/python benchmarks/profile_mission.py --save DIR   # the .prof files, for snakeviz

Profiling slows Python code several times over and compiled code not at all: read the split
between functions, not the absolute seconds (``bench_lockstep.py`` times the mission).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.campaign import hil_run  # noqa: E402
from hil_service.campaign.metrics import score  # noqa: E402
from hil_service.campaign.mission import Mission, oracle_trace, reference_only_trace  # noqa: E402


def _table(profile: pstats.Stats, top: int) -> str:
    out = io.StringIO()
    profile.stream = out  # type: ignore[attr-defined]
    profile.sort_stats("tottime").print_stats(top)
    return out.getvalue()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenario", default="disturbed")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=3600)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--no-oracle", action="store_true")
    parser.add_argument("--save", default=None, help="keep the .prof files in this directory")
    args = parser.parse_args()
    mission = Mission(
        args.scenario, args.seed, args.steps, args.steps // 3, max(2, args.steps // 6)
    )
    with tempfile.TemporaryDirectory() as scratch:
        keep = Path(args.save) if args.save else Path(scratch)
        keep.mkdir(parents=True, exist_ok=True)
        service_prof = keep / "service.prof"
        serve = hil_run._serve

        def profiled_serve(*a: object, **k: object) -> int:  # runs in the forked service
            profiler = cProfile.Profile(time.process_time)
            profiler.enable()
            try:
                return serve(*a, **k)  # type: ignore[arg-type]
            finally:
                profiler.disable()
                profiler.dump_stats(service_prof)

        hil_run._serve = profiled_serve  # type: ignore[assignment]
        emulator = cProfile.Profile(time.process_time)
        emulator.enable()
        outcome = hil_run.run_hil(mission, Path(scratch) / "run")
        emulator.disable()
        hil_run._serve = serve
        if outcome.failure is not None:
            raise SystemExit(f"the mission failed: {outcome.failure}")
        scoring = cProfile.Profile(time.process_time)
        scoring.enable()
        reference = reference_only_trace(mission)
        oracle = None if args.no_oracle else oracle_trace(mission)[0]
        vehicle = outcome.service["vehicles"]["1"]
        score(mission, outcome.trace, reference, oracle, vehicle.get("identifier", {}))
        scoring.disable()
        emulator.dump_stats(keep / "emulator.prof")
        scoring.dump_stats(keep / "scoring.prof")
        parts = {
            "emulator": pstats.Stats(emulator),
            "service": pstats.Stats(str(service_prof)),
            "scoring": pstats.Stats(scoring),
        }
        split = {}
        for name, stats in parts.items():
            split[name] = round(stats.total_tt, 3)  # type: ignore[attr-defined]
            print(f"==== {name}: {stats.total_tt:.3f} CPU s (profiled) ====")  # type: ignore[attr-defined]
            print(_table(stats, args.top))
    print(json.dumps({"profiled_cpu_s": split, "steps": mission.steps, "mission": mission.run_id}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
