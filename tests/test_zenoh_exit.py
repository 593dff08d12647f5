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

from tests.conftest import ROOT, free_tcp_port, free_udp_port

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


def test_an_uncaught_error_with_a_session_open_ends_the_process():
    process = subprocess.Popen(
        [sys.executable, "-c", SCRIPT.format(port=free_tcp_port())],
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


def test_serve_that_cannot_start_its_service_says_why_and_closes_what_it_opened(
    monkeypatch, tmp_path, capsys
):
    """A failure while the service is wired (after the link, the log and the Zenoh session
    are open) is a clear error and exit status 2, with all three closed (the session, the
    link's UDP port free again, the log taking no more records), not a traceback with
    everything left open."""
    from hil_service.cli import build_parser, serve

    opened, recorders = [], []
    real_open, real_recorder = serve.open_session, serve.open_recorder

    def open_and_keep(options):
        opened.append(real_open(options))
        return opened[-1]

    def recorder_and_keep(*args):
        recorders.append(real_recorder(*args))
        return recorders[-1]

    def refuse(*args, **kwargs):
        raise RuntimeError("declaration refused")

    monkeypatch.setattr(serve, "open_session", open_and_keep)
    monkeypatch.setattr(serve, "open_recorder", recorder_and_keep)
    monkeypatch.setattr(serve, "wire", refuse)
    # serve installs SIGINT/SIGTERM handlers: not in this test process beyond the test.
    monkeypatch.setattr(serve.signal, "signal", lambda *args: None)
    port = free_udp_port()
    args = build_parser().parse_args(
        ["serve", "--mavlink", f"udpin:127.0.0.1:{port}",
         "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", "--log-dir", str(tmp_path)]
    )  # fmt: skip
    assert serve.run(args) == 2
    assert "cannot start the service: declaration refused" in capsys.readouterr().err
    assert len(opened) == 1 and opened[0].is_closed()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as again:
        again.bind(("127.0.0.1", port))  # the link let its port go
    (recorder,) = recorders
    recorder.raw("in", b"after the close")
    assert recorder.status.dropped == 1  # closed: a record now is dropped, not logged
