"""Two git revisions measured in one session, interleaved, so that a speed-up is a ratio
measured side by side and not two figures from different phases of a noisy machine.

For each revision (checked out into temporary worktrees) and each of ``--rounds`` rounds:
the end-to-end service throughput (``bench_service.bench_throughput``) pinned to one CPU and
unpinned, and the dynamic model's control step per channel (``experiment.speed.measure``)
pinned to one CPU. With ``--lockstep STEPS``, also a lockstep campaign mission of STEPS steps
(``disturbed`` seed 0, logged) pinned to one CPU: its steps/s, and the CPU s of the whole
mission as a campaign worker runs it (``runner.execute``: emulator, service, scoring), with
the oracle and without. Prints the medians and the median of the paired ratios (new / old).

A revision with a ``setup.py`` has its compiled modules built in its worktree first (as an
install would), unless ``--interpreted``, which runs every revision's Python sources.

Run: .venv/bin/python benchmarks/compare_revisions.py OLD_REV NEW_REV [--rounds N] [--interpreted]
         [--lockstep 3600]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.process_tuning import one_cpu_child  # noqa: E402
from protocols.compiled import child_environment  # noqa: E402

_THROUGHPUT = """
import sys, json
sys.path.insert(0, sys.argv[1] + "/benchmarks"); sys.path.insert(0, sys.argv[1])
import bench_service
r = bench_service.bench_throughput(int(sys.argv[2]), 1)
print(json.dumps([r["pymavlink_parse_samples_per_s"]["best"],
                  r["service_incl_log_drain_samples_per_s"]["best"]]))
"""

_CONTROL = """
import sys, json
sys.path.insert(0, sys.argv[1])
from hil_service.experiment import speed
print(json.dumps(speed.measure(sys.argv[3], "dynamic", int(sys.argv[2])).control_per_s))
"""


_LOCKSTEP = """
import sys, json, resource, tempfile
sys.path.insert(0, sys.argv[1] + "/benchmarks"); sys.path.insert(0, sys.argv[1])
from pathlib import Path
import bench_lockstep
from hil_service.campaign.mission import Mission
from hil_service.campaign.runner import CampaignSpec, execute
steps = int(sys.argv[2])
mission = Mission("disturbed", 0, steps, steps // 3, max(2, steps // 6))
rate = bench_lockstep.lockstep_rate(mission, log=True)["steps_per_s"]
cpu = []
for oracle in (True, False):
    with tempfile.TemporaryDirectory() as out:
        spec = CampaignSpec(("disturbed",), (0,), Path(out), steps=steps, identify=steps // 3,
                            step_every=max(2, steps // 6), oracle=oracle)
        before = bench_lockstep.cpu_seconds()
        row = execute(spec, mission)
        assert row["status"] == "ok", row
        cpu.append(bench_lockstep.cpu_seconds() - before)
print(json.dumps([rate, cpu[0], cpu[1]]))
"""


def _run(code: str, tree: str, args: list[str], pinned: bool, interpreted: bool) -> object:
    child = subprocess.run(
        [sys.executable, "-c", code, tree, *args], capture_output=True, text=True,
        timeout=1800, check=True, env=child_environment(interpreted),
        preexec_fn=one_cpu_child()[1] if pinned else None,
    )  # fmt: skip
    return json.loads(child.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("old")
    parser.add_argument("new")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--samples", type=int, default=8000, help="throughput samples")
    parser.add_argument("--control-samples", type=int, default=4000)
    parser.add_argument(
        "--lockstep",
        type=int,
        default=0,
        metavar="STEPS",
        help="also a lockstep mission of STEPS steps (0: not measured)",
    )
    parser.add_argument(
        "--interpreted",
        action="store_true",
        help="run the Python sources of every revision (compile nothing)",
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as base:
        trees = {}
        for label, rev in (("old", args.old), ("new", args.new)):
            trees[label] = str(Path(base) / label)
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "-q", "--detach",
                            trees[label], rev], check=True)  # fmt: skip
            if not args.interpreted and (Path(trees[label]) / "setup.py").exists():
                subprocess.run([sys.executable, "setup.py", "--quiet", "build_ext", "--inplace"],
                               cwd=trees[label], check=True, capture_output=True)  # fmt: skip
        try:
            results: dict[tuple[str, str], list] = {}
            for _ in range(args.rounds):
                for label, tree in trees.items():
                    for pinned in (True, False):
                        key = (label, "throughput one core" if pinned else "throughput unpinned")
                        value = _run(_THROUGHPUT, tree, [str(args.samples)], pinned,
                                     args.interpreted)  # fmt: skip
                        results.setdefault(key, []).append(value)
                    for channel in ("depth", "pitch"):
                        value = _run(_CONTROL, tree, [str(args.control_samples), channel], True,
                                     args.interpreted)  # fmt: skip
                        results.setdefault((label, f"control step {channel}"), []).append(value)
                    if args.lockstep:
                        value = _run(_LOCKSTEP, tree, [str(args.lockstep)], True,
                                     args.interpreted)  # fmt: skip
                        results.setdefault((label, "lockstep mission"), []).append(value)
        finally:
            for tree in trees.values():
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", tree],
                               check=False)  # fmt: skip
    report = {}
    for figure in sorted({name for _, name in results}):
        old, new = results[("old", figure)], results[("new", figure)]
        if figure == "lockstep mission":
            report[figure] = {
                "old_median_steps_per_s": statistics.median(r[0] for r in old),
                "new_median_steps_per_s": statistics.median(r[0] for r in new),
                "old_median_cpu_s_with_oracle": statistics.median(r[1] for r in old),
                "new_median_cpu_s_with_oracle": statistics.median(r[1] for r in new),
                "old_median_cpu_s_without_oracle": statistics.median(r[2] for r in old),
                "new_median_cpu_s_without_oracle": statistics.median(r[2] for r in new),
                "paired_gain_steps_per_s": statistics.median(
                    n[0] / o[0] for o, n in zip(old, new, strict=True)
                ),
            }
        elif figure.startswith("throughput"):
            report[figure] = {
                "old_median_per_s": statistics.median(r[1] for r in old),
                "new_median_per_s": statistics.median(r[1] for r in new),
                "old_ratio_to_pymavlink": statistics.median(r[1] / r[0] for r in old),
                "new_ratio_to_pymavlink": statistics.median(r[1] / r[0] for r in new),
                "paired_gain": statistics.median(
                    n[1] / o[1] for o, n in zip(old, new, strict=True)
                ),
            }
        else:
            report[figure] = {
                "old_median_per_s": statistics.median(old),
                "new_median_per_s": statistics.median(new),
                "paired_gain": statistics.median(n / o for o, n in zip(old, new, strict=True)),
            }
    print(json.dumps({"old": args.old, "new": args.new, "rounds": args.rounds,
                      "interpreted": args.interpreted, **report},
                     indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
