"""Runs a campaign's missions as tasks on a Dask cluster (``campaign --scheduler ADDRESS``).

Each mission is one task (``mission_task``). On the worker the task forks a mission process,
as the local runner does (``runner.mission_worker``: the emulator in it, the service forked
from it, both on the worker's own loopback), into a scratch directory under the worker's
local directory, and waits for it. The mission's row and files then go one of two ways:

* ``shared``: ``-o DIR`` is the same directory on the worker (shared storage): the task moves
  the mission's files into ``DIR/runs/RUN_ID/`` itself and returns the row only;
* ``return``: the files come back with the row, and this process writes them.

``auto`` (the default) decides per task: this process writes a token into ``DIR`` (the
``MARKER`` file) and a worker that reads the same token there is on shared storage.

Only this process writes ``run.json``, once per mission and from the one result Dask gives
for its task, so a mission is never counted twice. A worker that dies mid-mission takes its
mission process down with it (``PR_SET_PDEATHSIG``; the service follows its own parent), and
the scheduler runs the task again on a worker that is alive, in a fresh scratch directory:
nothing of the lost attempt reaches ``DIR``. A task that fails for good (the scheduler's
``allowed-failures``, or an error on the worker) is a failed row with the reason, and the
campaign goes on. ``--resume`` reads back what ``run.json`` files exist, as locally.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys
import tempfile
import uuid
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from hil_service.campaign.mission import Mission
from hil_service.campaign.runner import (
    RUN_FILE,
    CampaignSpec,
    Progress,
    clear_result,
    describe_exit,
    failed_row,
    load_row,
    mission_worker,
    prepare,
    run_dir,
    write_row,
)
from hil_service.cli.processes import set_parent_death_signal

LOG_MODES = ("auto", "shared", "return")
#: The file in ``-o DIR`` whose token tells a worker that it sees the same directory.
MARKER = ".glider-hil-campaign-token"
WORKER_WAIT = 60.0  # wall s for the cluster to have at least one worker


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


def mission_task(spec: CampaignSpec, mission: Mission, token: str, logs: str) -> dict[str, Any]:
    """On a worker: run the mission in a forked process; its row and (``return``) files.

    Returns ``{"row": row, "files": {name: bytes}, "shared": bool}``.
    """
    shared = logs != "return" and _is_shared(str(spec.out), token)
    if logs == "shared" and not shared:
        raise RuntimeError(
            f"--logs shared: {spec.out} is not the campaign directory on this worker"
        )
    with tempfile.TemporaryDirectory(prefix="glider-hil-mission-", dir=_scratch_root()) as tmp:
        local = replace(spec, out=Path(tmp), resume=False)
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            try:
                set_parent_death_signal()  # SIGKILLed when the worker's task thread goes
                for number in (signal.SIGTERM, signal.SIGINT):
                    signal.signal(number, signal.SIG_DFL)  # not the worker's own handlers
            finally:
                mission_worker(local, mission)  # leaves with os._exit
        _, status = os.waitpid(pid, 0)
        directory = run_dir(local, mission)
        row = load_row(directory) or failed_row(mission, describe_exit(status))
        produced = (
            sorted(p for p in directory.iterdir() if p.is_file() and p.name != RUN_FILE)
            if directory.is_dir()
            else []
        )
        files: dict[str, bytes] = {}
        if shared:
            target = run_dir(spec, mission)
            target.mkdir(parents=True, exist_ok=True)
            for path in produced:
                partial = target / (path.name + ".partial")
                shutil.copyfile(path, partial)
                partial.replace(target / path.name)
        else:
            files = {path.name: path.read_bytes() for path in produced}
    return {"row": row, "files": files, "shared": shared}


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


def _store(spec: CampaignSpec, mission: Mission, result: dict[str, Any]) -> dict[str, Any]:
    directory = run_dir(spec, mission)
    directory.mkdir(parents=True, exist_ok=True)
    for name, data in result["files"].items():
        partial = directory / (Path(name).name + ".partial")
        partial.write_bytes(data)
        partial.replace(directory / Path(name).name)
    row = dict(result["row"])
    write_row(directory, row)
    return row


def run_campaign_dask(
    spec: CampaignSpec,
    scheduler: str,
    logs: str = "auto",
    timeout: float = WORKER_WAIT,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Every mission's row, in mission order, the pending ones run on the cluster.

    Raises OSError or TimeoutError when the scheduler cannot be reached, or has no worker,
    within ``timeout`` s.
    """
    from distributed import as_completed

    if logs not in LOG_MODES:
        raise ValueError(f"--logs must be one of {LOG_MODES}, got {logs!r}")
    client = connect(scheduler, timeout)
    missions = spec.missions()
    rows, pending = prepare(spec)
    token = uuid.uuid4().hex
    (spec.out / MARKER).write_text(token)
    progress = Progress(len(pending))
    try:
        futures: dict[str, tuple[Any, Mission]] = {}
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
            futures[future.key] = (future, mission)
        for future in as_completed([f for f, _ in futures.values()]):
            _, mission = futures[future.key]
            error = future.exception()
            if error is not None:
                row = failed_row(mission, f"task failed: {type(error).__name__}: {error}")
                write_row(run_dir(spec, mission), row)
            else:
                row = _store(spec, mission, future.result())
            future.release()
            rows[mission.run_id] = row
            progress.update(row)
            if on_row is not None:
                on_row(row)
    finally:
        client.close()
    return [rows[m.run_id] for m in missions]
