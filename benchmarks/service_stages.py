"""Where the service path's time goes, per stage: ``bench_service.py``'s datagrams through
``HilService.process_datagram`` under cProfile, own time summed by the module it is spent in
and the modules grouped into stages (decode, assemble, identify/control, publish, log, …).

cProfile sees into Python functions only, so this runs the sources
(``GLIDER_HIL_INTERPRETED=1``, set here before anything imports them): the split is that of
the interpreted path, in which the compiled modules' share is larger than when compiled
(``bench_service.py`` prints the compiled rate and its gain). Read the shares, not the
seconds.

    .venv/bin/python benchmarks/service_stages.py [--samples 5000] [--top 15] [--control]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("GLIDER_HIL_INTERPRETED", "1")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_service  # noqa: E402

#: (stage, path fragments of the modules whose own time counts for it), first match wins.
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("decode (pymavlink messages)", ("pymavlink",)),
    (
        "decode (frames, signing)",
        ("protocols/frame_decoder", "protocols/mavlink_io", "protocols/signing"),
    ),
    (
        "assemble a sample",
        ("hil_service/sources/lockstep_assembler", "hil_service/sources/periodic_assembler",
         "hil_service/sources/sampler", "hil_service/sources/lockstep.py", "protocols/mapping",
         "protocols/samples", "protocols/units", "protocols/readings",
         "hil_service/link_stats"),
    ),
    ("identify + control (the method)", ("hil_service/umodel", "hil_service/pipeline")),
    (
        "publish (JSON, Zenoh)",
        ("protocols/payload_json", "protocols/mavlink_json", "zenoh", "hil_service/listeners",
         "orjson", "protocols/keys"),
    ),
    ("log (MCAP)", ("hil_service/mcap",)),
    (
        "service loop and bookkeeping",
        ("hil_service/service", "hil_service/inputs", "hil_service/sources/lockstep_responder",
         "hil_service/sources/companion"),
    ),
    ("numpy", ("numpy",)),
)


OTHER = "other (builtins, stdlib)"


def stage_of(filename: str) -> str:
    for stage, fragments in STAGES:
        if any(fragment in filename for fragment in fragments):
            return stage
    return OTHER


def _with_callers(per_stage: dict[str, float], by_caller: dict[str, float]) -> dict[str, float]:
    moved = {stage: seconds for stage, seconds in by_caller.items() if stage != OTHER}
    shares = {stage: per_stage[stage] + moved.get(stage, 0.0) for stage in per_stage}
    shares[OTHER] = per_stage[OTHER] - sum(moved.values())
    for stage, seconds in moved.items():
        shares.setdefault(stage, seconds)
    return shares


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=5000)
    parser.add_argument("--top", type=int, default=15, help="functions listed by own time")
    parser.add_argument(
        "--control", action="store_true",
        help="control on with setpoints (bench_service.build_service): the controller decides",
    )  # fmt: skip
    args = parser.parse_args()
    datagrams = bench_service.telemetry_datagrams(args.samples)
    with tempfile.TemporaryDirectory() as log_dir:
        service, recorder, session = bench_service.build_service(log_dir, args.control)
        try:
            profiler = cProfile.Profile(time.process_time)
            profiler.enable()
            for data in datagrams:
                service.process_datagram(data)
            recorder.close(timeout=600)  # the log drained: its writer thread's time is not seen
            profiler.disable()
            samples = service.source.totals()["samples"]
        finally:
            service.notifier.stop()
            session.close()  # Zenoh's threads would otherwise keep the process alive
    stats = pstats.Stats(profiler)
    per_stage: dict[str, float] = defaultdict(float)
    functions = []
    by_caller: dict[str, float] = defaultdict(float)
    for (filename, line, name), (_, _, own, _, callers) in stats.stats.items():  # type: ignore[attr-defined]
        per_stage[stage_of(filename)] += own
        functions.append((own, f"{Path(filename).name}:{line}({name})", stage_of(filename)))
        if stage_of(filename) == OTHER:
            # A builtin's own time when called from each caller: the caller's stage.
            for (caller_file, _, _), (_, _, caller_own, _) in callers.items():
                by_caller[stage_of(caller_file)] += caller_own
    total = sum(per_stage.values())
    result = {
        "modules": "interpreted (GLIDER_HIL_INTERPRETED=1)",
        "control": args.control,
        "samples": samples,
        "profiled_cpu_s": round(total, 3),
        "profiled_us_per_sample": round(1e6 * total / max(samples, 1), 1),
        "share_by_stage": {
            stage: round(seconds / total, 3)
            for stage, seconds in sorted(per_stage.items(), key=lambda item: -item[1])
        },
        # The same with the builtins' and stdlib's time counted for the stage that called
        # them (one level up: a builtin called by the stdlib stays where it is).
        "share_by_stage_callers_included": {
            stage: round(seconds / total, 3)
            for stage, seconds in sorted(
                _with_callers(per_stage, by_caller).items(), key=lambda item: -item[1]
            )
        },
        "top_functions": [
            {"own_share": round(own / total, 3), "function": where, "stage": stage}
            for own, where, stage in sorted(functions, reverse=True)[: args.top]
        ],
    }
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
