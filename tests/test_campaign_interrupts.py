"""A campaign stopped partway: by a signal (SIGTERM, SIGINT, SIGKILL) to the campaign, to a
mission's service, by a lost Dask scheduler or worker, or refused from the start (a bad
``--scheduler`` or ``-o``, a directory another campaign is running in). What a user relies
on: no process of the campaign outlives it, nothing half-done is recorded (``--resume`` runs
it again), nothing of an abandoned mission reaches ``DIR/runs/``, and every such end is one
line on stderr, not a traceback."""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from hil_service.campaign import hil_run
from hil_service.campaign.runner import (
    CampaignLock,
    CampaignSpec,
    clear_result,
    prepare,
    run_dir,
)
from hil_service.cli import main
from hil_service.cli.processes import run_verb, set_parent_death_signal
from tests.conftest import free_tcp_port
from tests.orphans import running
from tests.test_campaign_dask import _end as end_process
from tests.test_campaign_dask import _start as dask_process
from tests.test_campaign_dask import children

#: Missions far longer than a test: each is stopped partway.
LONG = ("--steps", "400000", "--identify", "300", "--step-every", "1000")
SMALL = ("--no-oracle", "--no-figures")


def start_campaign(out: Path, *args: str, ignore_sigint: bool = False) -> subprocess.Popen[str]:
    """``glider-hil campaign -o OUT ARGS`` (it dies with this test process)."""

    def setup() -> None:
        set_parent_death_signal()
        # As a shell starts a background job (SIGINT ignored) or a foreground one (its
        # default), whatever this test process inherited: a suite started in the
        # background by a non-interactive shell ignores SIGINT, and so would the campaign.
        signal.signal(signal.SIGINT, signal.SIG_IGN if ignore_sigint else signal.SIG_DFL)

    return subprocess.Popen(
        [sys.executable, "-m", "hil_service.cli", "campaign", "-o", str(out), *SMALL, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=setup,
    )


#: How long a stopped mission may take to be gone: a mission stops its service and waits
#: for it to close its log (``hil_run.STOP_TIMEOUT``, then SIGKILL), on a loaded machine.
STOPPED = hil_run.STOP_TIMEOUT + 60.0


def wait_until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not {what} within {timeout} s"
        time.sleep(0.01)  # a poll of the process table or the directory, not a pacing sleep


def services_running(campaign: subprocess.Popen[str], out: Path, missions: int) -> list[int]:
    """The campaign's workers and services once ``missions`` missions are under way (each
    service has opened its log), as ``[worker, service, ...]``."""
    tree: list[int] = []

    def under_way() -> bool:
        assert campaign.poll() is None, campaign.communicate()[1]
        tree.clear()
        for worker in children(campaign.pid):
            tree.extend([worker, *children(worker)])
        logs = list((out / "runs").glob("*/*.mcap")) if (out / "runs").is_dir() else []
        return len(tree) == 2 * missions and len(logs) == missions

    wait_until(under_way, 60, f"{missions} missions under way")
    return list(tree)


def end(process: subprocess.Popen[str]) -> tuple[str, str]:
    if process.poll() is None:
        process.kill()
    return process.communicate(timeout=30)


def recorded(out: Path) -> list[str]:
    return sorted(p.parent.name for p in (out / "runs").glob("*/run.json"))


def pending_on_resume(out: Path, seeds: tuple[int, ...]) -> list[str]:
    spec = CampaignSpec(
        ("disturbed",), seeds, out, steps=400000, identify=300, step_every=1000, resume=True
    )
    return [m.run_id for m in prepare(spec, io.StringIO())[1]]


# ---- local campaigns -----------------------------------------------------------------------
@pytest.mark.wire
def test_a_sigkilled_campaign_takes_its_missions_and_services_with_it(tmp_path: Path) -> None:
    out = tmp_path / "c"
    campaign = start_campaign(out, "--scenarios", "disturbed", "--seeds", "0-1", *LONG)
    try:
        tree = services_running(campaign, out, 2)
        campaign.send_signal(signal.SIGKILL)
        campaign.wait(10)
        gone = "workers and services gone"
        wait_until(lambda: not any(running(pid) for pid in tree), STOPPED, gone)
    finally:
        end(campaign)
    assert recorded(out) == []  # nothing half-done recorded: --resume runs both again
    assert pending_on_resume(out, (0, 1)) == ["disturbed-s0000", "disturbed-s0001"]
    CampaignLock(out).release()  # the directory is free once the last of them is gone


@pytest.mark.wire
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_to_the_campaign_stops_it_and_its_missions_in_one_line(
    tmp_path: Path, signum: int
) -> None:
    out = tmp_path / "c"
    campaign = start_campaign(out, "--scenarios", "disturbed", "--seeds", "0-1", *LONG)
    try:
        tree = services_running(campaign, out, 2)
        campaign.send_signal(signum)
        _, stderr = campaign.communicate(timeout=60)
    finally:
        end(campaign)
    assert campaign.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines() == [
        f"glider-hil campaign: interrupted: the missions recorded in {out} are kept, the "
        "running ones are not; --resume runs the rest"
    ]
    assert not any(running(pid) for pid in tree)  # the campaign waited for them
    assert recorded(out) == []
    CampaignLock(out).release()


@pytest.mark.wire
def test_a_mission_whose_service_is_stopped_by_a_signal_is_left_for_resume(
    tmp_path: Path,
) -> None:
    out = tmp_path / "c"
    campaign = start_campaign(out, "--scenarios", "disturbed", "--seeds", "0", *LONG)
    try:
        _, service = services_running(campaign, out, 1)
        os.kill(service, signal.SIGINT)  # Ctrl-C that reaches the service alone
        stdout, stderr = campaign.communicate(timeout=60)
    finally:
        end(campaign)
    assert campaign.returncode == 1, stderr
    assert "Traceback" not in stderr
    assert (
        "1 mission(s) interrupted (a signal stopped the mission or its service), not recorded: "
        "disturbed-s0000; --resume runs them" in stderr
    )
    assert json.loads(stdout)["campaign"]["not_recorded"] == 1
    assert recorded(out) == []  # not a permanent failed row
    assert pending_on_resume(out, (0,)) == ["disturbed-s0000"]


@pytest.mark.wire
def test_a_background_campaign_ignores_ctrl_c_down_to_its_services(tmp_path: Path) -> None:
    out = tmp_path / "c"
    campaign = start_campaign(
        out, "--scenarios", "disturbed", "--seeds", "0", "--steps", "2000", ignore_sigint=True
    )
    try:
        _, service = services_running(campaign, out, 1)
        os.kill(service, signal.SIGINT)
        stdout, stderr = campaign.communicate(timeout=120)
    finally:
        end(campaign)
    assert campaign.returncode == 0, stderr
    assert json.loads(stdout)["campaign"]["ok"] == 1


def test_a_mission_run_again_starts_from_an_empty_run_directory(tmp_path: Path) -> None:
    spec = CampaignSpec(("disturbed",), (0,), tmp_path, steps=900)
    (mission,) = spec.missions()
    stale = run_dir(spec, mission)
    stale.mkdir(parents=True)
    for name in ("glider-hil_20260101-000000.mcap", "service.json", "run.json"):
        (stale / name).write_text("an interrupted attempt's")
    clear_result(spec, mission)
    assert not stale.exists() or list(stale.iterdir()) == []


@pytest.mark.wire
def test_a_second_campaign_in_the_same_directory_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "c"
    first = start_campaign(out, "--scenarios", "disturbed", "--seeds", "0", *LONG)
    try:
        services_running(first, out, 1)
        second = run_verb(
            "campaign", "-o", str(out), *SMALL,
            "--scenarios", "disturbed", "--seeds", "0", *LONG, "--resume",
            timeout=60,
        )  # fmt: skip
        assert first.poll() is None
    finally:
        first.send_signal(signal.SIGTERM)
        end(first)
    assert second.returncode == 2, second.stderr
    assert second.stderr.strip().splitlines() == [
        f"glider-hil campaign: -o {out}: another campaign is running in it (started by "
        f"process {first.pid}): wait for it to end, or use another -o"
    ]


# ---- bad flags: one line, exit 2, nothing started ------------------------------------------
def must_not_run(*args: object, **kwargs: object) -> None:
    raise AssertionError("the campaign started")


@pytest.fixture
def no_missions(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("hil_service.campaign.runner.run_campaign", must_not_run)
    monkeypatch.setattr("hil_service.campaign.dask_engine.run_campaign_dask", must_not_run)


@pytest.mark.usefixtures("no_missions")
@pytest.mark.parametrize(
    ("address", "reason"),
    [
        ("http://127.0.0.1:8786", "unknown address scheme 'http'"),
        ("udp://x", "unknown address scheme 'udp'"),
        ("127.0.0.1", "missing port number"),
        ("garbage", "missing port number"),
        ("", "missing port number"),
        ("tcp://:::", "invalid address"),
        ("tcp://127.0.0.1:99999", "port 99999 is not in 1..65535"),
    ],
)
def test_a_malformed_scheduler_address_is_refused_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, address: str, reason: str
) -> None:
    code = main(["campaign", "-o", str(tmp_path / "c"), "--seeds", "0", "--scheduler", address])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"glider-hil campaign: --scheduler {address!r}: {reason}")
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c").exists()


@pytest.mark.usefixtures("no_missions")
@pytest.mark.parametrize("where", ["a-file", "/proc/glider-hil-campaign"])
@pytest.mark.parametrize("scheduler", [[], ["--scheduler", "tcp://127.0.0.1:1"]], ids=["", "dask"])
def test_an_unusable_output_directory_is_refused_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, where: str, scheduler: list[str]
) -> None:
    out = Path(where) if where.startswith("/") else tmp_path / where
    if not where.startswith("/"):
        out.write_text("")
    code = main(["campaign", "-o", str(out), "--seeds", "0", *scheduler])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"glider-hil campaign: -o {out}: cannot use it as the campaign directory")
    assert "scheduler" not in err and len(err.strip().splitlines()) == 1


# ---- Dask ----------------------------------------------------------------------------------
class OneWorkerCluster:
    """A ``dask scheduler`` and one one-thread ``dask worker`` on 127.0.0.1."""

    def __init__(self, tmp: Path) -> None:
        self.address = f"tcp://127.0.0.1:{free_tcp_port()}"
        self.tmp = tmp
        port = self.address.rpartition(":")[2]
        self.scheduler = dask_process(
            "scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard",
            log=tmp / "scheduler.log",
        )  # fmt: skip
        self.nanny = dask_process(
            "worker", self.address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
            "--host", "127.0.0.1", "--local-directory", str(tmp / "worker"),
            log=tmp / "worker.log",
        )  # fmt: skip
        wait_until(lambda: "Registered to" in (tmp / "worker.log").read_text(), 60, "a worker")

    def missions(self) -> list[int]:
        """The mission processes running on the worker."""
        return [m for worker in children(self.nanny.pid) for m in children(worker)]

    def stop(self) -> None:
        end_process(self.nanny)
        end_process(self.scheduler)

    def logs(self) -> str:
        return "\n".join(p.read_text()[-2000:] for p in sorted(self.tmp.glob("*.log")))


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[OneWorkerCluster]:
    running = OneWorkerCluster(tmp_path)
    try:
        yield running
    finally:
        running.stop()


def dask_campaign(cluster: OneWorkerCluster, out: Path, *args: str) -> subprocess.Popen[str]:
    return start_campaign(
        out, "--scenarios", "disturbed", "--scheduler", cluster.address, "--logs", "shared", *args
    )


def wait_for_mission(campaign: subprocess.Popen[str], cluster: OneWorkerCluster) -> None:
    def under_way() -> bool:
        assert campaign.poll() is None, campaign.communicate()[1] + cluster.logs()
        return bool(cluster.missions())

    wait_until(under_way, 60, "a mission under way on the worker")


def files_in_runs(out: Path) -> list[str]:
    return sorted(str(p.relative_to(out)) for p in (out / "runs").rglob("*") if p.is_file())


@pytest.mark.wire
@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_a_stopped_client_s_mission_stops_and_leaves_nothing_in_runs(
    cluster: OneWorkerCluster, tmp_path: Path, signum: int
) -> None:
    out = tmp_path / "c"
    campaign = dask_campaign(cluster, out, "--seeds", "0", *LONG)
    try:
        wait_for_mission(campaign, cluster)
        campaign.send_signal(signum)
        _, stderr = campaign.communicate(timeout=30)
        wait_until(lambda: not cluster.missions(), STOPPED, "the abandoned mission stopped")
    finally:
        end(campaign)
    assert files_in_runs(out) == []
    if signum == signal.SIGINT:
        assert campaign.returncode == 130, stderr
        assert stderr.strip().splitlines() == [
            f"glider-hil campaign: interrupted: the missions recorded in {out} are kept, the "
            "running ones are not; --resume runs the rest"
        ]


@pytest.mark.wire
def test_a_lost_scheduler_is_one_line_with_the_finished_missions_kept(
    cluster: OneWorkerCluster, tmp_path: Path
) -> None:
    out = tmp_path / "c"
    # One worker thread: seed 0, then seed 1. Seed 0 finishes; the scheduler dies in seed 1.
    campaign = dask_campaign(
        cluster, out, "--seeds", "0-1", "--steps", "3000", "--identify", "300",
        "--step-every", "400",
    )  # fmt: skip
    try:
        wait_until(lambda: recorded(out) == ["disturbed-s0000"], 60, "seed 0 recorded")
        wait_for_mission(campaign, cluster)
        end_process(cluster.scheduler)
        stdout, stderr = campaign.communicate(timeout=60)
        wait_until(lambda: not cluster.missions(), STOPPED, "the worker's mission ended")
    finally:
        end(campaign)
    assert campaign.returncode == 1, stderr
    assert "Traceback" not in stderr
    (line,) = stderr.strip().splitlines()
    assert line.startswith(f"glider-hil campaign: lost the scheduler {cluster.address}")
    assert line.endswith(f"1 of 2 missions recorded in {out}; --resume runs the rest")
    assert json.loads(stdout)["campaign"]["runs"] == 1
    with (out / "runs.csv").open() as table:
        assert [row["seed"] for row in csv.DictReader(table)] == ["0"]
    assert [f for f in files_in_runs(out) if "s0001" in f] == []  # only through the client


@pytest.mark.wire
def test_a_campaign_whose_last_worker_dies_ends_after_the_scheduler_timeout(
    cluster: OneWorkerCluster, tmp_path: Path
) -> None:
    out = tmp_path / "c"
    campaign = dask_campaign(cluster, out, "--seeds", "0", *LONG, "--scheduler-timeout", "3")
    try:
        wait_for_mission(campaign, cluster)
        end_process(cluster.nanny)
        stdout, stderr = campaign.communicate(timeout=60)
    finally:
        end(campaign)
    assert campaign.returncode == 1, stderr
    assert stderr.strip().splitlines() == [
        f"glider-hil campaign: the scheduler {cluster.address} has had no worker for 3 s "
        f"(--scheduler-timeout) with missions still to run: 0 of 1 missions recorded in {out}; "
        "--resume runs the rest"
    ]
    assert json.loads(stdout)["campaign"]["not_recorded"] == 1
