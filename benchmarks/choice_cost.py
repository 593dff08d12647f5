"""What a channel's structure choice costs (the input lags, the dead zone and the identifier
rebuilt with them; docs/control.md, "The input lags, chosen from the record"), on the
compiled path as ``serve`` runs it.

Each channel makes its choice once, on the sample where it is first asked to command with a
record long enough; a fleet that started together makes them all around the same sample
(docs/benchmarks.md, "A fleet"). For family plants (seeded, as ``experiment --closed-loop
--scenario family``) this runs the service's pipeline in process on each vehicle, times every
sample's ``observe`` and ``decide`` and takes, per channel that chose, the choosing sample's
time less the median of its hundred neighbours' (shared between the channels that chose on
it): the choice's own cost. Printed: its median, p90 and max over the channels, and what a
fleet of ``--fleet`` vehicles would spend on them.

BLAS runs on one thread, as in every ``glider-hil`` command
(``process_tuning.single_threaded_blas``); ``OPENBLAS_NUM_THREADS=2`` in the environment
measures numpy's default on two cores.

    .venv/bin/python benchmarks/choice_cost.py [--seed 20] [--plants 30] [--fleet 1000]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.process_tuning import single_threaded_blas  # noqa: E402

single_threaded_blas()  # as every glider-hil command runs (before numpy loads)

from hil_service.experiment.closed_loop import (  # noqa: E402
    CHANNELS,
    ClosedLoopSettings,
    _drive,
    setpoint_schedule,
)
from hil_service.experiment.family_loop import levels  # noqa: E402
from hil_service.pipeline import PipelineSettings, VehiclePipeline  # noqa: E402
from plant_emulator.family import FamilyPlantSpec, FamilyVehicle, draw_family  # noqa: E402
from protocols.samples import TelemetrySample  # noqa: E402


def vehicle_choices(
    settings: ClosedLoopSettings, depth: FamilyPlantSpec, pitch: FamilyPlantSpec
) -> list[float]:
    """The choice's cost (s) of each channel of one vehicle that made one."""
    specs = {"depth": depth, "pitch": pitch}
    schedule = setpoint_schedule(settings, {ch: levels(specs[ch]) for ch in CHANNELS})
    pipeline = VehiclePipeline(PipelineSettings(seed=settings.seed))
    durations: list[float] = []
    chosen_at: dict[str, int] = {}

    def control(k: int, sample: TelemetrySample) -> tuple[float, float] | None:
        start = time.perf_counter()
        pipeline.observe(sample)
        decision = None
        if k >= settings.identify:
            setpoints = {ch: float(schedule[ch][k]) for ch in CHANNELS}
            decision = pipeline.decide(sample, setpoints, True)
        durations.append(time.perf_counter() - start)
        for ch, channel in pipeline.channels.items():
            if ch not in chosen_at and not channel._lags_pending:
                chosen_at[ch] = k  # chose (or found the record could not be judged)
        if decision is None or decision.command is None:
            return None
        return decision.command.u_depth, decision.command.u_pitch

    _drive(settings, FamilyVehicle(depth, pitch, settings.seed), schedule, control)
    # A sample's usual cost where it was taken: the median of its neighbours'.
    costs = []
    for k in chosen_at.values():
        around = durations[max(0, k - 50) : k] + durations[k + 1 : k + 51]
        sharing = sum(1 for j in chosen_at.values() if j == k)  # channels choosing together
        costs.append(max(durations[k] - statistics.median(around), 0.0) / sharing)
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=20)
    parser.add_argument("--plants", type=int, default=30)
    parser.add_argument("--fleet", type=int, default=1000)
    args = parser.parse_args()
    settings = ClosedLoopSettings(  # the family benchmark's run (family_harm.py)
        scenario="family",
        samples=2000,
        seed=args.seed,
        identify=800,
        step_every=300,
        neutral_after_identify=True,
    )
    costs: list[float] = []
    for depth, pitch in draw_family(args.seed, args.plants):
        costs += vehicle_choices(settings, depth, pitch)
    if not costs:
        raise SystemExit("no channel made a choice")
    ms = sorted(c * 1e3 for c in costs)
    per_vehicle = 2 * statistics.mean(ms) / 1e3
    print(
        json.dumps(
            {
                "seed": args.seed,
                "channels_that_chose": len(ms),
                "choice_ms": {
                    "median": round(statistics.median(ms), 2),
                    "p90": round(ms[int(0.9 * (len(ms) - 1))], 2),
                    "max": round(ms[-1], 2),
                    "mean": round(statistics.mean(ms), 2),
                },
                f"fleet_of_{args.fleet}_cpu_s": round(args.fleet * per_vehicle, 1),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
