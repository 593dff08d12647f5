"""The MAVLink side of the service's contract: a file is not a link, and the vehicle gets the
command before Zenoh does."""

from __future__ import annotations

import errno
import select
import socket
import time
from typing import Any

import pytest

from hil_service.config import ServiceConfig
from hil_service.listeners import Listener
from hil_service.mcap.reader import LogReader
from hil_service.offline.replay import ReplayInbox
from hil_service.service import HilService
from protocols import keys
from protocols.mavlink_io import Link, MavlinkCodec
from tests.conftest import DATA, free_udp_port

# ---- a file is not a link ----------------------------------------------------------------


def _refusal(processes, connection: str) -> str:
    process = processes.start("serve", "--mavlink", connection, "--no-log")
    _, err = process.communicate(timeout=60)
    assert process.returncode == 2, err
    assert "Traceback" not in err, err
    assert "glider-hil serve:" in err
    assert "udpin:HOST:PORT" in err and "serial device" in err  # what is accepted
    return err


def test_serve_refuses_a_tlog_naming_what_it_accepts(processes, tmp_path):
    tlog = tmp_path / "dive.tlog"
    tlog.write_bytes(bytes(range(256)) * 8)  # pymavlink would open this as a log to read
    err = _refusal(processes, str(tlog))
    assert f"'{tlog}' is a file, not a link" in err


def test_serve_refuses_any_regular_file_and_a_missing_log(processes, tmp_path):
    other = tmp_path / "telemetry.dat"
    other.write_bytes(b"\xfd" * 100)
    assert f"'{other}' is a file, not a link" in _refusal(processes, str(other))
    missing = tmp_path / "gone.tlog"  # a log name that does not exist is no device either
    assert f"'{missing}' is a file, not a link" in _refusal(processes, str(missing))


@pytest.mark.parametrize(
    "connection",
    ["udpin:127.0.0.1:14550", "udpout:10.0.0.2:14550", "tcp:127.0.0.1:5760", "/dev/ttyUSB0"],
)
def test_links_pass_the_check(connection):
    from protocols.mavlink_io import check_link

    check_link(connection)  # raises on a file


def test_a_udp_link_still_opens(tmp_path):
    link = Link(f"udpin:127.0.0.1:{free_udp_port()}")
    try:
        assert link.datagram and link.fileno() >= 0
    finally:
        link.close()


def test_a_scheme_in_capitals_opens_the_link_it_names():
    """The check reads ``UDPIN:`` as ``udpin:``; pymavlink would open it as a serial device
    of that name, so the link opens it in lower case and reports it so."""
    link = Link("UDPIN:127.0.0.1:0")
    try:
        assert link.datagram
        bound = link.bound()
        assert bound.startswith("udpin:127.0.0.1:") and not bound.endswith(":0")
        _assert_a_datagram_reaches(link)
    finally:
        link.close()


def _assert_a_datagram_reaches(link: Link) -> None:
    """A datagram sent to the port ``link`` listens on is what it receives."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sender.sendto(b"telemetry", ("127.0.0.1", int(link.bound().rpartition(":")[2])))
        assert link.wait(5.0)
        assert link.recv() == b"telemetry"


def test_the_same_link_in_two_cases_is_one_link_given_twice():
    import argparse

    from hil_service.cli.serve import add_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(
        ["--mavlink", "udpin:127.0.0.1:0", "--mavlink", "UDPin:127.0.0.1:0", "--no-log"]
    )
    with pytest.raises(ValueError, match="the same link given twice"):
        config_from_args(args)


def test_a_second_link_cannot_take_a_listening_port_and_its_vehicle():
    """pymavlink binds with SO_REUSEADDR; on Linux a second socket that sets it too could
    bind the port and take the vehicle's datagrams. The second must be refused, by name,
    and the first must keep receiving."""
    first = Link("udpin:127.0.0.1:0")
    try:
        with pytest.raises(OSError, match="in use by another process") as refused:
            Link(first.bound())
        assert refused.value.errno == errno.EADDRINUSE
        _assert_a_datagram_reaches(first)
    finally:
        first.close()


def test_a_closed_link_leaves_its_port_free_at_once():
    first = Link("udpin:127.0.0.1:0")
    taken = first.bound()
    first.close()
    again = Link(taken)  # a service restarted on its vehicle's port
    try:
        assert again.bound() == taken
    finally:
        again.close()


def test_serve_names_a_port_another_service_holds(processes):
    holder = Link("udpin:127.0.0.1:0")
    taken = holder.bound()
    try:
        process = processes.start(
            "serve", "--mavlink", taken, "--zenoh-listen", "tcp/127.0.0.1:0", "--no-log"
        )
        _, err = process.communicate(timeout=60)
    finally:
        holder.close()
    assert process.returncode == 2, err
    assert "Traceback" not in err, err
    assert f"cannot open {taken}" in err and "in use by another process" in err


# ---- the vehicle first, then Zenoh ---------------------------------------------------------


class OrderBus(Listener):
    """A bus that, at the n-th command publish, looks whether n command datagrams have
    reached the vehicle's socket (waiting up to ``patience``: a send that comes only after
    the publish never arrives in time)."""

    def __init__(self, vehicle: socket.socket, patience: float = 0.5):
        self.vehicle = vehicle
        self.patience = patience
        self.commands: list[bool] = []  # per command publish: was its datagram there?
        self.frames: list[bytes] = []

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        if not key.endswith("/command/ballast"):
            return
        wanted = len(self.commands) + 1
        deadline = time.monotonic() + self.patience
        while len(self.frames) < wanted:
            left = max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([self.vehicle], [], [], left)
            if not ready:
                break
            self.frames.append(self.vehicle.recv(65536))
        self.commands.append(len(self.frames) >= wanted)


def test_the_command_reaches_the_vehicle_before_it_is_published_on_zenoh():
    """The recorded frames and control inputs of a closed-loop fixture drive a service whose
    commands go to a real UDP socket; the bus checks that socket at each command publish."""
    path = DATA / "disturbed.mcap"
    reader = LogReader(path)
    inbox = ReplayInbox()
    for message in reader.messages():
        parsed = keys.parse(message.topic)
        if parsed is not None and parsed.kind == keys.DECISION_INPUTS:
            inbox.add_event(parsed.system_id, message.json())
    config = ServiceConfig.from_stored(reader.config())  # read with the messages
    assert config is not None
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    link = Link(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}")
    bus = OrderBus(vehicle)
    service = HilService(config, bus, inbox, link=link)
    try:
        for message in LogReader(path).messages({"mavlink/raw/in"}):
            service.process_datagram(message.data)
            if len(bus.commands) >= 3:
                break
    finally:
        link.close()
        vehicle.close()
    assert len(bus.commands) == 3, "the fixture's commands were not recomputed"
    assert bus.commands == [True, True, True]
    # And what reached the socket is the ballast command itself.
    decoded = [MavlinkCodec(1, 1).parse(frame, datagram=True) for frame in bus.frames]
    assert [m.get_type() for ms in decoded for m in ms] == ["COMMAND_LONG"] * 3
    assert service.vehicles[1].commands_sent == 3
