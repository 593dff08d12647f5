"""Running ``glider-hil`` verbs as child processes: the demo and the soak benchmark do."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from typing import Any


def free_port(kind: int) -> int:
    """A free port on 127.0.0.1 for ``socket.SOCK_DGRAM`` or ``socket.SOCK_STREAM``."""
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_verb(*args: str) -> subprocess.Popen[str]:
    """``glider-hil ARGS…`` with this interpreter, output captured, unbuffered."""
    return subprocess.Popen(
        [sys.executable, "-m", "hil_service.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def stop_process(process: subprocess.Popen[str], timeout: float = 15.0) -> tuple[str, str]:
    """SIGINT (a clean stop that prints the summary), SIGKILL if it does not end in time."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.communicate(timeout=5)


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
