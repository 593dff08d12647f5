"""Every test stops what it starts, including what a started verb starts itself: ``demo``
runs a service and an emulator, which must not outlive it when it is killed."""

from __future__ import annotations

import os
import time
from pathlib import Path


def _group_members(leader: int) -> list[int]:
    """Live processes of the process group ``leader`` leads, other than the leader."""
    members = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == leader:
            continue
        try:
            if os.getpgid(int(entry.name)) == leader:
                state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
                if state != "Z":  # a zombie is dead, waiting for its parent
                    members.append(int(entry.name))
        except (ProcessLookupError, FileNotFoundError, PermissionError):
            continue
    return members


def _until(condition, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def test_a_killed_demos_service_and_emulator_are_stopped_with_it(processes, tmp_path):
    demo = processes.start("demo", "--duration", "120", "--speed", "10", "--log-dir", str(tmp_path))
    # The service first, then the emulator: two processes of the demo's group.
    _until(lambda: len(_group_members(demo.pid)) >= 2, 120, "the demo's two processes")
    demo.kill()  # dies without stopping them
    demo.wait(10)
    assert _group_members(demo.pid), "the demo's processes should have outlived it"
    processes.stop_all()
    _until(lambda: not _group_members(demo.pid), 10, "the demo's processes to end")
