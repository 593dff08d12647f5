"""Runs a campaign's missions as tasks on a Dask cluster (``campaign --scheduler ADDRESS``).

Each mission is one task (``mission_task``). On the worker the task forks a mission process,
as the local runner does (``runner.mission_worker``: the emulator in it, the service forked
from it, both on the worker's own loopback), into a scratch directory under the worker's
local directory, and waits for it. The mission's row and files then go one of two ways:

* ``shared``: ``-o DIR`` is the same directory on the worker (shared storage): the task
  copies the mission's files into a staging directory of its own in ``DIR`` (``STAGING``)
  and returns the row; this process moves them into ``DIR/runs/RUN_ID/`` (a rename);
* ``return``: the files come back with the row, and this process writes them.

``auto`` (the default) decides per task: this process writes a token into ``DIR`` (the
``MARKER`` file) and a worker that reads the same token there is on shared storage.

Only this process writes ``run.json`` and puts files into ``runs/``, once per mission and
from the one result Dask gives for its task, so a mission is never counted twice and
nothing of an attempt whose result is not taken reaches ``runs/``. A worker that dies
mid-mission takes its mission process down with it (``PR_SET_PDEATHSIG``; the service
follows its own parent), and the scheduler runs the task again on a worker that is alive,
in a fresh scratch directory. A task this process no longer wants (it was stopped, or lost
the scheduler) stops its mission and copies nothing; a task whose token is no longer in
``DIR`` (another campaign took the directory over) copies nothing either. A task that fails
for good (the scheduler's ``allowed-failures``, or an error on the worker) is a failed row
with the reason, and the campaign goes on. Losing the scheduler, or having no worker for
``timeout`` s while missions are pending, ends the campaign (``CampaignStopped``) with the
rows recorded so far; ``--resume`` reads back what ``run.json`` files exist, as locally.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from concurrent.futures import CancelledError
from dataclasses import replace
from pathlib import Path
from typing import Any

from hil_service.campaign.hil_run import STOP_TIMEOUT, stop_process
from hil_service.campaign.mission import Mission
from hil_service.campaign.runner import (
    RUN_FILE,
    CampaignSpec,
    CampaignStopped,
    Progress,
    clear_result,
    describe_exit,
    failed_row,
    load_row,
    mission_worker,
    prepare,
    run_dir,
    worker_interrupted,
    write_row,
)
from hil_service.cli.processes import set_parent_death_signal

LOG_MODES = ("auto", "shared", "return")
#: The file in ``-o DIR`` whose token tells a worker that it sees the same directory.
MARKER = ".glider-hil-campaign-token"
#: The directory in ``-o DIR`` where tasks on shared storage leave a mission's files for
#: this process to move into ``runs/`` (``STAGING/TOKEN/RUN_ID/ATTEMPT/``).
STAGING = ".glider-hil-incoming"
WORKER_WAIT = 60.0  # wall s for the cluster to have at least one worker
POLL = 0.5  # wall s between looks at the cluster while no task finishes


class SchedulerUnusable(Exception):
    """The scheduler cannot be reached, or has no worker, within the timeout."""


def check_scheduler_address(address: str) -> None:
    """Refuse (ValueError, the flag named) an address Dask cannot connect to: an unknown
    scheme, no host or port, an in-process address."""
    from distributed.comm import registry
    from distributed.comm.addressing import parse_address

    try:
        scheme, location = parse_address(address)
        backend = registry.get_backend(scheme)
        if scheme == "inproc":
            raise ValueError("an in-process address is not reachable from this process")
        _, port = backend.get_address_host_port(location)
        if not 0 < port < 65536:
            raise ValueError(f"port {port} is not in 1..65535")
    except (ValueError, TypeError, NotImplementedError) as error:
        reason = str(error) or f"the scheme is not available here ({type(error).__name__})"
        raise ValueError(f"--scheduler {address!r}: {reason} (expected tcp://HOST:PORT)") from None


def _scratch_root() -> str | None:
    """The Dask worker's local directory (Dask removes a dead worker's), None elsewhere."""
    try:
        from distributed import get_worker

        return get_worker().local_directory
    except (ImportError, ValueError):
        return None


def _is_shared(out: str, token: str) -> bool:
    try:
        return (Path(out) / MARKER).read_text() == token
    except OSError:
        return False


def _task_given_up() -> bool:
    """On a worker, in a task: whether the scheduler no longer wants this task's result
    (its client released it: stopped, or lost). False where that cannot be told."""
    try:
        from distributed import get_worker
        from distributed.worker import thread_state

        task = get_worker().state.tasks.get(thread_state.key)
    except (ImportError, ValueError, AttributeError):
        return False
    return task is None or task.state in ("cancelled", "released", "forgotten")


def _wait_mission(pid: int) -> int | None:
    """The mission process's wait status; None when the task was given up meanwhile (the
    mission is then interrupted, its service stopped, and reaped)."""
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done == pid:
            return status
        if _task_given_up():
            stop_process(pid, signal.SIGTERM, STOP_TIMEOUT)
            return None
        time.sleep(POLL / 5)  # a poll of the child and the task's state, not a pacing sleep


def _stage(spec: CampaignSpec, mission: Mission, token: str, produced: list[Path]) -> str:
    """Copy the mission's files into a staging directory of this attempt in ``DIR``; its
    path under ``DIR/STAGING/TOKEN``."""
    attempt = f"{mission.run_id}/{uuid.uuid4().hex}"
    target = spec.out / STAGING / token / attempt
    target.mkdir(parents=True)
    for path in produced:
        shutil.copyfile(path, target / path.name)
    return attempt


def mission_task(spec: CampaignSpec, mission: Mission, token: str, logs: str) -> dict[str, Any]:
    """On a worker: run the mission in a forked process; its row and (``return``) files.

    Returns ``{"row": row, "files": {name: bytes}, "staged": path or None}``, or
    ``{"row": None, ...}`` when the task was given up or the directory's token is no longer
    ``token``: nothing is copied then. A mission interrupted by a signal on the worker
    (the worker being stopped, say) is rescheduled (``distributed.Reschedule``).
    """
    shared = logs != "return" and _is_shared(str(spec.out), token)
    if logs == "shared" and not shared:
        raise RuntimeError(
            f"--logs shared: {spec.out} is not the campaign directory on this worker"
        )
    nothing: dict[str, Any] = {"row": None, "files": {}, "staged": None}
    with tempfile.TemporaryDirectory(prefix="glider-hil-mission-", dir=_scratch_root()) as tmp:
        local = replace(spec, out=Path(tmp), resume=False)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            try:
                set_parent_death_signal()  # SIGKILLed when the worker's task thread goes
                for number in (signal.SIGTERM, signal.SIGINT):
                    # Not the worker's own handlers: interrupted as a local worker is.
                    signal.signal(number, signal.default_int_handler)
            finally:
                mission_worker(local, mission)  # leaves with os._exit
        status = _wait_mission(pid)
        if status is None:
            return nothing
        directory = run_dir(local, mission)
        row = load_row(directory)
        if row is None and worker_interrupted(status):
            from distributed import Reschedule

            raise Reschedule()
        row = row or failed_row(mission, describe_exit(status))
        produced = (
            sorted(p for p in directory.iterdir() if p.is_file() and p.name != RUN_FILE)
            if directory.is_dir()
            else []
        )
        if _task_given_up():
            return nothing
        if shared:
            if not _is_shared(str(spec.out), token):  # another campaign has DIR now
                return nothing
            return {"row": row, "files": {}, "staged": _stage(spec, mission, token, produced)}
        return {"row": row, "files": {p.name: p.read_bytes() for p in produced}, "staged": None}


def connect(address: str, timeout: float = WORKER_WAIT) -> Any:
    """A ``distributed.Client`` on ``address`` once the cluster has a worker."""
    from distributed import Client

    client = Client(address, timeout=timeout)
    try:
        client.wait_for_workers(1, timeout=timeout)
    except Exception:
        client.close()
        raise
    return client


def _store(
    spec: CampaignSpec, mission: Mission, result: dict[str, Any], token: str
) -> dict[str, Any]:
    """Put the task's files into the mission's run directory (written, or moved from the
    staging directory) and write its ``run.json``; the row."""
    directory = run_dir(spec, mission)
    directory.mkdir(parents=True, exist_ok=True)
    for name, data in result["files"].items():
        partial = directory / (Path(name).name + ".partial")
        partial.write_bytes(data)
        partial.replace(directory / Path(name).name)
    if result["staged"] is not None:
        staged = spec.out / STAGING / token / result["staged"]
        for path in sorted(staged.iterdir()):
            path.replace(directory / path.name)
        shutil.rmtree(staged.parent, ignore_errors=True)  # and any lost attempt's
    row = dict(result["row"])
    write_row(directory, row)
    return row


class _Lost(Exception):
    """The client lost its scheduler (the message says how)."""


def _lost(scheduler: str, why: str) -> str:
    return f"lost the scheduler {scheduler} ({why})"


class _Watch:
    """Ends the campaign when the cluster has had no worker for ``timeout`` s while
    missions are pending (the scheduler would wait for one forever)."""

    def __init__(self, client: Any, scheduler: str, timeout: float) -> None:
        self.client = client
        self.scheduler = scheduler
        self.timeout = timeout
        self.last_worker = time.monotonic()

    def problem(self) -> str | None:
        try:
            workers = len(self.client.nthreads())
        except (OSError, CancelledError, TimeoutError) as error:
            return _lost(self.scheduler, f"{type(error).__name__}: {error}")
        now = time.monotonic()
        if workers:
            self.last_worker = now
        elif now - self.last_worker >= self.timeout:
            return (
                f"the scheduler {self.scheduler} has had no worker for {self.timeout:g} s "
                "(--scheduler-timeout) with missions still to run"
            )
        return None


def _take(
    spec: CampaignSpec, mission: Mission, future: Any, token: str, scheduler: str
) -> dict[str, Any] | None:
    """The finished task's row, stored; None for a task that left nothing. ``_Lost`` when
    the task was cancelled or its result cannot be fetched."""
    if future.cancelled():
        try:
            future.result()
        except CancelledError as error:
            raise _Lost(_lost(scheduler, str(getattr(error, "reason", error)))) from None
        raise _Lost(_lost(scheduler, "its task was cancelled"))
    failure = future.exception()
    if failure is not None:
        row = failed_row(mission, f"task failed: {type(failure).__name__}: {failure}")
        write_row(run_dir(spec, mission), row)
        return row
    try:
        result = future.result()
    except (OSError, CancelledError) as error:
        raise _Lost(_lost(scheduler, f"{type(error).__name__}: {error}")) from None
    return None if result["row"] is None else _store(spec, mission, result, token)


def run_campaign_dask(
    spec: CampaignSpec,
    scheduler: str,
    logs: str = "auto",
    timeout: float = WORKER_WAIT,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Every mission's row, in mission order, the pending ones run on the cluster.

    Raises ``SchedulerUnusable`` when the scheduler cannot be reached, or has no worker,
    within ``timeout`` s (before anything is written), and ``CampaignStopped`` (with the
    rows recorded) when it is lost or has no worker for ``timeout`` s mid-campaign.
    """
    if logs not in LOG_MODES:
        raise ValueError(f"--logs must be one of {LOG_MODES}, got {logs!r}")
    try:
        client = connect(scheduler, timeout)
    except (OSError, TimeoutError) as error:
        raise SchedulerUnusable(f"cannot use the scheduler {scheduler}: {error}") from None
    try:
        return _run_on(client, spec, scheduler, logs, timeout, on_row)
    finally:
        _close(client)
        shutil.rmtree(spec.out / STAGING, ignore_errors=True)


def _close(client: Any) -> None:
    """Close the client, without the tracebacks Dask logs when that stops its attempts to
    reconnect to a lost scheduler (the campaign says what happened, in one line)."""
    logger = logging.getLogger("distributed.client")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        client.close()
    finally:
        logger.setLevel(level)


def _run_on(
    client: Any,
    spec: CampaignSpec,
    scheduler: str,
    logs: str,
    timeout: float,
    on_row: Callable[[dict[str, Any]], None] | None,
) -> list[dict[str, Any]]:
    from distributed import wait

    missions = spec.missions()
    rows, pending = prepare(spec)
    shutil.rmtree(spec.out / STAGING, ignore_errors=True)  # what earlier campaigns left
    token = uuid.uuid4().hex
    (spec.out / MARKER).write_text(token)
    progress = Progress(len(pending))
    futures: dict[Any, Mission] = {}
    for mission in pending:
        clear_result(spec, mission)
        future = client.submit(
            mission_task,
            spec,
            mission,
            token,
            logs,
            key=f"glider-hil-mission-{mission.run_id}-{token}",
            pure=False,
        )
        futures[future] = mission
    watch = _Watch(client, scheduler, timeout)
    not_recorded: list[str] = []
    problem: str | None = None
    while futures and problem is None:
        # Nothing finished yet (TimeoutError), or a task was cancelled: looked at below.
        with contextlib.suppress(TimeoutError, CancelledError):
            wait(list(futures), timeout=POLL, return_when="FIRST_COMPLETED")
        done = [future for future in futures if future.done()]
        if not done:
            problem = watch.problem()
        for future in done:
            mission = futures.pop(future)
            try:
                row = _take(spec, mission, future, token, scheduler)
            except _Lost as error:
                problem = str(error)
                break
            future.release()
            if row is None:
                not_recorded.append(mission.run_id)
                continue
            rows[mission.run_id] = row
            progress.update(row)
            if on_row is not None:
                on_row(row)
    recorded = [rows[m.run_id] for m in missions if m.run_id in rows]
    if problem is not None:
        raise CampaignStopped(
            f"{problem}: {len(recorded)} of {len(missions)} missions recorded in {spec.out}; "
            "--resume runs the rest",
            recorded,
        )
    if not_recorded:
        raise CampaignStopped(
            f"{len(not_recorded)} mission(s) left no result, not recorded: "
            f"{', '.join(not_recorded)}; --resume runs them",
            recorded,
        )
    return recorded
