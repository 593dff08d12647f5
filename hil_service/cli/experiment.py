"""``glider-hil experiment``: the paper's identification experiment, closed loop, speed.

Runs the emulator's plant models in-process (no sockets). By default: every model
(``paper``, ``dynamic``, ``rls-arx``, ``persistence``) on the same samples, scored on the
a-priori one-step prediction after a burn-in, and on the free-run fit and k-step NMSE of
the model frozen at ``--fit-split`` (``umodel/multistep.py``). ``--closed-loop`` tracks
setpoint steps with the inverse controller and compares with the reference-only plant and
with the oracle, a known-model constrained controller (``experiment/oracle.py``);
``--scenario random`` runs it on a seeded family of plants it was not tuned on.
``--bench`` prints how many samples per second one channel identifies and inverts on one
core. ``--log FILE.mcap`` runs the identification experiment on a log's recorded samples
instead of the emulator (a field import by its dives, ``experiment/field.py``). A flag
typed for an experiment that does not use it is refused, as are ``--samples`` beyond the
largest run and a typed ``--step-every`` with no second setpoint step in the run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.experiment.closed_loop import ClosedLoopResult, ClosedLoopSettings, run_closed_loop
from hil_service.experiment.family_loop import FamilyResult, run_family_closed_loop
from hil_service.experiment.field import FieldExperiment, field_table, run_field_experiment
from hil_service.experiment.identification import (
    IdentificationResult,
    IdentificationSettings,
    run_identification,
)
from hil_service.experiment.random_loop import (
    DEFAULT_PLANTS,
    RandomResult,
    run_random_closed_loop,
)
from hil_service.experiment.speed import measure_all
from hil_service.offline.plots import prediction_figure, tracking_figure
from hil_service.pipeline import PipelineSettings
from plant_emulator.excitation import EXCITATIONS
from plant_emulator.models import CHANNELS
from plant_emulator.scenarios import SCENARIOS
from protocols import compiled
from protocols.flag_types import non_negative_int

#: The most plant steps a run takes: the identification experiment holds about 0.9 kB per
#: sample at its peak (measured: 0.86 kB; ``--scenario all --channel all`` 1.7 kB, the
#: closed loop 0.15 kB), so the largest run stays near 1 GB. The documented runs take 20,000.
MAX_SAMPLES = 1_000_000
#: The most plants a family run takes: the documented runs take 200, at about three plants
#: a second on one core (2,000 samples each, no oracle), so this is an hour there and
#: hours with the oracle; more is a run that seems to hang. Another ``--seed`` draws other
#: plants.
MAX_PLANTS = 10_000

#: The experiments, each named by the flag that chooses it (``IDENTIFICATION``: none).
IDENTIFICATION = "the identification experiment"
CLOSED_LOOP = "--closed-loop"
BENCH = "--bench"
LOG = "--log"

#: The experiments each flag is for; ``--json`` and the flags choosing an experiment are
#: for every one. A flag typed for an experiment that does not use it is refused.
USED_BY: dict[str, tuple[str, ...]] = {
    "--scenario": (IDENTIFICATION, CLOSED_LOOP, BENCH),
    "--channel": (IDENTIFICATION,),
    "--samples": (IDENTIFICATION, CLOSED_LOOP, BENCH),
    "--seed": (IDENTIFICATION, CLOSED_LOOP, BENCH),
    "--burn-in": (IDENTIFICATION,),
    "--excitation": (IDENTIFICATION, CLOSED_LOOP),
    "--plots": (IDENTIFICATION, CLOSED_LOOP),
    "--identify": (CLOSED_LOOP,),
    "--step-every": (CLOSED_LOOP,),
    "--no-oracle": (CLOSED_LOOP,),
    "--plants": (CLOSED_LOOP,),
    "--input-lags": (CLOSED_LOOP,),
    "--fit-split": (IDENTIFICATION,),
    "--horizon": (IDENTIFICATION,),
    "--split": (LOG,),
}
#: Closed-loop scenarios of a seeded family of plants: ``--plants`` is for them alone, and
#: they draw no figures.
FAMILY_SCENARIOS = ("random", "family")
#: Where ``_Typed`` notes the flags typed on the command line.
TYPED = "typed_flags"
#: The switches of ``USED_BY`` (flag → attribute): typed exactly when true.
SWITCHES = {"--no-oracle": "no_oracle"}


class _Typed(argparse.Action):
    """argparse's ``store``, which also notes the flag in ``namespace.typed_flags``: a flag
    the user typed, whatever its value, and never one left at its default."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        setattr(namespace, self.dest, values)
        typed: frozenset[str] = getattr(namespace, TYPED, frozenset())
        setattr(namespace, TYPED, typed | {self.option_strings[0]})


def _figure_directory(text: str) -> Path:
    """``--plots DIR``: a directory named; an empty one would be the current directory."""
    if not text:
        raise argparse.ArgumentTypeError("expected a directory, got '' (the current one is .)")
    return Path(text)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.set_defaults(**{TYPED: frozenset()})
    _add_plant_arguments(parser)
    _add_output_arguments(parser)
    _add_mode_arguments(parser)
    _add_closed_loop_arguments(parser)
    _add_identification_arguments(parser)


def _add_plant_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("plant and samples")
    group.add_argument(
        "--scenario",
        action=_Typed,
        choices=(*SCENARIOS, "random", "family", "all"),
        default="paper",
        help="'random': a seeded family of plants; 'family': the do-no-harm benchmark's "
        "family (plant_emulator/family.py; closed loop only)",
    )
    group.add_argument(
        "--channel",
        action=_Typed,
        choices=(*CHANNELS, "all"),
        default="depth",
        help="identification: the channel (the closed loop and --bench run both)",
    )
    group.add_argument(
        "--samples",
        action=_Typed,
        type=int,
        default=5000,
        help=f"plant steps, at most {MAX_SAMPLES:,} (about 1 kB each; default 5000)",
    )
    group.add_argument("--seed", action=_Typed, type=non_negative_int, default=0)
    group.add_argument(
        "--burn-in",
        action=_Typed,
        type=int,
        default=None,
        help="identification: samples not scored (default: a fifth)",
    )
    group.add_argument("--excitation", action=_Typed, choices=EXCITATIONS, default="steps")


def _add_output_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("output")
    group.add_argument(
        "--json",
        action="store_true",
        help="print JSON: one object, or a list of objects for 'all'",
    )
    group.add_argument(
        "--plots",
        action=_Typed,
        type=_figure_directory,
        metavar="DIR",
        help="write PNG figures here (identification; closed loop on paper, disturbed, nonlinear)",
    )


def _add_mode_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("experiment (default: identification)")
    mode = group.add_mutually_exclusive_group()
    mode.add_argument(
        "--closed-loop",
        action="store_true",
        help="track depth and pitch setpoint steps with the inverse controller",
    )
    mode.add_argument(
        "--bench", action="store_true", help="samples/s of identifier + inverse per channel"
    )


def _add_closed_loop_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("closed loop")
    group.add_argument(
        "--identify",
        action=_Typed,
        type=int,
        default=1500,
        help="closed loop: open-loop samples before control starts (default 1500)",
    )
    group.add_argument(
        "--step-every",
        action=_Typed,
        type=int,
        default=800,
        help="closed loop: samples between setpoint steps (default 800; given, less than "
        "--samples minus --identify, so that a second step comes)",
    )
    group.add_argument(
        "--no-oracle",
        action="store_true",
        help="closed loop: skip the known-model oracle (an LP per sample: slow)",
    )
    group.add_argument(
        "--plants",
        action=_Typed,
        type=int,
        default=DEFAULT_PLANTS,
        help=f"scenarios random and family: plants per run (default {DEFAULT_PLANTS})",
    )
    group.add_argument(
        "--input-lags",
        action=_Typed,
        default=None,
        metavar="N|auto",
        help="closed loop: the identifier's input lags in samples or auto, as serve "
        "--input-lags (default auto)",
    )


def _add_identification_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("identification")
    group.add_argument(
        "--fit-split",
        action=_Typed,
        type=int,
        default=None,
        help="identification: free-run fit and k-step NMSE after this sample (default: half)",
    )
    group.add_argument(
        "--log",
        action=_Typed,
        type=Path,
        metavar="FILE.mcap",
        help="identification on a log's recorded samples (a field import by its dives) "
        "instead of the emulator's plant",
    )
    group.add_argument(
        "--split",
        action=_Typed,
        choices=("first", "alternate", "both"),
        default="first",
        help="--log of a field import: the first half of the dives trains, every other "
        "dive trains, or both (default first)",
    )
    group.add_argument(
        "--horizon",
        action=_Typed,
        type=int,
        default=None,
        help="identification: k of the k-step NMSE (default: the horizon the predictive "
        "inverse derives from the frozen dynamic model)",
    )


def run(args: argparse.Namespace) -> int:
    try:
        check_flags(args)
        if args.log is not None:
            return _field(args)
        if args.bench:
            return _bench(args)
        if args.plots:
            _plots_directory(args.plots)
        if args.closed_loop:
            return _closed_loop(args)
        return _identification(args)
    except ValueError as error:
        print(f"glider-hil experiment: {error}", file=sys.stderr)
        return 2


def check_flags(args: argparse.Namespace) -> None:
    """Raise ValueError, naming the flag, for flags the chosen experiment would ignore or
    that it cannot run with: one typed for another experiment, ``--samples`` beyond
    ``MAX_SAMPLES``, ``--plants`` outside 1..``MAX_PLANTS``, a ``--step-every`` no second
    setpoint step would come within."""
    experiment = _experiment(args)
    if experiment == LOG and (args.closed_loop or args.bench):
        raise ValueError("--log runs the identification experiment (no --closed-loop, --bench)")
    typed = typed_flags(args)
    for flag in sorted(typed, key=list(USED_BY).index):
        problem = _unused_problem(flag, experiment, args.scenario)
        if problem:
            raise ValueError(problem)
    if args.samples > MAX_SAMPLES:
        raise ValueError(
            f"--samples must be at most {MAX_SAMPLES:,} (a run holds about 1 kB per "
            f"sample), got {args.samples}"
        )
    if not 1 <= args.plants <= MAX_PLANTS:
        raise ValueError(
            f"--plants must be 1..{MAX_PLANTS:,} (the most is an hour's run or more; another "
            f"--seed draws other plants), got {args.plants}"
        )
    if "--step-every" in typed:
        _check_step_every(args)


def typed_flags(args: argparse.Namespace) -> frozenset[str]:
    """The flags of ``USED_BY`` the user typed: switches that are on, and value flags
    ``_Typed`` noted (a value equal to its default included, a default never)."""
    typed = set(getattr(args, TYPED, frozenset()))
    typed.update(flag for flag, dest in SWITCHES.items() if getattr(args, dest, False))
    return frozenset(flag for flag in typed if flag in USED_BY)


def _experiment(args: argparse.Namespace) -> str:
    if args.log is not None:
        return LOG
    if args.bench:
        return BENCH
    return CLOSED_LOOP if args.closed_loop else IDENTIFICATION


def _unused_problem(flag: str, experiment: str, scenario: str) -> str:
    """Why ``flag`` does nothing in ``experiment`` on ``scenario``, or "" when it is used."""
    used_by = USED_BY[flag]
    if experiment not in used_by:
        return f"{flag} does not apply to {experiment}: it is for {_either(used_by)}"
    if experiment == BENCH and flag == "--scenario" and scenario not in SCENARIOS:
        return (
            f"--scenario {scenario} does not apply to --bench: it times one plant scenario, "
            f"{_either(SCENARIOS)} (default paper)"
        )
    family = scenario in FAMILY_SCENARIOS
    if experiment == CLOSED_LOOP and flag == "--plants" and not family:
        return (
            f"--plants does not apply to --scenario {scenario}: it is for the closed loop's "
            f"--scenario {' and '.join(FAMILY_SCENARIOS)}"
        )
    if experiment == CLOSED_LOOP and flag == "--plots" and family:
        return (
            f"--plots: the closed loop's --scenario {scenario} draws no figures (paper, "
            "disturbed and nonlinear do)"
        )
    return ""


def _either(names: tuple[str, ...]) -> str:
    """``a``, ``a or b``, ``a, b or c``."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def _check_step_every(args: argparse.Namespace) -> None:
    """``--step-every`` as typed: a second setpoint (at sample ``identify + step_every``)
    must come before the run ends, else any value that large runs the same. A run with
    nothing to control is left to ``ClosedLoopSettings``, which names ``identify``."""
    controlled = args.samples - args.identify
    if args.identify >= 1 and controlled > 1 and args.step_every >= controlled:
        raise ValueError(
            f"--step-every {args.step_every} leaves one setpoint: the run controls "
            f"{controlled} samples (--samples {args.samples} minus --identify "
            f"{args.identify}), and a second step needs --step-every below {controlled}"
        )


def _field(args: argparse.Namespace) -> int:
    splits = ("first", "alternate") if args.split == "both" else (args.split,)
    results: list[FieldExperiment] = [run_field_experiment(args.log, split) for split in splits]
    # As replay and report say it: a log cut short or damaged is used as far as it reads.
    for recovery in dict.fromkeys(r.recovery for r in results if r.recovery):
        print(f"glider-hil experiment: {recovery}", file=sys.stderr)
    _emit(results, args.json, field_table)
    return 0


def _plots_directory(directory: Path) -> None:
    """Create ``--plots DIR`` before the experiment runs, so that a path that cannot be a
    writable directory is refused before a run of minutes rather than after it."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ValueError(
            f"--plots {directory}: cannot create the directory ({error.strerror})"
        ) from None
    if not os.access(directory, os.W_OK | os.X_OK):
        raise ValueError(f"--plots {directory}: the directory is not writable")


def _choices(value: str, options: tuple[str, ...]) -> tuple[str, ...]:
    return options if value == "all" else (value,)


# ---- identification ----------------------------------------------------------------------
def _identification(args: argparse.Namespace) -> int:
    if args.scenario in ("random", "family"):
        raise ValueError(
            f"--scenario {args.scenario} is a closed-loop scenario (add --closed-loop)"
        )
    results = []
    for scenario in _choices(args.scenario, SCENARIOS):
        for channel in _choices(args.channel, CHANNELS):
            settings = IdentificationSettings(
                scenario=scenario,
                channel=channel,
                samples=args.samples,
                seed=args.seed,
                burn_in=args.burn_in,
                excitation=args.excitation,
                fit_split=args.fit_split,
                horizon=args.horizon,
            )
            result = run_identification(settings)
            results.append(result)
            if args.plots:
                _identification_plots(result, args.plots)
    _emit(results, args.json, identification_table)
    if args.plots and not args.json:
        print(f"figures in {args.plots}")
    return 0


def _emit(results: list[Any], as_json: bool, table: Callable[[list[Any]], str]) -> None:
    """One JSON object per result (one object alone when there is one), or the table."""
    if as_json:
        objects = [r.as_json() for r in results]
        print(json.dumps(objects[0] if len(objects) == 1 else objects))
    else:
        print(table(results))


def identification_table(results: list[IdentificationResult]) -> str:
    first = results[0].settings
    lines = [
        f"one-step a-priori prediction, {first.samples} samples, burn-in "
        f"{first.effective_burn_in}, seed {first.seed}, excitation {first.excitation}; "
        f"free-run fit % and k-step NMSE of the model frozen at sample "
        f"{first.effective_fit_split}, on the samples after it; k "
        f"{'given' if first.horizon is not None else 'derived as the controller does'}",
        f"{'scenario':10s} {'channel':7s} {'model':12s} {'NMSE':>10s} {'skill':>8s} "
        f"{'converged_at':>12s} {'fit %':>9s} {'k':>4s} {'k-step NMSE':>12s}",
    ]
    for result in results:
        for name, trace in result.models.items():
            lines.append(
                f"{result.settings.scenario:10s} {result.settings.channel:7s} {name:12s} "
                f"{_fmt(trace.nmse, '.5f'):>10s} {_fmt(trace.skill, '.3f'):>8s} "
                f"{_fmt(trace.converged_at, 'd', 'never'):>12s} {_fmt(trace.fit, '.1f'):>9s} "
                f"{result.horizon:>4d} {_fmt(trace.k_step_nmse, '.4g'):>12s}"
            )
    return "\n".join(lines)


def _identification_plots(result: IdentificationResult, directory: Path) -> None:
    s = result.settings
    t = np.arange(s.samples, dtype=float)
    for name, trace in result.models.items():
        prediction_figure(
            directory / f"{s.scenario}_{s.channel}_{name}.png",
            f"{name} model, {s.channel}, scenario {s.scenario}: NMSE {_fmt(trace.nmse, '.5f')},"
            f" skill {_fmt(trace.skill, '.3f')}",
            s.channel,
            t,
            result.y,
            trace.y_hat,
            None if name == "persistence" else trace.alpha,
        )


# ---- closed loop -------------------------------------------------------------------------
def _closed_loop(args: argparse.Namespace) -> int:
    scenarios = _choices(args.scenario, SCENARIOS)
    results: list[ClosedLoopResult | RandomResult | FamilyResult] = []
    pipeline = (
        None
        if args.input_lags is None
        else PipelineSettings(seed=args.seed).with_input_lag_choice(args.input_lags)
    )
    for scenario in scenarios:
        settings = ClosedLoopSettings(
            scenario=scenario,
            samples=args.samples,
            seed=args.seed,
            identify=args.identify,
            step_every=args.step_every,
            excitation=args.excitation,
            oracle=not args.no_oracle,
        )
        if scenario == "random":
            random_result = run_random_closed_loop(settings, args.plants, pipeline)
            results.append(random_result)
            continue
        if scenario == "family":
            results.append(run_family_closed_loop(settings, args.plants, pipeline))
            continue
        result = run_closed_loop(settings, pipeline)
        results.append(result)
        if args.plots:
            _closed_loop_plots(result, args.plots)
    _emit(results, args.json, lambda rs: "\n\n".join(_closed_loop_text(r) for r in rs))
    return 0


def _closed_loop_text(result: ClosedLoopResult | RandomResult | FamilyResult) -> str:
    if isinstance(result, RandomResult):
        return random_table(result)
    if isinstance(result, FamilyResult):
        return family_table(result)
    return closed_loop_table(result)


def family_table(result: FamilyResult) -> str:
    s = result.settings
    summary = result.summary()
    lines = [
        f"closed loop, scenario family ({summary['plants']} plants, two per vehicle, seed "
        f"{s.seed}), {s.samples} samples ({s.identify} identifying, then a setpoint step every "
        f"{s.step_every}); IAE in output units·s",
        f"{'veh':>4s} {'ch':5s} {'inverse':>11s} {'ref-only':>11s} {'oracle':>11s} "
        f"{'inv/ref':>8s} {'inv/orc':>8s} {'trips':>5s} {'passed':>6s} {'cmd':>6s}  plant",
    ]
    for row in result.rows:
        r = row.as_json()
        lines.append(
            f"{row.spec.vehicle:>4d} {row.spec.channel:5s} {_fmt(r['inverse_iae'], '11.4g'):>11s} "
            f"{_fmt(r['reference_only_iae'], '11.4g'):>11s} {_fmt(r['oracle_iae'], '11.4g'):>11s} "
            f"{_fmt(r['iae_ratio_reference_only'], '.3f'):>8s} "
            f"{_fmt(r['iae_ratio_oracle'], '.3f'):>8s} {row.trips:>5d} "
            f"{'yes' if row.horizon_passed else 'no':>6s} {row.commanded:>6d}  "
            f"{row.spec.describe()}"
        )
    lines.append(
        f"worst inverse / reference-only {_fmt(summary['worst_ratio_reference_only'], '.3f')} "
        f"({summary['above_harm_limit']} plants above 1.1); median inverse / oracle where the "
        f"horizon test passed {_fmt(summary['median_ratio_oracle_where_passed'], '.3f')} "
        f"({summary['oracle_rows_where_passed']} plants with an oracle); horizon test passed "
        f"on {summary['horizon_passed']}, controlled {summary['controlled']} of "
        f"{summary['plants']} ({_fmt(summary['share_controlled'], '.3f')}); supervisor trips "
        f"{summary['trips']}; oracle LP failures {summary['oracle_failures']}"
    )
    return "\n".join(lines)


def random_table(result: RandomResult) -> str:
    s = result.settings
    data = result.as_json()
    summary = data["summary"]
    lines = [
        f"closed loop, scenario random ({summary['plants']} plants, two per vehicle, seed "
        f"{s.seed}), {s.samples} samples ({s.identify} identifying, then a setpoint step every "
        f"{s.step_every}); IAE in output units·s, ratios to the oracle",
        f"{'plant':>5s} {'ch':5s} {'inverse':>10s} {'ref-only':>10s} {'oracle':>10s} "
        f"{'inv/orc':>8s} {'ref/orc':>8s} {'div':>4s} {'nonfin':>6s}  plant",
    ]
    for row in result.rows:
        r = row.as_json()
        lines.append(
            f"{row.spec.index:>5d} {row.channel:5s} {r['inverse_iae']:10.3f} "
            f"{r['reference_only_iae']:10.3f} {_fmt(r['oracle_iae'], '10.3f'):>10s} "
            f"{_fmt(r['iae_ratio_oracle'], '.3f'):>8s} "
            f"{_fmt(r['reference_only_ratio_oracle'], '.3f'):>8s} {row.divergences:>4d} "
            f"{row.non_finite_commands:>6d}  {row.spec.describe()}"
        )
    lines.append(
        f"inverse / oracle: median {_fmt(summary['median_ratio'], '.3f')}, max "
        f"{_fmt(summary['max_ratio'], '.3f')}, {summary['above_2x']} plants above 2×; "
        f"identifier divergences {summary['divergences']}; non-finite commands "
        f"{summary['non_finite_commands']}; blocked steps {summary['blocked_steps']}; "
        f"oracle LP failures {summary['oracle_failures']}"
    )
    return "\n".join(lines)


def closed_loop_table(result: ClosedLoopResult) -> str:
    s = result.settings
    data = result.as_json()
    lines = [
        f"closed loop, scenario {s.scenario}, {s.samples} samples ({s.identify} identifying, "
        f"then a setpoint step every {s.step_every}), seed {s.seed}",
        f"{'channel':7s} {'run':15s} {'IAE':>10s} {'overshoot%':>10s} {'settling s':>10s} "
        f"{'settled':>8s}",
    ]
    for ch in CHANNELS:
        for run_name in ("inverse", "reference_only", "oracle"):
            m = data["channels"][ch][run_name]
            if m is None:
                continue
            lines.append(
                f"{ch:7s} {run_name:15s} {m['iae']:10.2f} {_fmt(m['overshoot_pct'], '.1f'):>10s}"
                f" {_fmt(m['settling_s'], '.0f'):>10s} {m['settled_steps']:>4d}/{m['steps']:<3d}"
            )
        entry = data["channels"][ch]
        bound = entry["iae_lower_bound"]
        if bound is not None:
            lines.append(
                f"{ch:7s} {'bound':15s} {bound:10.2f}   (non-minimum-phase zero: no causal "
                f"controller does better on these steps)"
            )
        lines.append(f"{ch:7s} IAE inverse / reference-only = {_fmt(entry['iae_ratio'], '.3f')}")
        if entry["oracle"] is not None:
            ratio = entry["oracle_ratio"]
            lines.append(
                f"{ch:7s} IAE / oracle: inverse {_fmt(ratio['inverse'], '.3f')}, reference-only "
                f"{_fmt(ratio['reference_only'], '.3f')}"
            )
    lines.append(
        f"solver paths {data['solver_paths']}; blocked steps {data['blocked_steps']}; "
        f"identifier divergences {data['divergences']}; non-finite commands "
        f"{data['non_finite_commands']}; oracle LP failures {data['oracle_failures']}"
    )
    return "\n".join(lines)


def _closed_loop_plots(result: ClosedLoopResult, directory: Path) -> None:
    t = np.arange(result.settings.samples, dtype=float)
    for ch in CHANNELS:
        tracking_figure(
            directory / f"closed_loop_{result.settings.scenario}_{ch}.png",
            f"{ch} setpoint steps, scenario {result.settings.scenario}",
            ch,
            t,
            [
                ("inverse control", result.inverse.y[ch]),
                ("reference only", result.reference_only.y[ch]),
                *([("oracle", result.oracle.y[ch])] if result.oracle is not None else []),
            ],
            result.inverse.setpoint[ch],
            [
                ("inverse control", result.inverse.u[ch]),
                ("reference only", result.reference_only.u[ch]),
                *([("oracle", result.oracle.u[ch])] if result.oracle is not None else []),
            ],
        )
        # One step as the paper shows it (output, setpoint, input): the second controlled
        # step (the first follows the identification phase's excitation), inverse beside
        # the oracle.
        settings = result.settings
        first = settings.identify + settings.step_every
        if first >= settings.samples:
            continue  # a run too short for a second step
        runs = [("inverse control", result.inverse)]
        if result.oracle is not None:
            runs.append(("oracle", result.oracle))
        # Twice the slower run's time to the settle band, so that a fast step is visible.
        settle = max(
            _settled_after(run.y[ch], run.setpoint[ch], first, settings) for _, run in runs
        )
        length = min(settings.step_every, max(20, 2 * settle))
        window = slice(max(0, first - length // 8), first + length)
        tracking_figure(
            directory / f"step_{settings.scenario}_{ch}.png",
            f"one {ch} step, scenario {settings.scenario}, seed {settings.seed}",
            ch,
            t[window],
            [(label, run.y[ch][window]) for label, run in runs],
            result.inverse.setpoint[ch][window],
            [(label, run.u[ch][window]) for label, run in runs],
        )


def _settled_after(
    y: np.ndarray, setpoint: np.ndarray, first: int, settings: ClosedLoopSettings
) -> int:
    """Samples after ``first`` until ``y`` stays within the settle band of the step there."""
    stop = min(first + settings.step_every, y.size)
    size = abs(float(setpoint[first] - setpoint[first - 1]))
    error = np.abs(y[first:stop] - setpoint[first:stop])
    outside = np.nonzero(~(error <= settings.settle_band * max(size, 1e-12)))[0]
    return int(outside[-1]) + 1 if outside.size else 0


# ---- speed -------------------------------------------------------------------------------
def _bench(args: argparse.Namespace) -> int:
    if args.samples < 1:
        raise ValueError(f"--samples must be at least 1, got {args.samples}")
    scenario = args.scenario  # one of SCENARIOS: check_flags refuses the others
    figures = measure_all(args.samples, scenario, args.seed)
    modules = compiled.summary()
    if args.json:
        print(json.dumps([{**f.__dict__, "modules": modules} for f in figures]))
        return 0
    print(
        f"one channel on one core, {args.samples} samples, scenario {scenario}; "
        f"best of {figures[0].repeats} runs (median in brackets); modules {modules}"
    )
    print(
        f"{'channel':7s} {'model':8s} {'update/s':>10s} {'update+inverse/s':>26s} {'fallback':>9s}"
    )
    for f in figures:
        control = f"{f.control_per_s:,.0f} ({f.control_per_s_median:,.0f})"
        print(
            f"{f.channel:7s} {f.model:8s} {f.update_per_s:10,.0f} {control:>26s} "
            f"{f.fallback_share:9.1%}"
        )
    return 0


def _fmt(value: Any, spec: str, missing: str = "-") -> str:
    return missing if value is None else format(value, spec)
