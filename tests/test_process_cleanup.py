"""Every test stops what it starts, including what a started verb starts itself: ``demo``
runs a service and an emulator, which must not outlive it when it is killed."""

from __future__ import annotations

import os
import time
from pathlib import Path

from tests.orphans import outlives_its_killed_parent


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


def test_a_killed_demos_service_and_emulator_are_stopped_with_it(processes, tmp_path, monkeypatch):
    scratch = tmp_path / "tmp"  # the children's temporary files go here
    scratch.mkdir()
    monkeypatch.setenv("TMPDIR", str(scratch))
    log_dir = tmp_path / "log"
    demo = processes.start("demo", "--duration", "120", "--speed", "10", "--log-dir", str(log_dir))
    # The service first, then the emulator: two processes of the demo's group.
    _until(lambda: len(_group_members(demo.pid)) >= 2, 120, "the demo's two processes")
    demo.kill()  # dies without stopping them: they die with it (their parent-death signal)
    demo.wait(10)
    _until(lambda: not _group_members(demo.pid), 10, "the demo's processes to end with it")
    # Nothing temporary is left behind by a demo that could not clean up after itself.
    assert not [p for p in scratch.iterdir() if p.name.startswith("glider-hil-demo-")]


def test_a_verb_dies_with_a_parent_that_is_sigkilled(tmp_path):
    """A test run SIGKILLed mid-test leaves no ``serve`` behind: the parent here is a plain
    Python process that starts ``serve`` as the suite does, then is SIGKILLed."""
    code = (
        "import sys, time\n"
        "from hil_service.cli.processes import start_service\n"
        "service = start_service('--mavlink', 'udpin:127.0.0.1:0',"
        " '--zenoh-listen', 'tcp/127.0.0.1:0',"
        f" '--log-dir', {str(tmp_path)!r})\n"
        "print(service.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    assert not outlives_its_killed_parent(code), "serve outlived its SIGKILLed parent"
