"""Shared helpers: free loopback ports, project processes that are always stopped."""

from __future__ import annotations

import functools
import gc
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil_service.cli.processes import (
    end_group,
    free_port,
    set_parent_death_signal,
    start_service,
    start_verb,
    stop_process,
)
from protocols.compiled import ENV_INTERPRETED, flag, orphan_binaries, stale_modules

ROOT = Path(__file__).resolve().parent.parent


def pytest_configure(config: pytest.Config) -> None:
    if "PYTEST_XDIST_WORKER" in os.environ:
        # A worker (`make test` runs two) dies with the pytest process that started it,
        # even when that one is SIGKILLed, and its own children (serve, emulate, peers)
        # die with it: nothing outlives a killed test run. Without it a worker would first
        # finish its test, whatever that takes.
        set_parent_death_signal()
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


#: Ports a test picks for a process to bind later: each xdist worker has a block of its own,
#: below the kernel's ephemeral range. A socket bound to port 0 (a campaign's service, a
#: Zenoh session) is given a port of that range, so it can never be given a picked one
#: between the pick and the bind, and no two workers pick the same one.
PORT_BLOCK = 1000
FIRST_PICKED_PORT = 10000
_picked = {socket.SOCK_DGRAM: 0, socket.SOCK_STREAM: 0}


@functools.cache
def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default


def _worker_block() -> range | None:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    index = int(worker) if worker.isdigit() else 0
    low = FIRST_PICKED_PORT + index * PORT_BLOCK
    if low + PORT_BLOCK > _ephemeral_low():
        return None
    return range(low, low + PORT_BLOCK)


def _bindable(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def pick_port(kind: int) -> int:
    """A port of this worker's block that binds now; the next pick tries the next one, so
    a test that picks several gets different ports."""
    block = _worker_block()
    if block is not None:
        for _ in range(len(block)):
            port = block[_picked[kind] % len(block)]
            _picked[kind] += 1
            if _bindable(port, kind):
                return port
    return free_port(kind)  # no block below the ephemeral range, or a full one


def free_udp_port() -> int:
    return pick_port(socket.SOCK_DGRAM)


def free_tcp_port() -> int:
    return pick_port(socket.SOCK_STREAM)


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


@pytest.fixture(autouse=True)
def interpreter_as_found() -> Iterator[None]:
    """A command run in the test's process (``main(["replay", …])``) tunes the interpreter
    as that command's own process would (``process_tuning``: automatic garbage collection
    off, a short switch interval); the next test gets the pytest worker back as it was."""
    collecting = gc.isenabled()
    interval = sys.getswitchinterval()
    yield
    if collecting:
        gc.enable()
    sys.setswitchinterval(interval)


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
