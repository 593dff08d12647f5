"""Where the service path's time goes, per stage: ``bench_service.py``'s datagrams through
``HilService.process_datagram`` under cProfile, own time summed by the module it is spent in
and the modules grouped into stages (decode, assemble, identify/control, publish, log, …).

cProfile sees into Python functions only, so this runs the sources
(``GLIDER_HIL_INTERPRETED=1``, set here before anything imports them): the split is that of
the interpreted path, in which the compiled modules' share is larger than when compiled
(``bench_service.py`` prints the compiled rate and its gain). Read the shares, not the
seconds.

``--compiled`` splits the compiled path instead, as it runs in ``serve``: ``perf record``
(Linux perf, call graphs unwound with DWARF) samples this process while the datagrams go
through, and each sample counts for the stage of the nearest compiled function on its
stack (``payload_json``'s for its caller's), so the interpreter's and C libraries' work
(dict updates, struct packing, orjson, zstd on the log's thread) counts for the compiled
code that asked for it. Samples are taken at a fixed rate of CPU time: their count per
sample is the path's CPU time.

    .venv/bin/python benchmarks/service_stages.py [--samples 5000] [--top 15] [--control]
    .venv/bin/python benchmarks/service_stages.py --compiled [--samples 6000] [--control]
        [--callees CLASS.METHOD ...]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

if "--compiled" not in sys.argv:
    os.environ.setdefault("GLIDER_HIL_INTERPRETED", "1")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_service  # noqa: E402

from protocols import compiled  # noqa: E402

#: (stage, path fragments of the modules whose own time counts for it), first match wins.
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("decode (pymavlink messages)", ("pymavlink",)),
    (
        "decode (frames, signing)",
        ("protocols/frame_decoder", "protocols/mavlink_io", "protocols/signing"),
    ),
    (
        "assemble a sample",
        (
            "hil_service/sources/lockstep_assembler",
            "hil_service/sources/periodic_assembler",
            "hil_service/sources/sampler",
            "hil_service/sources/lockstep.py",
            "protocols/mapping",
            "protocols/samples",
            "protocols/units",
            "protocols/readings",
            "hil_service/link_stats",
        ),
    ),
    ("identify + control (the method)", ("hil_service/umodel", "hil_service/pipeline")),
    (
        "publish (JSON, Zenoh)",
        (
            "protocols/payload_json",
            "protocols/mavlink_json",
            "zenoh",
            "hil_service/listeners",
            "orjson",
            "protocols/keys",
        ),
    ),
    ("log (MCAP)", ("hil_service/mcap",)),
    (
        "service loop and bookkeeping",
        (
            "hil_service/service",
            "hil_service/inputs",
            "hil_service/sources/lockstep_responder",
            "hil_service/sources/companion",
        ),
    ),
    ("numpy", ("numpy",)),
)


OTHER = "other (builtins, stdlib)"

#: ``--compiled``: the stage of each compiled module (mypyc names a function
#: ``CPyDef_{module}___{class}___{method}``); payload_json counts for its caller.
COMPILED_STAGES: dict[str, tuple[str, ...]] = {
    "decode (frames, signing)": ("frame_decoder", "mavlink_io", "signing"),
    "assemble a sample": ("lockstep_assembler", "lockstep", "lockstep_responder", "readings",
                          "samples", "mapping", "link_stats"),
    "identify + control (the method)": ("pipeline", "box_qp", "dynamics", "estimate", "guards",
                                        "horizon", "inverse", "models", "nlms", "predictive",
                                        "rbf", "reproducible", "rls", "scoring", "supervisor"),
    "publish (JSON, Zenoh)": ("notifier",),
    "log (MCAP)": ("recorder", "writer", "mavlink_json"),
    "service loop and bookkeeping": ("service",),
}  # fmt: skip
PERF_HZ = 797


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


def compiled_stage(stack: list[str]) -> str:
    """The stage of one perf sample: its stack's symbols, innermost first."""
    for symbol in stack:
        if not symbol.startswith("CPyDef_"):
            continue
        module = symbol[len("CPyDef_") :].split("___")[0]
        if module == "payload_json":
            continue
        for stage, modules in COMPILED_STAGES.items():
            if module in modules:
                return stage
        return f"other compiled ({module})"
    return "other (outside the compiled path)"


def perf_stacks(script: str) -> list[list[str]]:
    """Each sample's stack in ``perf script`` output: its symbols, innermost first."""
    stacks: list[list[str]] = []
    stack: list[str] = []
    for line in [*script.splitlines(), ""]:
        if not line.strip():
            if stack:
                stacks.append(stack)
            stack = []
        elif line[0] in " \t":
            match = re.search(r"\s[0-9a-f]+\s+(\S+)", line)
            if match:
                stack.append(match.group(1).split("+")[0])
    return stacks


def perf_split(stacks: list[list[str]]) -> dict[str, int]:
    """Samples per stage."""
    counts: dict[str, int] = defaultdict(int)
    for stack in stacks:
        counts[compiled_stage(stack)] += 1
    return dict(counts)


def callee_split(stacks: list[list[str]], function: str) -> dict[str, int]:
    """The samples in which compiled ``function`` (a name such as
    ``PredictiveInverse.decide``) is on the stack, by the compiled function it had called
    (``(own)`` when none: the function itself and what it calls outside compiled code)."""
    counts: dict[str, int] = defaultdict(int)
    for stack in stacks:
        names = [_plain_name(symbol) for symbol in stack if symbol.startswith("CPyDef_")]
        if function in names:
            at = names.index(function)
            counts["(own)" if at == 0 else names[at - 1]] += 1
    return dict(counts)


def _plain_name(symbol: str) -> str:
    """``CPyDef_predictive___PredictiveInverse___decide`` → ``PredictiveInverse.decide``."""
    return ".".join(part for part in symbol[len("CPyDef_") :].split("___")[1:] if part)


def datagrams_for(args: argparse.Namespace) -> list[bytes]:
    """``bench_service.py``'s datagrams: with ``--control`` those of a vehicle the service
    commands (``closed_loop_datagrams``), so that the controller's own path is split."""
    if args.control:
        return bench_service.closed_loop_datagrams(args.samples)[0]
    return bench_service.telemetry_datagrams(args.samples)


def main_compiled(args: argparse.Namespace) -> int:
    datagrams = datagrams_for(args)
    warm = 400  # datagrams before perf attaches (first vehicle, first chunk, caches)
    with tempfile.TemporaryDirectory() as scratch:
        data_file = str(Path(scratch) / "perf.data")
        log_dir = str(Path(scratch) / "log")
        service, recorder, session = bench_service.build_service(log_dir, args.control)
        assert recorder is not None
        try:
            for data in datagrams[:warm]:
                service.process_datagram(data)
            warm_samples = service.source.totals()["samples"]
            perf = subprocess.Popen(
                ["perf", "record", "-F", str(PERF_HZ), "--call-graph", "dwarf,16384",
                 "-o", data_file, "-p", str(os.getpid())],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
            time.sleep(0.5)  # perf attached
            for data in datagrams[warm:]:
                service.process_datagram(data)
            recorder.close(timeout=600)  # the log drained: its thread's time is counted
            perf.send_signal(signal.SIGINT)
            perf.wait()
            steps = service.source.totals()["samples"] - warm_samples
        finally:
            service.notifier.stop()
            session.close()
        script = subprocess.run(
            ["perf", "script", "-i", data_file], capture_output=True, text=True, check=True
        ).stdout
    stacks = perf_stacks(script)
    counts = perf_split(stacks)
    total = sum(counts.values())
    result = {
        "modules": compiled.summary(),
        "control": args.control,
        "samples": steps,
        "perf_samples": total,
        "cpu_us_per_sample": round(1e6 * total / PERF_HZ / steps, 1),
        "share_by_stage": {
            stage: round(n / total, 3) for stage, n in sorted(counts.items(), key=lambda i: -i[1])
        },
        "us_per_sample_by_stage": {
            stage: round(1e6 * n / PERF_HZ / steps, 1)
            for stage, n in sorted(counts.items(), key=lambda i: -i[1])
        },
    }
    for function in args.callees:
        split = callee_split(stacks, function)
        result[f"us_per_sample_in {function}, by callee"] = {
            callee: round(1e6 * n / PERF_HZ / steps, 1)
            for callee, n in sorted(split.items(), key=lambda i: -i[1])
            if n / total >= 0.002
        }
    print(json.dumps(result, indent=1))
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--samples", type=int, default=5000)
    parser.add_argument("--top", type=int, default=15, help="functions listed by own time")
    parser.add_argument(
        "--control", action="store_true",
        help="control on with setpoints (bench_service.build_service): the controller decides",
    )  # fmt: skip
    parser.add_argument(
        "--compiled", action="store_true",
        help="split the compiled path with Linux perf (needs perf) instead of cProfile",
    )  # fmt: skip
    parser.add_argument(
        "--callees", action="append", default=[], metavar="CLASS.METHOD",
        help="with --compiled: this compiled function's time by the compiled function it "
        "called (e.g. PredictiveInverse.decide); may be repeated",
    )  # fmt: skip
    args = parser.parse_args()
    if args.compiled:
        return main_compiled(args)
    datagrams = datagrams_for(args)
    with tempfile.TemporaryDirectory() as log_dir:
        service, recorder, session = bench_service.build_service(log_dir, args.control)
        assert recorder is not None
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
