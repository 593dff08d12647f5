"""The glider oracle's depth IAE under other settings (can a fair, better known-model
controller bring paper depth to the target's 12,829?). Printed, not a test.

    .venv/bin/python benchmarks/oracle_settings_sweep.py --scenarios paper --variants main,previous

Each variant is ``GLIDER_ORACLE["depth"]`` with one change; pitch keeps its settings. Runs
``oracle_run`` as ``experiment --closed-loop --samples 20000 --seed 0`` does.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from hil_service.experiment.closed_loop import (
    GLIDER_ORACLE,
    ClosedLoopSettings,
    oracle_run,
    score,
    setpoint_schedule,
)
from hil_service.experiment.oracle import OracleSettings
from plant_emulator.plant import GliderPlant, PlantConfig

BASE = GLIDER_ORACLE["depth"]
#: The coarse oracle (blocks of 4 samples, the error costed every 4th sample): 12,835.28 on
#: paper, where the full-resolution optimum is ``BASE``.
PREVIOUS = replace(
    BASE,
    horizon=600,
    blocks=(4, 4, 4, 4, 4, 4, 8, 8, 16, 16, 32, 64, 128),
    cost_stride=4,
    stride_from=0,
)
VARIANTS: dict[str, OracleSettings] = {
    "main": BASE,
    "previous": PREVIOUS,
    # The reference: a free input on every one of the first 200 samples, costed on every one.
    "full1000": replace(
        BASE, horizon=1000, blocks=(1,) * 200 + (800,), cost_stride=1, stride_from=0
    ),
    "stride1": replace(BASE, cost_stride=1, stride_from=0),
    # The stride over the single-sample moves too: the plan wiggles between costed samples.
    "stride4_everywhere": replace(BASE, stride_from=0),
    "stride2_everywhere": replace(BASE, cost_stride=2, stride_from=0),
    "first2": replace(BASE, blocks=(2,) * 8 + (4,) * 8 + (8,) * 8 + (16,) * 4 + (32,) * 4),
    "first1x4": replace(
        BASE, blocks=(1,) * 4 + (2,) * 4 + (4,) * 4 + (8,) * 4 + (16,) * 4 + (32,) * 4 + (64,) * 2
    ),
    "h600": replace(BASE, horizon=600),
    "no_terminal": replace(BASE, terminal=False),
    "move1e-3": replace(BASE, move_weight=1e-3),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scenarios", default="paper")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--samples", type=int, default=20000)
    parser.add_argument(
        "--ipm",
        action="store_true",
        help="HiGHS's interior point without crossover: the centre of the optimal face, not a "
        "vertex (slow; a solve that ends without an optimum is a failure, input held)",
    )
    args = parser.parse_args()
    if args.ipm:
        from hil_service.experiment import oracle

        oracle.LP_OPTIONS.update({"solver": "ipm", "run_crossover": "off"})
    for scenario in args.scenarios.split(","):
        for name in args.variants.split(","):
            settings = ClosedLoopSettings(scenario, samples=args.samples, seed=0, oracle=True)
            config = PlantConfig(scenario=scenario, seed=0)
            started = time.process_time()
            run, failures = oracle_run(
                settings,
                GliderPlant(config),
                setpoint_schedule(settings),
                {"depth": VARIANTS[name], "pitch": GLIDER_ORACLE["pitch"]},
                {"depth": config.trim_depth, "pitch": 0.0},
            )
            score(run, settings, config.period)
            print(
                f"{scenario:9} {name:15} depth IAE {run.metrics['depth'].iae:10.2f}  "
                f"LP failures {failures}  CPU {time.process_time() - started:.1f} s",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
