"""The ArduSub depth step in process (the depth stall): how fast the offset goes.

``tests/test_mavproxy_router.py`` runs ``serve --profile ardusub`` through MAVProxy: the
glider plant at 0.1 s, PRBS identification (burn-in 400 samples, the setpoint put about 100
samples later), then a 16 m depth and 0.1 rad pitch step from wherever the PRBS left the
vehicle. In 2 of 16 runs depth stalled 0.5-1.2 m short for about 550 samples, until a
telemetry gap reset the controller. This steps the same plant, excitation and pipeline in
lockstep (optionally with the link's late readings and late commands, as
``hil_service.experiment.jitter`` reproduces them) and prints, per seed, the mean |depth
error| over the step's second half and over the samples 200-800 of the step, with
``--trace`` the controller's internal state every 10 samples (y, the internal model's
y_m, the disturbance estimate d, the command u, the identified DC gain).

Run: .venv/bin/python benchmarks/ardusub_offset.py --seeds 0-15 [--jitter] [--trace SEED]
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from hil_service.pipeline import ControlSettings, PipelineSettings, VehiclePipeline  # noqa: E402
from hil_service.umodel.predictive import factorise, step_response  # noqa: E402
from plant_emulator.excitation import build_channel_excitations  # noqa: E402
from plant_emulator.plant import GliderPlant, PlantConfig  # noqa: E402
from protocols.samples import TelemetrySample  # noqa: E402

PERIOD = 0.1
BURN_IN = 400
IDENTIFY = 500  # the setpoint comes about 100 samples after burn-in
CONTROL = 800
SETPOINTS = {"depth": 16.0, "pitch": 0.1}


def dc_gain(pipeline: VehiclePipeline, channel: str) -> float:
    """The identified step response's final value (the linear part, N scaled to slope 1)."""
    dyn = pipeline.channels[channel].dynamics
    if dyn is None:
        return float("nan")
    factors = factorise(dyn, -2.0, 2.0)
    if factors is None:
        return float("nan")
    return step_response(dyn.ar, factors[0], 1000)[-1]


def run(
    seed: int,
    jitter: bool = False,
    identify: int = IDENTIFY,
    control: int = CONTROL,
    trace: bool = False,
    scenario: str = "paper",
    control_settings: ControlSettings | None = None,
) -> dict[str, object]:
    """One run; the depth error over the step, and the trace when asked."""
    rng = random.Random(seed)
    plant = GliderPlant(PlantConfig(period=PERIOD, seed=seed, scenario=scenario))
    pipeline = VehiclePipeline(
        PipelineSettings(burn_in=BURN_IN, control=control_settings or ControlSettings())
    )
    excitation = build_channel_excitations("prbs", seed)
    late_in = late_out = 0.03 if jitter else 0.0
    late_command = 0.3 if jitter else 0.0
    truth: list[TelemetrySample] = []
    pending: list[tuple[int, tuple[float, float]]] = []
    command = (0.0, 0.0)
    served = {"output": -1, "input": -1}
    rows: list[dict[str, float]] = []
    depth_errors: list[float] = []
    depth = pipeline.channels["depth"]
    for step in range(identify + control + 1):
        for item in [p for p in pending if p[0] <= step]:
            command = item[1]
            pending.remove(item)
        truth.append(plant.step(*command))
        if step == 0:
            continue
        k = step - 1
        index = {}
        for reading, share in (("output", late_out), ("input", late_in)):
            late = served[reading] == k - 1 and rng.random() < share
            index[reading] = k - 1 if late else k
        reused = index["input"] == served["input"]
        served = dict(index)
        y, u = truth[index["output"]], truth[index["input"]]
        sample = y._replace(
            time_boot_ms=round(k * PERIOD * 1000), u_depth=u.u_depth, u_pitch=u.u_pitch
        )
        pipeline.observe(sample, reused, sampled=True)
        if k < identify:
            new = (excitation["depth"].value(k), excitation["pitch"].value(k))
        else:
            decision = pipeline.decide(sample, dict(SETPOINTS), True)
            depth_errors.append(abs(sample.depth - SETPOINTS["depth"]))
            new = command if decision.command is None else (
                decision.command.u_depth, decision.command.u_pitch
            )  # fmt: skip
            if trace and (k - identify) % 10 == 0:
                sim = depth.controller._sim
                rows.append(
                    {
                        "n": k - identify,
                        "y": round(sample.depth, 3),
                        "y_m": round(sim[0], 3) if sim else float("nan"),
                        "d": round(depth.controller.disturbance, 3),
                        "u": round(new[0], 3),
                        "dc": round(dc_gain(pipeline, "depth"), 2),
                        "h": depth.controller.horizon,
                    }
                )
        pending.append((step + 1 + (1 if rng.random() < late_command else 0), new))
    half = depth_errors[len(depth_errors) // 2 :]
    middle = depth_errors[200:800]
    result: dict[str, object] = {
        "seed": seed,
        "start_depth": round(truth[identify].depth, 3),
        "second_half_m": round(statistics.mean(half), 4),
        "samples_200_800_m": round(statistics.mean(middle), 4),
    }
    if trace:
        result["trace"] = rows
    return result


def seeds_arg(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-7"))
    parser.add_argument("--jitter", action="store_true", help="the link's late readings")
    parser.add_argument("--control", type=int, default=CONTROL, help="samples of the step")
    parser.add_argument("--trace", type=int, help="print this seed's trace")
    parser.add_argument("--scenario", default="paper")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a ControlSettings field (e.g. cost_points=1000)",
    )
    args = parser.parse_args(argv)
    changes = {}
    for item in args.set:
        name, _, value = item.partition("=")
        changes[name] = type(getattr(ControlSettings(), name))(value)
    control_settings = ControlSettings(**changes)
    if args.trace is not None:
        result = run(args.trace, args.jitter, control=args.control, trace=True,
                     scenario=args.scenario, control_settings=control_settings)  # fmt: skip
        trace = result.pop("trace")
        print(json.dumps(result))
        for row in trace:  # type: ignore[attr-defined]
            print(" ".join(f"{k}={v}" for k, v in row.items()))
        return 0
    halves = []
    for seed in args.seeds:
        result = run(
            seed,
            args.jitter,
            control=args.control,
            scenario=args.scenario,
            control_settings=control_settings,
        )
        halves.append(result["second_half_m"])
        print(json.dumps(result), flush=True)
    print(
        json.dumps(
            {
                "seeds": len(halves),
                "mean_second_half_m": round(statistics.mean(halves), 4),  # type: ignore[arg-type]
                "max_second_half_m": max(halves),  # type: ignore[type-var]
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
