"""Runs a campaign: every (scenario, seed) mission in a forked worker, ``jobs`` at a time.

Each worker runs one mission (``hil_run.run_hil``: its own forked service), scores it and
writes ``runs/RUN_ID/run.json``; the parent only forks, waits and collects. A worker that
dies, or a mission that fails or diverges, is recorded with its reason and the campaign
goes on. ``resume`` skips missions whose ``run.json`` is already there and is theirs, in a
directory made with the same settings (``check_resume``).

A mission stopped by a signal (SIGINT, SIGTERM: ``hil_run.INTERRUPTING``) is interrupted,
not failed: nothing is recorded for it and ``resume`` runs it again. The workers die with
the campaign's process, even a SIGKILLed one (their parent-death signal), each stopping its
service first; while any of them lives the campaign directory stays locked
(``CampaignLock``), so that no second campaign runs the same missions beside them.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import resource
import shutil
import signal
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from hil_service.campaign.hil_run import STOP_TIMEOUT, interrupted, run_hil
from hil_service.campaign.metrics import columns, divergence, score
from hil_service.campaign.mission import Mission, oracle_trace, reference_only_trace
from hil_service.cli.processes import set_parent_death_signal

RUN_FILE = "run.json"
RUNS_DIR = "runs"
SPEC_FILE = "campaign.json"
#: The file in ``-o DIR`` a running campaign holds an exclusive lock on (``CampaignLock``).
LOCK_FILE = ".glider-hil-campaign.lock"
#: A mission process's exit status when its mission was interrupted (nothing recorded).
INTERRUPTED_EXIT = 130
#: Keys every recorded row holds (``execute`` and ``failed_row`` write them all).
ROW_KEYS = ("scenario", "seed", "steps", "status")
STATUSES = ("ok", "diverged", "failed")
#: The settings in campaign.json that define a mission beside its scenario and seed (the
#: samples and setpoints its IAEs sum over), and their flags.
MISSION_SETTINGS = {"steps": "--steps", "identify": "--identify", "step_every": "--step-every"}
#: The settings in campaign.json that change a mission's result, and their flags.
RESULT_SETTINGS = {**MISSION_SETTINGS, "oracle": "--oracle/--no-oracle"}


class MissionInterrupted(BaseException):
    """The mission's service was stopped by a signal: the mission has no result. A
    BaseException, as KeyboardInterrupt is, so that no ``except Exception`` records it."""


class CampaignStopped(Exception):
    """The campaign ended before every mission was recorded (missions interrupted, its
    cluster lost). ``rows``: the missions recorded, in mission order, for the tables;
    ``resume`` runs the rest."""

    def __init__(self, message: str, rows: list[dict[str, Any]]) -> None:
        super().__init__(message)
        self.rows = rows


class CampaignInUse(ValueError):
    """Another campaign holds the directory's lock."""


class CampaignLock:
    """An exclusive lock (``flock``) on ``DIR/LOCK_FILE``, made with the directory when it
    is missing, held until ``release`` or until every process holding it has ended: the
    forked workers and services inherit it, so a SIGKILLed campaign's directory stays
    locked until the last of them is gone. OSError when the directory cannot be made or
    written, ``CampaignInUse`` when another campaign holds it."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.created = not out.exists()
        out.mkdir(parents=True, exist_ok=True)
        path = out / LOCK_FILE
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(self.fd, 32, 0).decode(errors="replace").strip()
            os.close(self.fd)
            raise CampaignInUse(
                f"-o {out}: another campaign is running in it"
                + (f" (started by process {holder})" if holder else "")
                + ": wait for it to end, or use another -o"
            ) from None
        except OSError:
            os.close(self.fd)
            raise
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, f"{os.getpid()}\n".encode(), 0)

    def release(self, remove_if_new: bool = False) -> None:
        """Unlock; with ``remove_if_new``, remove the directory if this lock made it and
        nothing else was written there (a campaign that could not start)."""
        try:
            if remove_if_new and self.created and os.listdir(self.out) == [LOCK_FILE]:
                (self.out / LOCK_FILE).unlink()
                self.out.rmdir()
        except OSError:
            pass
        finally:
            os.close(self.fd)


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
        if outcome.interrupted is not None:
            raise MissionInterrupted(outcome.interrupted)
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
    """The forked worker's body; it leaves with os._exit, never returning to the caller:
    0 with its row written, ``INTERRUPTED_EXIT`` (no row) when the mission was interrupted
    (KeyboardInterrupt, which SIGTERM raises in a worker, or its service stopped by a
    signal)."""
    code = 1
    try:
        cpu = _cpu_seconds()
        row = execute(spec, mission)
        row["cpu_s"] = round(_cpu_seconds() - cpu, 3)  # the worker's and its service's
        write_row(run_dir(spec, mission), row)
        code = 0
    except (KeyboardInterrupt, MissionInterrupted):
        code = INTERRUPTED_EXIT
    finally:
        os._exit(code)


def worker_interrupted(status: int) -> bool:
    """Whether a mission process's wait status says its mission was interrupted."""
    exited = os.WIFEXITED(status) and os.WEXITSTATUS(status) == INTERRUPTED_EXIT
    return exited or interrupted(status)


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
    """Empty a mission's run directory before it runs: a stale ``run.json`` (one that was
    not usable) and what an interrupted attempt left (its log, ``service.json``), so that
    the directory holds one attempt's files."""
    directory = run_dir(spec, mission)
    if directory.is_symlink() or (directory.exists() and not directory.is_dir()):
        directory.unlink()
    elif directory.is_dir():
        shutil.rmtree(directory)


def _start_worker(spec: CampaignSpec, mission: Mission) -> int:
    """Fork the mission's worker; its pid. SIGTERM interrupts the worker as Ctrl-C does,
    and it gets SIGTERM when the campaign's process ends, however it ends."""
    pid = os.fork()
    if pid != 0:
        return pid
    try:
        signal.signal(signal.SIGTERM, signal.default_int_handler)
        set_parent_death_signal(signal.SIGTERM)
    except KeyboardInterrupt:
        os._exit(INTERRUPTED_EXIT)
    mission_worker(spec, mission)  # leaves with os._exit
    raise AssertionError("unreachable")


def _stop_workers(running: dict[int, Mission]) -> None:
    """Interrupt every running worker and reap it (each first waits for its service, its
    log closed); SIGKILL what is left after ``STOP_TIMEOUT``, or on a second Ctrl-C."""
    for pid in running:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + STOP_TIMEOUT
    left = set(running)
    try:
        while left and time.monotonic() < deadline:
            left = {pid for pid in left if not _reaped(pid)}
            time.sleep(0.01)  # a bounded poll for the workers' exit, not a pacing sleep
    except KeyboardInterrupt:
        pass
    for pid in left:
        if not _reaped(pid):
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)


def _reaped(pid: int) -> bool:
    """Reap the child ``pid`` if it has exited; whether it is gone."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] == pid
    except ChildProcessError:  # reaped already
        return True


def run_campaign(
    spec: CampaignSpec, on_row: Callable[[dict[str, Any]], None] | None = None
) -> list[dict[str, Any]]:
    """Every mission's row (finished ones read back when resuming), in mission order.

    Waits for any child (``os.waitpid(-1)``): call it from a process whose only children
    are its workers (the ``campaign`` verb's), not from one that runs other subprocesses.
    An exception here (KeyboardInterrupt) interrupts and reaps the running workers before
    it propagates; missions interrupted while the campaign went on raise
    ``CampaignStopped`` at the end, with the rows recorded.
    """
    missions = spec.missions()
    rows, pending = prepare(spec)
    progress = Progress(len(pending))
    running: dict[int, Mission] = {}
    not_recorded: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        while pending or running:
            while pending and len(running) < spec.jobs:
                mission = pending.pop(0)
                clear_result(spec, mission)
                running[_start_worker(spec, mission)] = mission
            pid, status = os.waitpid(-1, 0)
            if pid not in running:
                continue
            mission = running.pop(pid)
            row = load_row(run_dir(spec, mission), mission)
            if row is None and worker_interrupted(status):
                not_recorded.append(mission.run_id)
                continue
            if row is None:
                row = failed_row(mission, describe_exit(status))
                write_row(run_dir(spec, mission), row)
            rows[mission.run_id] = row
            progress.update(row)
            if on_row is not None:
                on_row(row)
    except BaseException:
        _stop_workers(running)
        raise
    recorded = [rows[m.run_id] for m in missions if m.run_id in rows]
    if not_recorded:
        raise CampaignStopped(
            f"{len(not_recorded)} mission(s) interrupted (a signal stopped the mission or "
            f"its service), not recorded: {', '.join(not_recorded)}; --resume runs them",
            recorded,
        )
    return recorded
