"""Running ``glider-hil`` verbs as child processes: the demo and the soak benchmark do."""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any


def free_port(kind: int) -> int:
    """A free port on 127.0.0.1 for ``socket.SOCK_DGRAM`` or ``socket.SOCK_STREAM``."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


#: util-linux's ``setpriv`` (in every Debian system): sets the parent-death signal, then
#: execs the command, so the process keeps its pid and needs no ``preexec_fn`` (which is not
#: safe in a process with threads, as every one with a Zenoh session has).
SETPRIV = shutil.which("setpriv")


def dies_with_parent(argv: Sequence[str]) -> list[str]:
    """``argv`` run so that Linux SIGKILLs it when the process that starts it ends, even
    when that one is SIGKILLed itself (``PR_SET_PDEATHSIG``): no ``serve``, ``emulate`` or
    peer outlives a killed test run or demo. The signal follows the thread that starts the
    child, so start it from a thread that lives as long as the child should. Without
    ``setpriv`` (not Linux), ``argv`` unchanged."""
    if SETPRIV is None:
        return list(argv)
    return [SETPRIV, "--pdeathsig", "KILL", *argv]


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def set_parent_death_signal(signum: int = signal.SIGKILL) -> bool:
    """Have Linux send ``signum`` to this process when the thread that started it ends,
    even when that process is SIGKILLed (``PR_SET_PDEATHSIG``): for a process that was not
    started through ``dies_with_parent`` (a fork, a pytest-xdist worker, a ``preexec_fn``).
    When the parent has already gone by the time the signal is armed, the signal is sent
    now. False where Linux's ``prctl`` is not there (the caller's own cleanup has to do)."""
    parent = os.getppid()
    try:
        import ctypes

        armed = ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signum, 0, 0, 0) == 0
    except (OSError, AttributeError):  # not Linux
        return False
    if armed and os.getppid() != parent:
        os.kill(os.getpid(), signum)
    return armed


def _verb(args: Sequence[str]) -> list[str]:
    """``glider-hil ARGS…`` with this interpreter, dying with this process."""
    return dies_with_parent([sys.executable, "-m", "hil_service.cli", *args])


def start_verb(*args: str, own_group: bool = False) -> subprocess.Popen[str]:
    """``glider-hil ARGS…`` with this interpreter, output captured, unbuffered.

    ``own_group``: the child leads a process group of its own, which ``stop_process`` ends
    as a whole, so a verb that starts processes of its own (``demo``) leaves none behind
    even when it has to be killed. Either way the child dies with this process
    (``dies_with_parent``).
    """
    process = subprocess.Popen(
        _verb(args),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        start_new_session=own_group,
    )
    process.leads_group = own_group  # type: ignore[attr-defined]
    return process


def run_verb(*args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    """``glider-hil ARGS…`` with this interpreter, to its end, output captured as text;
    killed at ``timeout`` s (``subprocess.TimeoutExpired``), and with this process
    (``dies_with_parent``)."""
    return subprocess.run(
        _verb(args),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


#: What ``serve`` prints on stderr once its MAVLink link, Zenoh session and log are open.
SERVICE_READY = "glider-hil serve: ready"


class NotReady(RuntimeError):
    """A child process exited, or did not say it was ready, before the timeout."""


def wait_for_line(process: subprocess.Popen[str], marker: str, timeout: float = 60.0) -> str:
    """Read the child's stderr until a line containing ``marker``; return what was read.

    Reads the pipe's file descriptor directly (``select`` then ``os.read``) so that the wait
    has a real timeout; the text read is returned (and kept on ``process.early_stderr``) for
    error messages, since ``communicate()`` will not see it again.
    """
    assert process.stderr is not None, "start the process with stderr=PIPE"
    fd = process.stderr.fileno()
    seen = b""
    deadline = time.monotonic() + timeout
    while marker.encode() not in seen:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise NotReady(f"no {marker!r} within {timeout:g} s; stderr so far:\n{seen.decode()}")
        ready, _, _ = select.select([fd], [], [], min(remaining, 0.5))
        if not ready:
            continue
        chunk = os.read(fd, 65536)
        if not chunk:  # end of file: the child exited
            process.wait(5)
            raise NotReady(
                f"exited with {process.returncode} before {marker!r}; stderr:\n{seen.decode()}"
            )
        seen += chunk
    text = seen.decode(errors="replace")
    process.early_stderr = text  # type: ignore[attr-defined]
    return text


def start_service(
    *args: str, timeout: float = 60.0, own_group: bool = False
) -> subprocess.Popen[str]:
    """``glider-hil serve ARGS…``, returned once it says it is ready (see ``SERVICE_READY``)."""
    process = start_verb("serve", *args, own_group=own_group)
    try:
        wait_for_line(process, SERVICE_READY, timeout)
    except NotReady:
        stop_process(process)
        raise
    return process


def stop_process(process: subprocess.Popen[str], timeout: float = 15.0) -> tuple[str, str]:
    """SIGINT (a clean stop that prints the summary), SIGKILL if it does not end in time."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.communicate(timeout=5)
    finally:
        end_group(process)


def end_group(process: subprocess.Popen[str]) -> None:
    """SIGKILL whatever is left of the group ``process`` leads (started with ``own_group``):
    its children, when it ended before stopping them. The group outlives its leader, so
    its id is still this pid's while any member is alive."""
    if not getattr(process, "leads_group", False):
        return
    with contextlib.suppress(ProcessLookupError, PermissionError):  # nothing left
        os.killpg(process.pid, signal.SIGKILL)


def last_json(text: str, key: str) -> dict[str, Any]:
    """The value under ``key`` in the last JSON line of ``text`` that has it, or {}."""
    for line in reversed(text.strip().splitlines()):
        try:
            data = json.loads(line)
        except ValueError:
            continue
        if isinstance(data, dict) and key in data:
            return data[key]
    return {}
