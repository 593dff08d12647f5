"""A process that ends with a Zenoh session still open exits rather than hanging.

zenoh-python serves a subscriber's Python callback on a non-daemon thread that ends only
when the session closes, and the interpreter joins such threads at exit before ``atexit``
runs: a verb that dies of an uncaught exception before its ``finally`` closes the session
would hang there forever (``hil_service/listeners/zenoh_shutdown.py``)."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from tests.orphans import ROOT

#: A subscriber with a Python callback on a session opened as every verb opens one, a
#: sample delivered to it, and then an exception nobody catches.
SCRIPT = """
import time
from hil_service.listeners.zenoh_config import ZenohOptions, open_session
session = open_session(ZenohOptions(listen=("tcp/127.0.0.1:{port}",)))
heard = []
subscriber = session.declare_subscriber("exit/**", heard.append)
session.put("exit/test", "x")
deadline = time.monotonic() + 10
while not heard and time.monotonic() < deadline:
    time.sleep(0.01)
print("heard", len(heard), flush=True)
raise RuntimeError("an uncaught error with the session open")
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_an_uncaught_error_with_a_session_open_ends_the_process():
    process = subprocess.Popen(
        [sys.executable, "-c", SCRIPT.format(port=_free_port())],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        out, err = process.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        pytest.fail("the process hung at exit with its Zenoh session open")
    assert "heard 1" in out  # the callback's thread was running
    assert process.returncode == 1
    assert "an uncaught error with the session open" in err
