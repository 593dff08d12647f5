"""A Zenoh router in its own process, for tests that kill and restart it.

Run: python -m tests.zenoh_router ENDPOINT [CONFIG.json5]. It subscribes to ``glider/**``
and prints one JSON line per 0.2 s with the number of samples received so far; it exits on
SIGTERM/SIGINT. ``start_router``, ``wait_listening``, ``first_received`` and
``stop_router`` drive it from a test.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from hil_service.cli.processes import dies_with_parent
from hil_service.listeners.zenoh_config import ZenohOptions, open_session

ROOT = Path(__file__).resolve().parent.parent


def start_router(endpoint: str, config_file: str | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        dies_with_parent(
            [sys.executable, "-m", "tests.zenoh_router", endpoint, *filter(None, [config_file])]
        ),
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def wait_listening(router: subprocess.Popen[str]) -> bool:
    """Block until the router prints its first count line (it is listening then); False if
    it exited first."""
    assert router.stdout is not None
    return bool(router.stdout.readline())


def first_received(router: subprocess.Popen[str], until: float) -> int:
    """Read the router's count lines until ``until`` (monotonic) or it reports > 0."""
    assert router.stdout is not None
    latest = 0
    while time.monotonic() < until:
        line = router.stdout.readline()
        if not line:
            break
        latest = json.loads(line)["received"]
        if latest > 0:
            break
    return latest


def stop_router(router: subprocess.Popen[str]) -> None:
    if router.poll() is None:
        router.terminate()
    try:
        router.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        router.kill()
        router.communicate(timeout=5)


def main(endpoint: str, config_file: str | None = None) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    session = open_session(ZenohOptions(config_file, mode="router", listen=(endpoint,)))
    received = [0]

    def count(_sample: object) -> None:
        received[0] += 1

    subscriber = session.declare_subscriber("glider/**", count)
    while not stop.wait(0.2):
        print(json.dumps({"received": received[0], "t": time.time()}), flush=True)
    subscriber.undeclare()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
