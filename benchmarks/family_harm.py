"""Which family plants end above 1.1 × reference-only, and why (docs/control.md, "Do no
harm on the family").

Runs ``experiment --closed-loop --scenario family`` (the same runs, in process) for each
seed, under both models of what a channel the service does not command gets:

* ``hold``: the vehicle holds its input (neutral after the excitation), as the emulator does;
* ``vehicle``: the vehicle's own controller takes the channel back (reference-only), from
  the sample the service stops commanding it; a tripped channel's safe input is "release".

and prints, per semantics, the targets' figures, then the plants above the limit classified
by what the channel did (never qualified / tripped / commanded throughout), by the phase
where most of their IAE accrued, and by plant feature, beside the same count for the
known-model oracle.

    python benchmarks/family_harm.py --seeds 10 11 12 13 14 --plants 50
    python benchmarks/family_harm.py --seeds 0 1 2 --plants 200 --save a.pkl   # and 3 4: b.pkl
    python benchmarks/family_harm.py --combine a.pkl b.pkl

What-if runs (docs/control.md, "What the excess is made of"): ``--horizon-fit F`` and
``--mean-fit M`` set the horizon test's thresholds against holding and against the mean
(``--mean-fit -1``: none), ``--nb N`` the identifier's input lags (by default each channel
chooses them from its record, as ``serve`` does; ``--nb 4`` is the model's own four), and
``--nb-from-true-delay E`` gives each plant's identifier max(4, delay + E) input lags from
the plant's *true* input delay, which no deployed identifier knows: an upper bound on what
choosing the lags from the data could give, not a controller. ``--lag-smoothing-gain K``
sets the smoothness prior on the input lags (0: none; docs/control.md, "A smoothness prior
on the input lags"). ``--control NAME=VALUE`` sets any numeric ``ControlSettings`` constant
(e.g. ``move_weight=0.1``; repeatable), ``--degree M`` the identifier's input polynomial
degree, ``--no-dead-zone`` leaves out the input dead zone's choice and ``--dead-zone-margin
M`` sets the tie of that choice (docs/control.md, "An input dead zone, chosen from the
record"). ``--best-of SHIPPED A.pkl B.pkl …`` compares
saved runs of the same plants: each one's count, its geometric mean ratio and the plants it
moved against the first, and how many plants stay above the limit when each keeps its
lowest ratio over the runs (docs/control.md, "One constant at a time, and the best of them
plant by plant").
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import pickle
import time
from collections import Counter
from collections.abc import Callable, Iterable

from hil_service.process_tuning import single_threaded_blas

single_threaded_blas()  # as every glider-hil command runs (before numpy loads)

import numpy as np  # noqa: E402

from hil_service.experiment.closed_loop import ClosedLoopSettings  # noqa: E402
from hil_service.experiment.family_loop import (  # noqa: E402
    HARM_LIMIT,
    PHASES,
    RELEASED,
    FamilyRow,
    run_vehicle,
)
from hil_service.pipeline import ControlSettings, PipelineSettings  # noqa: E402
from hil_service.umodel import structure  # noqa: E402
from plant_emulator.family import FamilyPlantSpec, draw_family  # noqa: E402


def features(row: FamilyRow) -> list[str]:
    spec = row.spec
    share = spec.disturbance_level / spec.authority() if spec.disturbance != "none" else 0.0
    size = (
        "none"
        if share == 0.0
        else "<0.1 A"
        if share < 0.1
        else "0.1-0.3 A"
        if share < 0.3
        else ">=0.3 A"
    )
    return [
        f"kind={spec.kind}",
        f"delay={spec.delay}",
        f"nmp={spec.zero is not None}",
        f"integrator={spec.integrator}",
        f"disturbance={spec.disturbance}",
        f"disturbance size={size}",
        f"scale {'<0.05' if spec.scale < 0.05 else '>=0.05'}",
    ]


def kind_of(row: FamilyRow) -> str:
    if not row.horizon_passed:
        return "never qualified"
    if row.trips:
        return "tripped (then safe input)"
    if row.commanded == 0:
        return "qualified, never commanded"
    return "commanded throughout"


def dominant_phase(row: FamilyRow) -> str:
    return max(PHASES, key=lambda p: row.phases.get(p, 0.0))


def _table(title: str, counts: Counter[str], totals: Counter[str]) -> None:
    print(f"  {title}")
    for key in sorted(totals):
        n, total = counts.get(key, 0), totals[key]
        print(f"    {key:<32} {n:>5} of {total:>5}  ({100.0 * n / total:5.1f} %)")


def summarise(name: str, rows: list[FamilyRow]) -> dict[str, object]:
    ratios = [r.reference_ratio for r in rows if r.reference_ratio is not None]
    above = [r for r in rows if (r.reference_ratio or 0.0) > HARM_LIMIT]
    passed = [r.oracle_ratio for r in rows if r.horizon_passed and r.oracle_ratio is not None]
    oracle_rows = [r for r in rows if r.oracle_iae is not None and r.reference_iae > 0]
    oracle_above = [r for r in oracle_rows if r.oracle_iae > HARM_LIMIT * r.reference_iae]
    summary = {
        "semantics": name,
        "plants": len(rows),
        "above_1.1x_reference_only": len(above),
        "worst_ratio_reference_only": round(max(ratios), 4) if ratios else None,
        "median_ratio_oracle_where_passed": round(float(np.median(passed)), 4) if passed else None,
        "rows_where_passed_with_oracle": len(passed),
        "share_controlled": round(sum(r.commanded > 0 for r in rows) / len(rows), 4),
        "oracle_above_1.1x_reference_only": f"{len(oracle_above)} of {len(oracle_rows)}",
        "trips": sum(r.trips for r in rows),
    }
    print(f"\n== {name}: " + json.dumps(summary))
    if above:
        _table(
            "what the channel did (above / all plants of that kind)",
            Counter(kind_of(r) for r in above),
            Counter(kind_of(r) for r in rows),
        )
        _table(
            "phase holding most of the IAE (of the plants above the limit)",
            Counter(dominant_phase(r) for r in above),
            Counter(dict.fromkeys(PHASES, len(above))),
        )
        _table(
            "by feature (above / all)",
            Counter(f for r in above for f in features(r)),
            Counter(f for r in rows for f in features(r)),
        )
        both = sum(1 for r in above if r in oracle_above)
        print(
            f"  of the {len(above)} above the limit, {both} are plants where the oracle is "
            f"above it too"
        )
        worst = sorted(above, key=lambda r: -(r.reference_ratio or 0.0))[:5]
        for r in worst:
            phases = ", ".join(f"{p} {r.phases.get(p, 0.0) / r.inverse_iae:.2f}" for p in PHASES)
            print(
                f"    {r.reference_ratio:7.2f}x  {r.name()}  {kind_of(r):<26} [{phases}]  "
                f"{r.spec.describe()}"
            )
    return summary


def run(
    seeds: Iterable[int],
    plants: int,
    samples: int,
    identify: int,
    step_every: int,
    oracle: bool,
    semantics: Iterable[str],
    progress: Callable[[str], None] = print,
    pipeline: Callable[[int, FamilyPlantSpec, FamilyPlantSpec], PipelineSettings | None] = (
        lambda seed, depth, pitch: None
    ),
) -> dict[str, list[FamilyRow]]:
    out: dict[str, list[FamilyRow]] = {s: [] for s in semantics}
    for seed in seeds:
        settings = ClosedLoopSettings(
            scenario="family",
            samples=samples,
            seed=seed,
            identify=identify,
            step_every=step_every,
            oracle=oracle,
            neutral_after_identify=True,
        )
        for name in out:
            t0 = time.perf_counter()
            found: list[FamilyRow] = []
            for depth, pitch in draw_family(seed, plants):
                found += run_vehicle(settings, depth, pitch, pipeline(seed, depth, pitch), name)[0]
            out[name] += found
            above = sum((r.reference_ratio or 0.0) > HARM_LIMIT for r in found)
            progress(
                f"seed {seed} {name}: {len(found)} plants in "
                f"{time.perf_counter() - t0:.0f} s, above {HARM_LIMIT}x: {above}"
            )
    return out


def what_if(
    horizon_fit: float | None,
    nb: int | None,
    nb_from_true_delay: int | None,
    mean_fit: float | None = None,
    lag_smoothing_gain: float | None = None,
    control_changes: dict[str, float] | None = None,
    degree: int | None = None,
    dead_zone: bool = True,
) -> Callable[[int, FamilyPlantSpec, FamilyPlantSpec], PipelineSettings | None]:
    """The pipeline settings of a what-if run (None: the defaults; a negative ``mean_fit``
    asks for no test against the mean). ``control_changes``: other ``ControlSettings``
    fields; ``degree``: the identifier's input polynomial degree; ``dead_zone``: the input
    dead zone chosen from the record (the default) or not."""
    chosen = (horizon_fit, nb, nb_from_true_delay, mean_fit, lag_smoothing_gain, degree)
    if all(v is None for v in chosen) and not control_changes and dead_zone:
        return lambda seed, depth, pitch: None

    def lags(spec: FamilyPlantSpec) -> dict[str, int]:
        options = {} if degree is None else {"degree": degree}
        if nb_from_true_delay is not None:
            return {**options, "nb": max(4, spec.delay + nb_from_true_delay)}
        return {**options, "nb": nb} if nb is not None else options

    def settings(seed: int, depth: FamilyPlantSpec, pitch: FamilyPlantSpec) -> PipelineSettings:
        control = dataclasses.replace(ControlSettings(), **(control_changes or {}))
        if horizon_fit is not None:
            control = dataclasses.replace(control, horizon_fit=horizon_fit)
        if mean_fit is not None:
            control = dataclasses.replace(control, mean_fit=None if mean_fit < 0 else mean_fit)
        options = {"depth": lags(depth), "pitch": lags(pitch)}
        settings = PipelineSettings(
            seed=seed, control=control, model_options=options, choose_dead_zone=dead_zone
        )
        if lag_smoothing_gain is not None:
            settings = settings.replace(lag_smoothing_gain=lag_smoothing_gain)
        return settings

    return settings


def set_dead_zone_margin(margin: float) -> None:
    """What-if: the tie of the input dead zone's choice in this process. The pipeline calls
    ``structure.choose_dead_zone`` without a margin, so its default is what is set."""
    choose = structure.choose_dead_zone
    names = list(inspect.signature(choose).parameters)
    defaults = list(choose.__defaults__ or ())
    defaults[names.index("margin") - (len(names) - len(defaults))] = margin
    choose.__defaults__ = tuple(defaults)


def control_change(text: str) -> tuple[str, float]:
    """``--control NAME=VALUE``: a numeric ``ControlSettings`` field and its value."""
    name, sep, value = text.partition("=")
    # The field types are classes where ControlSettings is compiled, strings where not.
    types = {
        f.name: getattr(f.type, "__name__", f.type) for f in dataclasses.fields(ControlSettings)
    }
    numeric = {n for n, t in types.items() if t in ("int", "float")}
    if not sep or name not in numeric:
        raise argparse.ArgumentTypeError(
            f"expected NAME=VALUE with NAME one of {', '.join(sorted(numeric))}, got {text!r}"
        )
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: not a number: {value!r}") from None
    return name, int(number) if types[name] == "int" else number


def best_of(paths: list[str], semantics: str = "hold") -> None:
    """Each saved run's plants above the limit, and how many stay above it when each plant
    keeps the lowest of its ratios over the runs: a bound on choosing among these runs'
    settings plant by plant (no deployed pipeline knows which to choose)."""
    runs = []
    for path in paths:
        with open(path, "rb") as f:
            found = pickle.load(f)[semantics]
        runs.append({row.name(): row.reference_ratio or 0.0 for row in found})
    names = sorted(set(runs[0]).intersection(*runs[1:]))
    first = runs[0]
    for path, ratios in zip(paths, runs, strict=True):
        above = sum(ratios[n] > HARM_LIMIT for n in names)
        line = f"{path}: {above} of {len(names)} above {HARM_LIMIT}x reference-only"
        if ratios is not first:
            # Against the first run: the geometric mean of the plants' ratios, and how many
            # moved by more than 1 % either way (plants whose ratio is 0 left out).
            pairs = [(ratios[n], first[n]) for n in names if ratios[n] > 0 and first[n] > 0]
            change = [a / b for a, b in pairs]
            mean = float(np.exp(np.mean(np.log(change)))) if change else float("nan")
            better = sum(c < 0.99 for c in change)
            worse = sum(c > 1.01 for c in change)
            line += (
                f"; against the first: geometric mean {mean:.4f}, better {better}, worse {worse}"
            )
        print(line)
    lowest = {n: min(r[n] for r in runs) for n in names}
    left = sorted((n for n in names if lowest[n] > HARM_LIMIT), key=lambda n: -lowest[n])
    print(f"the best of the {len(paths)} runs, plant by plant: {len(left)} above")
    for name in left:
        print(f"  {lowest[name]:.3f}  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[10, 11, 12, 13, 14])
    parser.add_argument("--plants", type=int, default=50)
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--identify", type=int, default=800)
    parser.add_argument("--step-every", type=int, default=300)
    parser.add_argument("--no-oracle", action="store_true")
    parser.add_argument("--semantics", nargs="+", choices=RELEASED, default=list(RELEASED))
    parser.add_argument("--save", help="also write the rows to this file (pickle)")
    parser.add_argument("--horizon-fit", type=float, help="the horizon test's threshold, %%")
    parser.add_argument(
        "--mean-fit",
        type=float,
        help="the horizon test's threshold against the mean, %% (negative: none)",
    )
    parser.add_argument("--nb", type=int, help="the identifier's input lags")
    parser.add_argument(
        "--nb-from-true-delay",
        type=int,
        metavar="E",
        help="input lags max(4, the plant's true delay + E): an upper bound, not a controller",
    )
    parser.add_argument(
        "--lag-smoothing-gain",
        type=float,
        metavar="K",
        help="the smoothness prior's gain on the input lags (0: none), as serve's flag",
    )
    parser.add_argument(
        "--control",
        type=control_change,
        action="append",
        metavar="NAME=VALUE",
        help="a ControlSettings constant (e.g. move_weight=0.1); may be repeated",
    )
    parser.add_argument("--degree", type=int, help="the identifier's input polynomial degree")
    parser.add_argument(
        "--no-dead-zone", action="store_true", help="no input dead zone chosen from the record"
    )
    parser.add_argument(
        "--dead-zone-margin",
        type=float,
        help="the dead zone choice's tie: the narrowest candidate within this of the best fit",
    )
    parser.add_argument(
        "--combine", nargs="+", help="summarise rows saved by earlier runs instead of running"
    )
    parser.add_argument(
        "--best-of",
        nargs="+",
        metavar="FILE",
        help="saved runs of the same plants: how many stay above the limit on the best of "
        "them, plant by plant (hold semantics)",
    )
    args = parser.parse_args()
    if args.best_of:
        best_of(args.best_of)
        return
    if args.combine:
        rows: dict[str, list[FamilyRow]] = {}
        for path in args.combine:
            with open(path, "rb") as f:
                for name, found in pickle.load(f).items():
                    rows.setdefault(name, []).extend(found)
        print(f"\ncombined {args.combine}")
        for name, found in rows.items():
            summarise(name, found)
        return
    if args.dead_zone_margin is not None:
        set_dead_zone_margin(args.dead_zone_margin)
    rows = run(
        args.seeds,
        args.plants,
        args.samples,
        args.identify,
        args.step_every,
        not args.no_oracle,
        args.semantics,
        pipeline=what_if(
            args.horizon_fit,
            args.nb,
            args.nb_from_true_delay,
            args.mean_fit,
            args.lag_smoothing_gain,
            dict(args.control or []),
            args.degree,
            not args.no_dead_zone,
        ),
    )
    print(
        f"\nseeds {args.seeds}, {args.plants} plants each, {args.samples} samples "
        f"({args.identify} identifying, a step every {args.step_every})"
    )
    for name, found in rows.items():
        summarise(name, found)
    if args.save:
        with open(args.save, "wb") as f:
            pickle.dump(rows, f)


if __name__ == "__main__":
    main()
