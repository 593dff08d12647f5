"""Whether a process a test starts dies with its parent when that parent is SIGKILLed (a test
run killed mid-test must leave nothing running)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.conftest import ROOT


def running(pid: int) -> bool:
    """Whether ``pid`` is still running (not gone, nor a zombie nobody reaped yet)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:  # gone (ENOENT, or ESRCH while it was being reaped)
        return False
    return stat.rpartition(")")[2].split()[0] != "Z"


def outlives_its_killed_parent(code: str, timeout: float = 10.0) -> bool:
    """Run ``code`` in a plain Python process (the parent) from the checkout; ``code`` starts
    the child and prints its pid. SIGKILL the parent, then wait up to ``timeout`` s for the
    child to end. True when it did not (it is then killed, so that the test leaves nothing
    behind either way)."""
    parent = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT
    )
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        assert running(child), "the child ended before its parent was killed"
    finally:
        parent.kill()
        parent.communicate(timeout=30)
    deadline = time.monotonic() + timeout
    while running(child):
        if time.monotonic() > deadline:
            os.kill(child, signal.SIGKILL)
            return True
        time.sleep(0.05)
    return False
