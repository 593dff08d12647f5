"""``glider-hil campaign``: many lockstep HIL missions, scored against reference-only control
and (``--oracle``) the known-model oracle; ``campaign compare DIR_A DIR_B`` pairs two.

    glider-hil campaign --scenarios disturbed,nonlinear,random --seeds 0-49 --steps 3600 \\
        --jobs 2 -o DIR [--resume] [--no-oracle]
    glider-hil campaign ... --scheduler tcp://HOST:PORT [--logs auto|shared|return]
    glider-hil campaign compare DIR_A DIR_B [--json]

Writes DIR/runs.csv, DIR/runs.json, DIR/summary.md, DIR/iae_ratios.png and one MCAP log per
run under DIR/runs/SCENARIO-sSEED/. With ``--scheduler`` each mission is a task on a Dask
cluster's workers (``hil_service/campaign/dask_engine.py``, docs/cluster.md).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil_service.campaign import SCENARIOS
from protocols.flag_types import positive_float, positive_int

if TYPE_CHECKING:
    from hil_service.campaign.runner import CampaignSpec

#: The exit status of a campaign stopped by Ctrl-C or SIGTERM (as a shell reports SIGINT).
INTERRUPTED = 130


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "action",
        nargs="?",
        choices=("run", "compare"),
        default="run",
        help="run a campaign (default) or compare two campaign directories",
    )
    parser.add_argument("dirs", nargs="*", metavar="DIR", help="compare: DIR_A DIR_B")
    _add_mission_arguments(parser)
    _add_execution_arguments(parser)
    _add_output_arguments(parser)
    parser.add_argument("--json", action="store_true", help="compare: print JSON")


def _add_mission_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("missions")
    group.add_argument(
        "--scenarios",
        default="disturbed,nonlinear,random",
        help=f"comma list of {', '.join(SCENARIOS)} (default %(default)s)",
    )
    group.add_argument("--seeds", default="0-49", help="N, N-M or a comma list (default 0-49)")
    group.add_argument(
        "--steps",
        type=mission_steps,
        default=3600,
        help="plant steps per mission, more than the identifier's burn-in (default 3600)",
    )
    group.add_argument(
        "--identify",
        type=positive_int,
        default=None,
        help="steps of open-loop excitation before the setpoints start, at least the "
        "identifier's burn-in (default steps/3)",
    )
    group.add_argument(
        "--step-every",
        type=positive_int,
        default=None,
        help="steps between setpoint steps (default steps/6)",
    )


def _add_execution_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("where the missions run (local processes or a Dask cluster)")
    group.add_argument(
        "--jobs",
        type=int,
        default=2,
        help="missions at a time (default 2; with --scheduler the cluster's worker threads decide)",
    )
    group.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="a Dask scheduler (tcp://HOST:PORT): run each mission as a task on its workers "
        "(docs/cluster.md)",
    )
    group.add_argument(
        "--scheduler-timeout",
        type=positive_float,
        default=60.0,
        metavar="S",
        help="wall s to reach the scheduler and for it to have a worker (default %(default)s)",
    )
    group.add_argument(
        "--logs",
        choices=("auto", "shared", "return"),
        default="auto",
        help="with --scheduler: where a mission's log goes. shared: the workers write into "
        "-o DIR (shared storage); return: it comes back with the result; auto (default): "
        "shared where a worker sees this -o DIR, else return",
    )


def _add_output_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("the campaign directory and each run")
    group.add_argument("-o", "--out", default=None, help="campaign directory")
    group.add_argument("--resume", action="store_true", help="skip missions already recorded")
    group.add_argument(
        "--oracle",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="run the known-model oracle offline per mission, for its IAE ratio (default on: "
        "about 2.5 CPU s per glider mission of 3,600 steps; --no-oracle skips it)",
    )
    group.add_argument(
        "--lockstep-timeout",
        type=positive_float,
        default=1.0,
        metavar="S",
        help="wall s a step waits for the service (default %(default)s)",
    )
    group.add_argument("--no-figures", action="store_true", help="no PNG")
    group.add_argument(
        "--kill-service",
        action="append",
        default=[],
        metavar="RUN_ID:STEP",
        help=argparse.SUPPRESS,  # fault injection for tests: SIGKILL that run's service
    )


def run(args: argparse.Namespace) -> int:
    if args.action == "compare":
        return _compare(args)
    try:
        spec = _campaign_spec(args)
    except ValueError as error:
        print(f"glider-hil campaign: {error}", file=sys.stderr)
        return 2
    # SIGTERM (kill, a batch system, docker stop) ends a campaign as Ctrl-C does.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        return _run_in_directory(args, spec)
    except KeyboardInterrupt:
        print(
            f"glider-hil campaign: interrupted: the missions recorded in {spec.out} are kept, "
            "the running ones are not; --resume runs the rest",
            file=sys.stderr,
        )
        return INTERRUPTED


def _campaign_spec(args: argparse.Namespace) -> CampaignSpec:
    """The campaign the flags describe; ValueError names a bad flag."""
    from hil_service.campaign.runner import CampaignSpec, parse_seeds

    if args.dirs:
        raise ValueError(f"unexpected arguments {args.dirs}")
    if args.out is None or not args.out.strip():
        raise ValueError("-o DIR is required")
    if args.scheduler is None and args.logs != "auto":
        raise ValueError("--logs needs --scheduler")
    if args.scheduler is not None:
        from hil_service.campaign.dask_engine import check_scheduler_address

        check_scheduler_address(args.scheduler)
    scenarios = tuple(s.strip() for s in args.scenarios.split(",") if s.strip())
    unknown = [s for s in scenarios if s not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenarios {unknown}; choose from {SCENARIOS}")
    kills = {}
    for item in args.kill_service:
        run_id, _, step = item.rpartition(":")
        kills[run_id] = int(step)
    spec = CampaignSpec(
        scenarios=scenarios,
        seeds=parse_seeds(args.seeds),
        out=Path(args.out),
        steps=args.steps,
        jobs=args.jobs,
        identify=args.identify,
        step_every=args.step_every,
        oracle=args.oracle,
        timeout=args.lockstep_timeout,
        resume=args.resume,
        kill_service=kills,
    )
    check_mission_segments(spec)
    return spec


def _run_in_directory(args: argparse.Namespace, spec: CampaignSpec) -> int:
    """Lock ``-o DIR`` (one campaign at a time in it), check it, run the missions, write
    the tables; the exit status."""
    from hil_service.campaign.runner import CampaignInUse, CampaignLock, check_resume

    try:
        lock = CampaignLock(spec.out)
    except CampaignInUse as error:
        print(f"glider-hil campaign: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(
            f"glider-hil campaign: -o {spec.out}: cannot use it as the campaign directory: "
            f"{error.strerror or error}",
            file=sys.stderr,
        )
        return 2
    could_not_start = False
    try:
        try:
            if not args.resume and (spec.out / "runs").exists():
                raise ValueError(f"{spec.out} already holds runs: --resume, or another -o")
            check_resume(spec)  # before a scheduler is reached or anything is written
        except ValueError as error:
            print(f"glider-hil campaign: {error}", file=sys.stderr)
            return 2
        code = _run_missions(args, spec)
        could_not_start = code == 2  # the scheduler: nothing was written
        return code
    finally:
        lock.release(remove_if_new=could_not_start)


def _run_missions(args: argparse.Namespace, spec: CampaignSpec) -> int:
    """Run the campaign and write its tables: 0, 1 when every mission failed or the
    campaign stopped before it recorded them all (those it did are written), 2 when the
    scheduler cannot be used (nothing written)."""
    from hil_service.campaign.runner import CampaignStopped, run_campaign

    started = time.monotonic()
    stopped: CampaignStopped | None = None
    try:
        if args.scheduler is None:
            rows = run_campaign(spec)
        else:
            from hil_service.campaign.dask_engine import SchedulerUnusable, run_campaign_dask

            try:
                rows = run_campaign_dask(spec, args.scheduler, args.logs, args.scheduler_timeout)
            except SchedulerUnusable as error:
                print(f"glider-hil campaign: {error}", file=sys.stderr)
                return 2
    except CampaignStopped as error:
        stopped, rows = error, error.rows
    except OSError as error:
        print(f"glider-hil campaign: {error}", file=sys.stderr)
        return 1
    counts = _write_tables(args, spec, rows, time.monotonic() - started)
    if stopped is not None:
        print(f"glider-hil campaign: {stopped}", file=sys.stderr)
        return 1
    if counts["failed"] == len(rows):
        print(
            f"glider-hil campaign: every mission failed (reasons in {spec.out / 'summary.md'})",
            file=sys.stderr,
        )
        return 1
    return 0


def _write_tables(
    args: argparse.Namespace, spec: CampaignSpec, rows: list[dict[str, Any]], wall: float
) -> dict[str, int]:
    """runs.csv, runs.json, summary.md and the figure of the recorded rows (none when no
    row is), and the JSON line on stdout; the count of each status."""
    from hil_service.campaign.summary import write_outputs

    if rows:
        write_outputs(spec.out, rows, spec.to_json(), figures=not args.no_figures, wall_s=wall)
    counts = {k: sum(r.get("status") == k for r in rows) for k in ("ok", "diverged", "failed")}
    not_recorded = len(spec.missions()) - len(rows)
    print(
        json.dumps(
            {
                "campaign": {
                    "runs": len(rows),
                    **counts,
                    **({"not_recorded": not_recorded} if not_recorded else {}),
                    "wall_s": round(wall, 1),
                    "out": str(spec.out),
                }
            }
        ),
        flush=True,
    )
    return counts


def burn_in() -> int:
    """Samples the identifier learns from before its controller may act (``pipeline.py``):
    the campaign's service runs the default pipeline (``hil_run.service_config``). Imported
    here, not with the module: the verb's parser is built without the numerics."""
    from hil_service.pipeline import PipelineSettings

    return PipelineSettings().burn_in


def mission_steps(text: str) -> int:
    """``--steps``: more plant steps than the identifier's burn-in, the least a mission
    needs for its controller ever to act."""
    steps, least = positive_int(text), burn_in()
    if steps <= least:
        raise argparse.ArgumentTypeError(
            f"expected more than the identifier's burn-in of {least} steps, got {text!r}"
        )
    return steps


def check_mission_segments(spec: CampaignSpec) -> None:
    """Refuse missions too short to score control: the identification segment must hold
    the identifier's burn-in (the controller may not act before it, so the first scored
    setpoints would meet the vehicle's excitation), and the control segment a setpoint
    change after its first level (where the divergence check starts)."""
    mission = spec.missions()[0]  # every mission of a campaign has the same segments
    least = burn_in()
    if mission.identify < least:
        what, remedy = f"--identify {mission.identify}", f"--identify {least} or more"
        if spec.identify is None:  # the default, a third of the steps
            what = f"{what} (a third of --steps {spec.steps})"
            remedy = f"{remedy}, or --steps {3 * least} or more"
        raise ValueError(
            f"{what} is shorter than the identifier's burn-in of {least} steps: give {remedy}"
        )
    if mission.steps - mission.identify <= mission.step_every:
        raise ValueError(
            f"--steps {mission.steps} leaves {mission.steps - mission.identify} steps of "
            f"control after --identify {mission.identify}, not more than one --step-every "
            f"{mission.step_every}: no setpoint step to score"
        )


def _compare(args: argparse.Namespace) -> int:
    from hil_service.campaign.compare import (
        compare,
        format_table,
        load_runs,
        mission_differences,
    )

    if len(args.dirs) != 2:
        print("glider-hil campaign compare: give DIR_A DIR_B", file=sys.stderr)
        return 2
    different = mission_differences(Path(args.dirs[0]), Path(args.dirs[1]))
    if different:
        print(
            f"glider-hil campaign compare: {args.dirs[0]} and {args.dirs[1]} ran different "
            f"missions ({', '.join(different)}): their figures do not pair",
            file=sys.stderr,
        )
        return 2
    try:
        a, b = (load_runs(Path(d)) for d in args.dirs)
    except ValueError as error:
        print(f"glider-hil campaign compare: {error}", file=sys.stderr)
        return 2
    for directory, runs in zip(args.dirs, (a, b), strict=True):
        if runs.skipped:
            print(
                f"glider-hil campaign compare: {Path(directory) / 'runs.json'}: skipped "
                f"{runs.skipped} of {runs.skipped + len(runs.rows)} rows that are not a run "
                "with a scenario name and an integer seed",
                file=sys.stderr,
            )
    results = compare(a.rows, b.rows)
    if not results:
        print(
            f"glider-hil campaign compare: no pairs to compare: no scenario and seed is ok in "
            f"both {args.dirs[0]} and {args.dirs[1]} with a compared metric in both",
            file=sys.stderr,
        )
        return 1
    if args.json:
        skipped = {"a": a.skipped, "b": b.skipped}
        print(json.dumps({"compare": results, "skipped_rows": skipped}))
    else:
        print(format_table(results, args.dirs[0], args.dirs[1]))
    return 0
