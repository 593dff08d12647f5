"""Runs a campaign: every (scenario, seed) mission in a forked worker, ``jobs`` at a time.

Each worker runs one mission (``hil_run.run_hil``: its own forked service), scores it and
writes ``runs/RUN_ID/run.json``; the parent only forks, waits and collects. A worker that
dies, or a mission that fails or diverges, is recorded with its reason and the campaign
goes on. ``resume`` skips missions whose ``run.json`` is already there and is theirs, in a
directory made with the same settings (``check_resume``).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from hil_service.campaign.hil_run import run_hil
from hil_service.campaign.metrics import columns, divergence, score
from hil_service.campaign.mission import Mission, oracle_trace, reference_only_trace

RUN_FILE = "run.json"
RUNS_DIR = "runs"
SPEC_FILE = "campaign.json"
#: Keys every recorded row holds (``execute`` and ``failed_row`` write them all).
ROW_KEYS = ("scenario", "seed", "steps", "status")
STATUSES = ("ok", "diverged", "failed")
#: The settings in campaign.json that change a mission's result, and their flags.
RESULT_SETTINGS = {
    "steps": "--steps",
    "identify": "--identify",
    "step_every": "--step-every",
    "oracle": "--oracle/--no-oracle",
}


@dataclass(frozen=True)
class CampaignSpec:
    scenarios: tuple[str, ...]
    seeds: tuple[int, ...]
    out: Path
    steps: int = 3600
    jobs: int = 2
    identify: int | None = None  # default: a third of the steps
    step_every: int | None = None  # default: a sixth of the steps
    oracle: bool = False
    timeout: float = 1.0  # lockstep timeout, wall s
    resume: bool = False
    #: Fault injection for tests: run id → step at which its service is SIGKILLed.
    kill_service: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.jobs < 1:
            raise ValueError(f"--jobs must be at least 1, got {self.jobs}")
        if not self.scenarios or not self.seeds:
            raise ValueError("a campaign needs at least one scenario and one seed")
        for mission in self.missions():
            mission.settings()  # refuses a bad steps/identify/step-every combination

    def missions(self) -> list[Mission]:
        identify = self.identify if self.identify is not None else self.steps // 3
        step_every = self.step_every if self.step_every is not None else max(2, self.steps // 6)
        return [
            Mission(scenario, seed, self.steps, identify, step_every)
            for scenario in self.scenarios
            for seed in self.seeds
        ]

    def to_json(self) -> dict[str, Any]:
        return {
            "scenarios": list(self.scenarios),
            "seeds": list(self.seeds),
            "steps": self.steps,
            "jobs": self.jobs,
            "identify": self.missions()[0].identify,
            "step_every": self.missions()[0].step_every,
            "oracle": self.oracle,
            "lockstep_timeout": self.timeout,
        }


def parse_seeds(text: str) -> tuple[int, ...]:
    """``0-49``, ``7`` or a comma list of both; ValueError says what is wrong."""
    seeds: list[int] = []
    for part in text.split(","):
        low, dash, high = part.strip().partition("-")
        try:
            first = int(low)
            last = int(high) if dash else first
        except ValueError:
            raise ValueError(f"--seeds {text!r}: expected N, N-M or a comma list") from None
        if first < 0 or last < first:
            raise ValueError(f"--seeds {text!r}: seeds are >= 0 and a range runs low-high")
        seeds.extend(range(first, last + 1))
    return tuple(dict.fromkeys(seeds))


def run_dir(spec: CampaignSpec, mission: Mission) -> Path:
    return spec.out / RUNS_DIR / mission.run_id


def execute(spec: CampaignSpec, mission: Mission) -> dict[str, Any]:
    """One mission, scored: the row of runs.csv. Never raises (a crash is a failed row)."""
    directory = run_dir(spec, mission)
    row: dict[str, Any] = dict.fromkeys(columns())
    row.update(scenario=mission.scenario, seed=mission.seed, steps=mission.steps)
    try:
        outcome = run_hil(mission, directory, spec.timeout, spec.kill_service.get(mission.run_id))
        row["wall_s"] = round(outcome.wall_s, 3)
        row["steps_per_s"] = round(mission.steps / outcome.wall_s) if outcome.wall_s > 0 else None
        row["lockstep_timeouts"] = outcome.lockstep.get("timeouts")
        row["log"] = (
            None if outcome.log_path is None else os.path.relpath(outcome.log_path, spec.out)
        )
        vehicle = outcome.service.get("vehicles", {}).get("1", {})
        row["commands_sent"] = vehicle.get("commands_sent")
        row["commands_refused"] = (vehicle.get("acks") or {}).get("refused")
        if outcome.failure is not None:
            row.update(status="failed", reason=outcome.failure)
            return row
        reference = reference_only_trace(mission)
        oracle, failures = oracle_trace(mission) if spec.oracle else (None, None)
        row["oracle_failures"] = failures
        row.update(score(mission, outcome.trace, reference, oracle, vehicle.get("identifier", {})))
        diverged = divergence(mission, outcome.trace, mission.schedule())
        row.update(status="diverged" if diverged else "ok", reason=diverged or "")
    except Exception as error:  # recorded, and the campaign goes on
        row.update(status="failed", reason=f"{type(error).__name__}: {error}")
        (directory / "error.txt").write_text(traceback.format_exc())
    return row


def write_row(directory: Path, row: dict[str, Any]) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    partial = directory / (RUN_FILE + ".partial")
    partial.write_text(json.dumps(row))
    partial.replace(directory / RUN_FILE)


def _cpu_seconds() -> float:
    """CPU time of this worker and its reaped children (the mission's service)."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        total += usage.ru_utime + usage.ru_stime
    return total


def mission_worker(spec: CampaignSpec, mission: Mission) -> None:
    """The forked worker's body; it leaves with os._exit, never returning to the caller."""
    code = 1
    try:
        cpu = _cpu_seconds()
        row = execute(spec, mission)
        row["cpu_s"] = round(_cpu_seconds() - cpu, 3)  # the worker's and its service's
        write_row(run_dir(spec, mission), row)
        code = 0
    finally:
        os._exit(code)


def describe_exit(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"worker killed by signal {os.WTERMSIG(status)}"
    return f"worker exited with {os.WEXITSTATUS(status)} without a result"


def recorded_row(
    directory: Path, mission: Mission | None = None
) -> tuple[dict[str, Any] | None, str]:
    """The row in ``directory/run.json``, or None and why it is not usable ("" when there is
    no file). A usable row is an object with every key of ``ROW_KEYS``, a known status and,
    when ``mission`` is given, that mission's scenario, seed and steps."""
    path = directory / RUN_FILE
    if not path.exists():
        return None, ""
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        return None, f"cannot be read ({error})"
    if not isinstance(row, dict):
        return None, "is not a JSON object"
    missing = [key for key in ROW_KEYS if key not in row]
    if missing:
        return None, f"lacks {', '.join(missing)}"
    if row["status"] not in STATUSES:
        return None, f"has an unknown status {row['status']!r}"
    if mission is not None:
        identity = (row["scenario"], row["seed"], row["steps"])
        if identity != (mission.scenario, mission.seed, mission.steps):
            return None, (
                f"is {row['scenario']!r} seed {row['seed']!r} of {row['steps']!r} steps, not "
                f"{mission.scenario!r} seed {mission.seed} of {mission.steps} steps"
            )
    return row, ""


def load_row(directory: Path, mission: Mission | None = None) -> dict[str, Any] | None:
    """The usable row in ``directory/run.json`` (``recorded_row``), or None."""
    return recorded_row(directory, mission)[0]


class Progress:
    """A one-line progress bar (\\r) on a terminal; silent otherwise."""

    def __init__(self, total: int, stream: TextIO | None = None):
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = self.stream.isatty()
        self.started = time.monotonic()
        self.done = 0
        self.failed = 0

    def update(self, row: dict[str, Any]) -> None:
        self.done += 1
        self.failed += row.get("status") != "ok"
        if not self.enabled:
            return
        elapsed = time.monotonic() - self.started
        eta = elapsed / self.done * (self.total - self.done)
        width = 30
        filled = round(width * self.done / max(self.total, 1))
        bar = "#" * filled + "." * (width - filled)
        self.stream.write(
            f"\r[{bar}] {self.done}/{self.total} runs, {self.failed} not ok, "
            f"{elapsed:.0f} s, ETA {eta:.0f} s "
        )
        if self.done == self.total:
            self.stream.write("\n")
        self.stream.flush()


def failed_row(mission: Mission, reason: str) -> dict[str, Any]:
    """The row of a mission that left no result of its own (its worker died, say)."""
    row: dict[str, Any] = dict.fromkeys(columns())
    row.update(
        scenario=mission.scenario,
        seed=mission.seed,
        steps=mission.steps,
        status="failed",
        reason=reason,
    )
    return row


def check_resume(spec: CampaignSpec) -> None:
    """With ``resume``, refuse (ValueError) a directory whose recorded runs had other
    settings that change a mission's result: resuming would mix them in one summary. A
    directory with runs but no readable campaign.json is refused too (its settings are
    unknown). Without ``resume``, or on a new directory, there is nothing to check."""
    path = spec.out / SPEC_FILE
    if not spec.resume or not (path.exists() or (spec.out / RUNS_DIR).exists()):
        return
    try:
        stored = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ValueError(
            f"--resume: cannot read {path} ({error}), so whether the runs recorded in "
            f"{spec.out} had these settings is unknown: use another -o"
        ) from None
    if not isinstance(stored, dict):
        raise ValueError(f"--resume: {path} is not a JSON object: use another -o")
    current = spec.to_json()
    differing = [
        f"{flag} {stored.get(key)!r} there, {current[key]!r} here"
        for key, flag in RESULT_SETTINGS.items()
        if stored.get(key) != current[key]
    ]
    if differing:
        raise ValueError(
            f"--resume: the runs in {spec.out} were made with other settings "
            f"({'; '.join(differing)}): give the same settings, or another -o"
        )


def prepare(
    spec: CampaignSpec, report: TextIO | None = None
) -> tuple[dict[str, dict[str, Any]], list[Mission]]:
    """Write campaign.json; the rows already recorded (when resuming) and what is left.

    Raises ValueError when resuming into a directory made with other settings
    (``check_resume``). A recorded run.json that is not usable, or not this mission's, is
    said on ``report`` (stderr by default) and its mission runs again.
    """
    check_resume(spec)
    spec.out.mkdir(parents=True, exist_ok=True)
    (spec.out / SPEC_FILE).write_text(json.dumps(spec.to_json(), indent=1))
    report = report if report is not None else sys.stderr
    rows: dict[str, dict[str, Any]] = {}
    pending: list[Mission] = []
    unusable = 0
    for mission in spec.missions():
        directory = run_dir(spec, mission)
        row, problem = recorded_row(directory, mission) if spec.resume else (None, "")
        if row is not None:
            rows[mission.run_id] = row
            continue
        pending.append(mission)
        if problem:
            unusable += 1
            print(
                f"glider-hil campaign: {directory / RUN_FILE} {problem}: "
                f"{mission.run_id} runs again",
                file=report,
            )
    if unusable:
        print(
            f"glider-hil campaign: {unusable} recorded result(s) not usable, run again",
            file=report,
        )
    return rows, pending


def clear_result(spec: CampaignSpec, mission: Mission) -> None:
    """Remove a mission's stale ``run.json`` (an earlier, unfinished campaign's, or one
    that was not usable) before it runs."""
    stale = run_dir(spec, mission) / RUN_FILE
    if stale.is_dir() and not stale.is_symlink():
        shutil.rmtree(stale)
    elif stale.exists() or stale.is_symlink():
        stale.unlink()


def run_campaign(
    spec: CampaignSpec, on_row: Callable[[dict[str, Any]], None] | None = None
) -> list[dict[str, Any]]:
    """Every mission's row (finished ones read back when resuming), in mission order.

    Waits for any child (``os.waitpid(-1)``): call it from a process whose only children
    are its workers (the ``campaign`` verb's), not from one that runs other subprocesses.
    """
    missions = spec.missions()
    rows, pending = prepare(spec)
    progress = Progress(len(pending))
    running: dict[int, Mission] = {}
    sys.stdout.flush()
    sys.stderr.flush()
    while pending or running:
        while pending and len(running) < spec.jobs:
            mission = pending.pop(0)
            clear_result(spec, mission)
            pid = os.fork()
            if pid == 0:
                mission_worker(spec, mission)
            running[pid] = mission
        pid, status = os.waitpid(-1, 0)
        mission = running.pop(pid, None)
        if mission is None:
            continue
        row = load_row(run_dir(spec, mission), mission)
        if row is None:
            row = failed_row(mission, describe_exit(status))
            write_row(run_dir(spec, mission), row)
        rows[mission.run_id] = row
        progress.update(row)
        if on_row is not None:
            on_row(row)
    return [rows[m.run_id] for m in missions]
