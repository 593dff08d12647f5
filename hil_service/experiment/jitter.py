"""The ArduSub test's loop in process, with the link's sampling reproduced (a diagnosis tool).

``tests/test_ardusub_link.py`` runs the plant at 0.1 s behind ``emulate --profile ardusub``:
60 s of prbs identification, then a 1 m depth and 0.1 rad pitch step for 150 s. Its streams
reach the sampler with jitter, so a reading is sometimes served a tick early and then again
on the next tick, independently for the output (depth, pitch) and the input (servo
readback); a command sometimes takes effect one step late. This module steps the same plant
with the same excitation and pipeline, and reproduces those three effects with given
probabilities, so that each one's share of the tracking error can be measured. Since the
sampler places a reading inside its clock tick, the link's remaining case is the *late*
reading (the previous tick's served again, then a fresh one: ``output_late``,
``input_late``); ``flag_reused`` tells the pipeline which input readings were reused, as
the ArduSub assembler does (docs/control.md, "The ArduSub profile"):

    .venv/bin/python -m hil_service.experiment.jitter            # the table of docs/control.md
    .venv/bin/python -m hil_service.experiment.jitter --identify 1800 --excitation steps

Returns the mean |error| over the second half of the step, as the test measures it.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
from typing import TypedDict

from hil_service.pipeline import PipelineSettings, VehiclePipeline
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.samples import TelemetrySample

PERIOD = 0.1
IDENTIFY, CONTROL = 600, 1500  # samples: 60 s and 150 s at 10 Hz
SETPOINTS = {"depth": 16.0, "pitch": 0.1}


def jittered_loop(
    seed: int,
    output_early: float = 0.0,
    input_early: float = 0.0,
    late_command: float = 0.0,
    settings: PipelineSettings | None = None,
    identify: int = IDENTIFY,
    excitation_name: str = "prbs",
    output_late: float = 0.0,
    input_late: float = 0.0,
    flag_reused: bool = False,
) -> tuple[float, float]:
    """(mean |depth error| m, mean |pitch error| rad) over the second half of the step."""
    rng = random.Random(seed)
    plant = GliderPlant(PlantConfig(period=PERIOD, seed=seed))
    pipeline = VehiclePipeline(settings or PipelineSettings(burn_in=identify // 2))
    excitation = build_channel_excitations(excitation_name, seed)
    truth: list[TelemetrySample] = []
    pending: list[tuple[int, tuple[float, float]]] = []  # (plant step it applies at, command)
    command = (0.0, 0.0)
    early = {"output": False, "input": False}
    share = {"output": output_early, "input": input_early}
    # A reading served late: the previous tick's served again (no newer one stamped by the
    # tick, the link's case once stamps are placed in their clock tick), then a fresh one.
    late = {"output": output_late, "input": input_late}
    served = {"output": -1, "input": -1}
    reused = False
    errors: list[tuple[float, float]] = []
    for step in range(identify + CONTROL + 1):
        due = [item for item in pending if item[0] <= step]
        for item in due:
            command = item[1]
            pending.remove(item)
        truth.append(plant.step(*command))
        if step == 0:
            continue
        k = step - 1  # the tick reported: one plant step ahead is available
        index = {}
        for reading in ("output", "input"):
            if early[reading]:
                index[reading], early[reading] = k, False  # served again: a repeat
            elif rng.random() < share[reading]:
                index[reading], early[reading] = k + 1, True
            elif served[reading] == k - 1 and rng.random() < late[reading]:
                index[reading] = k - 1
            else:
                index[reading] = k
        reused = index["input"] == served["input"]
        served = dict(index)
        y, u = truth[index["output"]], truth[index["input"]]
        sample = y._replace(
            time_boot_ms=round(k * PERIOD * 1000), u_depth=u.u_depth, u_pitch=u.u_pitch
        )
        pipeline.observe(sample, flag_reused and reused, sampled=True)
        if k < identify:
            new = (excitation["depth"].value(k), excitation["pitch"].value(k))
        else:
            decision = pipeline.decide(sample, dict(SETPOINTS), True)
            errors.append(
                (abs(sample.depth - SETPOINTS["depth"]), abs(sample.pitch - SETPOINTS["pitch"]))
            )
            new = command if decision.command is None else (
                decision.command.u_depth, decision.command.u_pitch
            )  # fmt: skip
        pending.append((step + 1 + (1 if rng.random() < late_command else 0), new))
    tail = errors[len(errors) // 2 :]
    return (
        sum(e[0] for e in tail) / len(tail),
        sum(e[1] for e in tail) / len(tail),
    )


class Jitter(TypedDict, total=False):
    """A case's arguments of ``jittered_loop``."""

    output_early: float
    input_early: float
    late_command: float
    output_late: float
    input_late: float
    flag_reused: bool


CASES: dict[str, Jitter] = {
    "none": {},
    "command latency only": {"late_command": 0.3},
    "output readings only": {"output_early": 0.08},
    "input (servo readback) readings only": {"input_early": 0.08},
    "both": {"output_early": 0.08, "input_early": 0.08, "late_command": 0.3},
    "input readings late (reused) 3 %": {"input_late": 0.03},
    "input late 3 %, reuse flagged": {"input_late": 0.03, "flag_reused": True},
    "all late 3 % + latency, flagged": {
        "input_late": 0.03,
        "output_late": 0.03,
        "late_command": 0.3,
        "flag_reused": True,
    },
    "all late 3 % + latency, not flagged": {
        "input_late": 0.03,
        "output_late": 0.03,
        "late_command": 0.3,
    },
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--identify", type=int, default=IDENTIFY, help="samples (10 Hz)")
    parser.add_argument("--excitation", default="prbs", help="the emulator's excitation")
    parser.add_argument("--seeds", type=int, default=6, help="seeds 1..N")
    parser.add_argument("--cases", nargs="*", help="only these cases (substring match)")
    args = parser.parse_args(argv)
    seeds = range(1, args.seeds + 1)
    print("jitter of                              depth error (mean of seeds)  per seed")
    for name, kwargs in CASES.items():
        if args.cases and not any(c in name for c in args.cases):
            continue
        depth = [
            jittered_loop(seed, **kwargs, identify=args.identify, excitation_name=args.excitation)[
                0
            ]
            for seed in seeds
        ]
        per_seed = " ".join(f"{d:.3f}" for d in depth)
        print(f"{name:38s} {statistics.mean(depth):8.3f} m                    {per_seed}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
