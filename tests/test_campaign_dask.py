"""``glider-hil campaign --scheduler``: missions as tasks on a real Dask cluster on loopback (a
``dask scheduler`` and two ``dask worker`` processes): the same figures as the same campaign
run locally, a worker killed mid-mission, ``--resume``, logs shared or sent back."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import distributed
import pytest

from hil_service.cli.processes import last_json, run_verb, set_parent_death_signal
from tests.conftest import free_tcp_port

pytestmark = pytest.mark.wire

DASK = str(Path(sys.executable).with_name("dask"))
#: Columns that are wall clock or CPU time, or name a log file by the time it was opened.
TIMING = {"wall_s", "cpu_s", "steps_per_s", "log"}
SHORT = ("--steps", "500", "--identify", "300", "--step-every", "60")


def _start(*args: str, log: Path) -> subprocess.Popen[bytes]:
    """A Dask process in a group of its own, which ends with this test process."""
    with log.open("wb") as out:
        return subprocess.Popen(
            [DASK, *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=set_parent_death_signal,
        )


def _end(process: subprocess.Popen[bytes]) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(process.pid, signal.SIGKILL)  # the nanny, its worker, a mission
    process.wait(10)


class Cluster:
    def __init__(self, tmp: Path):
        self.address = f"tcp://127.0.0.1:{free_tcp_port()}"
        self.tmp = tmp
        self.processes: list[subprocess.Popen[bytes]] = []
        self.nannies: list[subprocess.Popen[bytes]] = []

    def start(self) -> None:
        port = self.address.rpartition(":")[2]
        self.processes.append(
            _start(
                "scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard",
                log=self.tmp / "scheduler.log",
            )
        )  # fmt: skip
        for i in range(2):
            nanny = _start(
                "worker", self.address, "--nworkers", "1", "--nthreads", "1",
                "--no-dashboard", "--host", "127.0.0.1",
                "--local-directory", str(self.tmp / f"worker-{i}"),
                log=self.tmp / f"worker-{i}.log",
            )  # fmt: skip
            self.processes.append(nanny)
            self.nannies.append(nanny)
        self.wait_for_workers(2)

    def wait_for_workers(self, n: int) -> None:
        with distributed.Client(self.address, timeout=60) as client:
            client.wait_for_workers(n, timeout=120)

    def stop(self) -> None:
        for process in reversed(self.processes):
            _end(process)

    def logs(self) -> str:
        return "\n".join(p.read_text()[-3000:] for p in sorted(self.tmp.glob("*.log")))


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    running = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        running.start()
        yield running
    finally:
        running.stop()


def campaign(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return run_verb("campaign", *args, timeout=timeout)


def start_campaign(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "hil_service.cli", "campaign", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=set_parent_death_signal,
    )


def figures(directory: Path) -> list[dict[str, object]]:
    """Every mission's row but its timings, as runs.json holds it."""
    rows = json.loads((directory / "runs.json").read_text())
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


def table(directory: Path) -> list[dict[str, str]]:
    with (directory / "runs.csv").open() as handle:
        return list(csv.DictReader(handle))


def children(pid: int) -> list[int]:
    try:
        paths = Path(f"/proc/{pid}/task").glob("*/children")
        return [int(c) for path in paths for c in path.read_text().split()]
    except OSError:
        return []


def test_a_campaign_on_the_cluster_has_the_figures_of_the_same_campaign_run_here(
    cluster: Cluster, tmp_path: Path
) -> None:
    spec = ("--scenarios", "disturbed,random", "--seeds", "0-1", *SHORT)
    local = campaign(*spec, "-o", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    remote = campaign(
        *spec, "-o", str(tmp_path / "dask"), "--scheduler", cluster.address, "--logs", "return"
    )
    assert remote.returncode == 0, remote.stderr + cluster.logs()
    assert last_json(remote.stdout, "campaign")["ok"] == 4
    assert figures(tmp_path / "dask") == figures(tmp_path / "local")
    assert all(row["status"] == "ok" for row in figures(tmp_path / "dask"))
    summary = (tmp_path / "dask" / "summary.md").read_text()
    local_summary = (tmp_path / "local" / "summary.md").read_text()
    tables = [
        s.split("## Worst runs")[0].split("| scenario |", 1)[1] for s in (summary, local_summary)
    ]
    assert tables[0] == tables[1]  # the review table, ratios and counts, is the same
    # The figure is drawn from the same numbers: the same PNG, byte for byte.
    png = (tmp_path / "dask" / "iae_ratios.png").read_bytes()
    assert png == (tmp_path / "local" / "iae_ratios.png").read_bytes()
    for row in table(tmp_path / "dask"):  # each log came back with its result
        log = tmp_path / "dask" / row["log"]
        assert log.stat().st_size > 0 and log.read_bytes()[:8] == b"\x89MCAP0\r\n"
        assert (log.parent / "service.json").exists()


def test_on_shared_storage_the_workers_write_the_logs(cluster: Cluster, tmp_path: Path) -> None:
    out = tmp_path / "shared"  # the workers run on this machine: they see the same directory
    done = campaign(
        "--scenarios", "random", "--seeds", "0", *SHORT, "--no-figures", "--no-oracle",
        "-o", str(out), "--scheduler", cluster.address, "--logs", "shared",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    (row,) = table(out)
    assert row["status"] == "ok" and (out / row["log"]).stat().st_size > 0


def test_a_worker_killed_mid_mission_its_mission_runs_again_once_and_resume_works(
    cluster: Cluster, tmp_path: Path
) -> None:
    spec = ("--scenarios", "random", "--steps", "2500", "--identify", "900", "--step-every",
            "300", "--no-figures", "--no-oracle")  # fmt: skip
    out = tmp_path / "dask"
    running = start_campaign(
        *spec, "--seeds", "0-2", "-o", str(out), "--scheduler", cluster.address
    )
    killed = None
    try:
        deadline = time.monotonic() + 120
        while killed is None and running.poll() is None and time.monotonic() < deadline:
            for nanny in cluster.nannies:
                for worker in children(nanny.pid):
                    if children(worker):  # a mission process: the worker is mid-mission
                        os.kill(worker, signal.SIGKILL)
                        killed = worker
                        break
                if killed is not None:
                    break
            time.sleep(0.005)  # a poll of the process table, not a wait for readiness
        stdout, stderr = running.communicate(timeout=300)
    finally:
        if running.poll() is None:
            running.kill()
            running.wait(10)
    assert killed is not None, "no worker was seen mid-mission"
    assert running.returncode == 0, stderr + cluster.logs()
    assert last_json(stdout, "campaign") | {"wall_s": 0} == {
        "runs": 3, "ok": 3, "diverged": 0, "failed": 0, "wall_s": 0, "out": str(out),
    }  # fmt: skip
    rows = table(out)
    assert [r["seed"] for r in rows] == ["0", "1", "2"]  # each mission once
    for row in rows:  # one log per mission: nothing of the killed attempt reached DIR
        assert len(list((out / "runs" / f"random-s{int(row['seed']):04d}").glob("*.mcap"))) == 1
    local = campaign(*spec, "--seeds", "0-2", "-o", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    assert figures(out) == figures(tmp_path / "local")
    # The killed worker's nanny starts a new one; --resume runs only the new seed.
    cluster.wait_for_workers(2)
    before = {r["seed"]: r["wall_s"] for r in rows}
    resumed = campaign(
        *spec, "--seeds", "0-3", "-o", str(out), "--scheduler", cluster.address, "--resume"
    )
    assert resumed.returncode == 0, resumed.stderr
    after = table(out)
    assert [r["seed"] for r in after] == ["0", "1", "2", "3"]
    assert {r["seed"]: r["wall_s"] for r in after[:3]} == before  # read back, not run again
    assert after[3]["status"] == "ok"


def test_a_scheduler_that_is_not_there_is_a_clear_error(tmp_path: Path) -> None:
    address = f"tcp://127.0.0.1:{free_tcp_port()}"
    done = campaign(
        "--scenarios", "random", "--seeds", "0", *SHORT, "-o", str(tmp_path / "x"),
        "--scheduler", address, "--scheduler-timeout", "2", timeout=120,
    )  # fmt: skip
    assert done.returncode == 2
    assert f"cannot use the scheduler {address}" in done.stderr
    alone = campaign("--seeds", "0", "-o", str(tmp_path / "y"), "--logs", "shared", timeout=60)
    assert alone.returncode == 2 and "--logs needs --scheduler" in alone.stderr
