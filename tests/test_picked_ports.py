"""The ports tests pick for a process to bind later: never ones the kernel gives to a socket
bound to port 0, never one another worker picks, never one in use."""

from __future__ import annotations

import socket

import pytest

from tests import conftest


@pytest.mark.parametrize("kind", [socket.SOCK_DGRAM, socket.SOCK_STREAM])
def test_picked_ports_are_this_workers_below_the_ephemeral_range_and_free(monkeypatch, kind):
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw1")
    block = conftest._worker_block()
    assert block is not None and block[-1] < conftest._ephemeral_low()
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw0")
    assert set(block).isdisjoint(conftest._worker_block() or ())
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw1")
    first = conftest.pick_port(kind)
    assert first in block
    with socket.socket(socket.AF_INET, kind) as holder:
        # The next port of the block, or the first one after it that is free: under xdist
        # the real worker gw1 may hold some of its block while this test borrows its name.
        for step in range(1, len(block)):
            try:
                holder.bind(("127.0.0.1", block[(block.index(first) + step) % len(block)]))
                break
            except OSError:
                continue
        held = holder.getsockname()[1]
        assert held != 0, "no other port of the block was free to hold"
        second = conftest.pick_port(kind)  # the held one is passed over
        assert second not in (first, held) and second in block
