"""The live view runs in a process of its own (hil_service/live/server.py), fed through a
bounded, never-blocking hand-off: the service's process does not load the Foxglove SDK, a
live view that stops taking costs counted drops (never a wait), and it ends with the
service, even one that is killed."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys

import pytest

from hil_service.live.address import LiveAddress
from hil_service.live.view import LiveView
from tests.foxglove_stalled import StalledViewer
from tests.orphans import outlives_its_killed_parent

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_the_services_process_never_loads_the_sdk() -> None:
    code = (
        "import sys, json\n"
        "from hil_service.live.view import LiveView\n"
        "from hil_service.live.address import LiveAddress\n"
        "live = LiveView(LiveAddress('127.0.0.1', 0)).start()\n"
        "live.offer('glider/1/telemetry', b'{}')\n"
        "synced = live.sync(30)\n"
        "live.close()\n"
        "print(json.dumps({'sdk': 'foxglove' in sys.modules, 'synced': synced,\n"
        "                  'received': live.status()['received']}))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report == {"sdk": False, "synced": True, "received": 1}, report


def test_a_live_view_that_stops_taking_costs_counted_drops_never_a_wait() -> None:
    live = LiveView(LiveAddress("127.0.0.1", 0), max_pending=2000).start()
    viewer = StalledViewer("127.0.0.1", live.port)
    assert live.pid is not None
    payload = b'{"x": "' + b"y" * 2000 + b'"}'
    try:
        os.kill(live.pid, signal.SIGSTOP)  # its process takes nothing more
        for k in range(20_000):
            live.offer(f"glider/{1 + k % 4}/telemetry", payload)
        assert live.offered == 20_000
        dropped = live.status()["dropped"]
        assert dropped > 0  # the bound held: the rest was refused, and counted
        os.kill(live.pid, signal.SIGCONT)
        assert live.sync(60)
        status = live.status()
        # Every entry offered was either taken by the live view's process or counted.
        assert status["received"] + status["dropped"] == 20_000, status
        assert status["received"] >= 2000, status  # at least what the bound holds
        viewer.wait_advertised("glider/4/telemetry")  # and the process works on
    finally:
        if live.pid is not None:
            os.kill(live.pid, signal.SIGCONT)
        viewer.close()
        live.close()


def test_the_live_view_process_ends_with_a_killed_service() -> None:
    code = (
        "from hil_service.live.view import LiveView\n"
        "from hil_service.live.address import LiveAddress\n"
        "import sys, time\n"
        "live = LiveView(LiveAddress('127.0.0.1', 0)).start()\n"
        "print(live.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    assert not outlives_its_killed_parent(code, 30), "the live view outlived its service by 30 s"


def test_a_port_in_use_is_a_clear_error() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(RuntimeError, match="did not start"):
            LiveView(LiveAddress("127.0.0.1", port)).start()


@pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="Linux scheduling policies")
def test_the_live_view_process_yields_to_the_service() -> None:
    """Every thread of the live view's process (the SDK's server threads too) runs under
    SCHED_BATCH, five nice levels below the service: woken, it never preempts the service's
    thread, and on busy cores the service's path runs first."""
    live = LiveView(LiveAddress("127.0.0.1", 0)).start()
    try:
        assert live.pid is not None
        tasks = os.listdir(f"/proc/{live.pid}/task")
        assert len(tasks) > 1  # the SDK's threads are there
        for task in tasks:
            with open(f"/proc/{live.pid}/task/{task}/stat") as f:
                fields = f.read().rpartition(")")[2].split()
            # Fields after the command: nice is the 19th of stat, policy the 41st.
            assert int(fields[16]) == min(os.getpriority(os.PRIO_PROCESS, 0) + 5, 19), task
            assert int(fields[38]) == os.SCHED_BATCH, task
    finally:
        live.close()
