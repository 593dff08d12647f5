"""Shared helpers: free loopback ports, project processes that are always stopped."""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil_service.cli.processes import end_group, free_port, start_service, start_verb, stop_process
from protocols.compiled import ENV_INTERPRETED, flag, orphan_binaries, stale_modules

ROOT = Path(__file__).resolve().parent.parent


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_the_test_run() -> None:
    """In a pytest-xdist worker (``make test`` runs two), have Linux SIGKILL this worker
    when the pytest process that started it ends, even by SIGKILL: the worker's own children
    (``serve``, ``emulate``, peers) are started to die with it, so nothing outlives a
    killed test run. Without it a worker finishes its test first, whatever that takes."""
    if "PYTEST_XDIST_WORKER" not in os.environ or not sys.platform.startswith("linux"):
        return
    parent = os.getppid()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:  # the run ended before the signal was armed
        os._exit(1)


def pytest_configure(config: pytest.Config) -> None:
    die_with_the_test_run()
    config.addinivalue_line(
        "markers", "wire: runs project processes on real sockets (left out of `make mutate`)"
    )


def pytest_sessionstart(session: pytest.Session) -> None:
    """Refuse to test compiled modules built from older sources (they would be what runs).

    With GLIDER_HIL_INTERPRETED=1 the sources run, here and in every child process, so a
    stale build does not matter (``make mutate`` edits sources without recompiling). A
    compiled module outside HOT_PATH matters either way: the switch does not cover it.
    """
    orphans = orphan_binaries(ROOT)
    if orphans:
        raise pytest.UsageError(
            f"compiled modules with no HOT_PATH source: {', '.join(map(str, orphans))}; "
            "run `make build` (it deletes them)"
        )
    stale = [] if flag(ENV_INTERPRETED) else stale_modules(ROOT)
    if stale:
        raise pytest.UsageError(
            f"compiled modules older than their sources: {', '.join(stale)}; "
            "run `make build` (or `make test`, which rebuilds them)"
        )


def free_udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


def free_tcp_port() -> int:
    return free_port(socket.SOCK_STREAM)


class ProcessGroup:
    """Starts ``glider-hil`` processes and guarantees they are gone at teardown."""

    def __init__(self) -> None:
        self.processes: list[subprocess.Popen[str]] = []

    def start(self, *args: str) -> subprocess.Popen[str]:
        process = start_verb(*args, own_group=True)  # its children end with it
        self.processes.append(process)
        return process

    def start_service(self, *args: str, timeout: float = 60.0) -> subprocess.Popen[str]:
        """``serve ARGS…``, returned once it says it is ready (never a fixed sleep)."""
        process = start_service(*args, timeout=timeout, own_group=True)
        self.processes.append(process)
        return process

    @staticmethod
    def stop(process: subprocess.Popen[str], timeout: float = 10.0) -> tuple[str, str]:
        """SIGINT (a clean stop, like Ctrl-C), then SIGKILL if it does not exit in time."""
        return stop_process(process, timeout)

    def stop_all(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                self.stop(process)
            else:
                end_group(process)  # what it started and left behind


@pytest.fixture
def processes() -> Iterator[ProcessGroup]:
    group = ProcessGroup()
    try:
        yield group
    finally:
        group.stop_all()


DATA = Path(__file__).resolve().parent / "data"


@pytest.fixture
def replay_log():
    """Feed a recorded log through the live service path: ``replay_log(path, **options)``."""
    from hil_service.offline.replay import ReplayOptions, replay

    def run(path: str | Path, **options: object):
        return replay(path, ReplayOptions(**options))

    return run
