"""Runs a campaign: every (scenario, seed) mission in a forked worker, ``jobs`` at a time.

Each worker runs one mission (``hil_run.run_hil``: its own forked service), scores it and
writes ``runs/RUN_ID/run.json``; the parent only forks, waits and collects. A worker that
dies, or a mission that fails or diverges, is recorded with its reason and the campaign
goes on. ``resume`` skips missions whose ``run.json`` is already there.
"""

from __future__ import annotations

import json
import os
import resource
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


def load_row(directory: Path) -> dict[str, Any] | None:
    path = directory / RUN_FILE
    if not path.exists():
        return None
    try:
        row = json.loads(path.read_text())
    except ValueError:
        return None
    return row if isinstance(row, dict) else None


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


def prepare(spec: CampaignSpec) -> tuple[dict[str, dict[str, Any]], list[Mission]]:
    """Write campaign.json; the rows already recorded (when resuming) and what is left."""
    spec.out.mkdir(parents=True, exist_ok=True)
    (spec.out / "campaign.json").write_text(json.dumps(spec.to_json(), indent=1))
    rows: dict[str, dict[str, Any]] = {}
    pending: list[Mission] = []
    for mission in spec.missions():
        row = load_row(run_dir(spec, mission)) if spec.resume else None
        if row is not None:
            rows[mission.run_id] = row
        else:
            pending.append(mission)
    return rows, pending


def clear_result(spec: CampaignSpec, mission: Mission) -> None:
    """Remove a mission's stale ``run.json`` (an earlier, unfinished campaign's) before it runs."""
    stale = run_dir(spec, mission) / RUN_FILE
    if stale.exists():
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
        row = load_row(run_dir(spec, mission))
        if row is None:
            row = failed_row(mission, describe_exit(status))
            write_row(run_dir(spec, mission), row)
        rows[mission.run_id] = row
        progress.update(row)
        if on_row is not None:
            on_row(row)
    return [rows[m.run_id] for m in missions]
