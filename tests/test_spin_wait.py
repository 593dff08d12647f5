"""Lockstep on two cores: a link that polls before it sleeps, and a service that answers the
vehicle before its listeners hear the datagram (docs/lockstep.md, "Two cores")."""

from __future__ import annotations

import os
import select
import socket
import time
from pathlib import Path
from typing import Any

import pytest

from hil_service.campaign.hil_run import Placement, run_hil
from hil_service.campaign.mission import Mission
from hil_service.cli import main
from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener, Notifier
from hil_service.service import HilService
from hil_service.vehicle_links import LinkSet
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import Link, MavlinkCodec, readable
from tests.conftest import free_udp_port
from tests.test_lockstep import _payloads

MISSION = Mission("disturbed", seed=2, steps=600, identify=350, step_every=80)


@pytest.fixture
def pair():
    """Two bound loopback UDP sockets."""
    a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    a.bind(("127.0.0.1", 0))
    b.bind(("127.0.0.1", 0))
    yield a, b
    a.close()
    b.close()


def test_a_spinning_wait_sees_a_datagram_already_there_and_times_out_without_one(pair) -> None:
    a, b = pair
    # Nothing to read: the wait ends empty, also when the timeout is shorter than the spin.
    assert readable([a.fileno()], 0.002, spin=0.001) == []
    assert readable([a.fileno()], 0.0005, spin=0.001) == []
    assert readable([a.fileno()], 0.0, spin=0.001) == []
    b.sendto(b"x", a.getsockname())
    assert readable([a.fileno()], 1.0, spin=0.001) == [a.fileno()]
    assert readable([a.fileno(), b.fileno()], 1.0, spin=0.0) == [a.fileno()]


def test_a_datagram_sent_after_the_spin_ends_still_wakes_the_wait(pair) -> None:
    a, b = pair
    receiver = a.getsockname()
    pid = os.fork()
    if pid == 0:  # sends once the parent is past its 1 ms spin, asleep in select
        try:
            select.select([], [], [], 0.05)
            b.sendto(b"late", receiver)
        finally:
            os._exit(0)
    started = time.monotonic()
    try:
        assert readable([a.fileno()], 30.0, spin=0.001) == [a.fileno()]
    finally:
        os.waitpid(pid, 0)
    assert time.monotonic() - started < 30.0
    assert a.recv(16) == b"late"


def test_a_link_refuses_a_spin_out_of_bounds() -> None:
    port = free_udp_port()
    with pytest.raises(ValueError, match=r"--spin-wait must be 0\.\.10000 µs"):
        Link(f"udpout:127.0.0.1:{port}", spin_wait=0.02)
    with pytest.raises(ValueError, match="--spin-wait"):
        Link(f"udpout:127.0.0.1:{port}", spin_wait=-1e-6)


def test_the_flags_refuse_a_spin_out_of_bounds_and_a_spinning_fleet(capsys) -> None:
    for verb in ("emulate", "serve"):
        with pytest.raises(SystemExit) as refused:
            main([verb, "--spin-wait", "20000"])
        assert refused.value.code == 2
        assert "expected 0..10000 µs" in capsys.readouterr().err
    assert main(["emulate", "--spin-wait", "100", "--vehicles", "3"]) == 2
    assert "--spin-wait runs one vehicle" in capsys.readouterr().err


class ReplyWatch(Listener):
    """Notes, for each received frame it hears of, whether the vehicle's socket already
    holds the service's answer."""

    def __init__(self, vehicle: socket.socket) -> None:
        self.vehicle = vehicle
        self.answered_before: list[tuple[str, bool]] = []

    def on_mavlink(self, direction: str, message: Any, frame: Any, t_ns: int) -> None:
        if direction == "in":
            there = bool(select.select([self.vehicle], [], [], 0.0)[0])
            self.answered_before.append((message.get_type(), there))


def test_the_vehicle_gets_its_release_before_the_listeners_hear_the_step(pair) -> None:
    vehicle, _ = pair
    link = Link(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}", 255, 191, spin_wait=1e-4)
    watch = ReplyWatch(vehicle)
    service = HilService(ServiceConfig(lockstep=True), Notifier([watch]), Inbox(), link=link)
    try:
        codec = MavlinkCodec(1, 1)
        step = GliderPlant(PlantConfig(seed=1)).step(0.0, 0.0)
        # One step's telemetry in one datagram, as a lockstep vehicle sends it.
        service.process_datagram(
            b"".join(codec.pack(m) for m in TelemetryMapping().encode_telemetry(step))
        )
        assert len(watch.answered_before) == 4
        assert all(there for _, there in watch.answered_before), watch.answered_before
        released = MavlinkCodec(1, 1).parse(vehicle.recv(300), datagram=True)
        assert [m.get_type() for m in released] == ["SYSTEM_TIME"]
    finally:
        link.close()


def test_held_events_reach_the_listeners_on_release_in_their_order() -> None:
    heard: list[tuple[str, ...]] = []

    class Tape(Listener):
        def on_publish(self, key: str, payload: Any, data: bytes, reliable: bool) -> None:
            heard.append(("publish", key))

        def on_record(self, key: str, payload: Any, direction: str) -> None:
            heard.append(("record", key))

        def on_mavlink(self, direction: str, message: Any, frame: Any, t_ns: int) -> None:
            heard.append(("mavlink", direction))

    notifier = Notifier([Tape()])
    notifier.hold()
    notifier.publish("glider/1/telemetry", {"t": 0.0})
    notifier.mavlink("out", None, b"", 1)
    notifier.record("glider-hil/1/decision-inputs", {}, "internal")
    assert heard == []
    notifier.release()
    assert heard == [
        ("publish", "glider/1/telemetry"),
        ("mavlink", "out"),
        ("record", "glider-hil/1/decision-inputs"),
    ]
    notifier.release()  # nothing held: nothing heard again
    notifier.publish("glider/1/telemetry", {"t": 1.0})  # no hold: heard at once
    assert len(heard) == 4


def test_a_mission_with_a_core_each_and_spinning_links_is_the_same_run(tmp_path: Path) -> None:
    cores = sorted(os.sched_getaffinity(0))
    placement = Placement(spin_wait=300e-6, service_cpus=frozenset({cores[-1]}))
    spun = run_hil(MISSION, tmp_path / "spun", placement=placement)
    slept = run_hil(MISSION, tmp_path / "slept")
    for outcome in (spun, slept):
        assert outcome.failure is None
        assert outcome.lockstep["timeouts"] == 0
    assert spun.log_path is not None and slept.log_path is not None
    a, b = _payloads(spun.log_path), _payloads(slept.log_path)
    assert a.keys() == b.keys()
    for topic in a:
        assert a[topic] == b[topic], f"{topic} differs between the two placements"
    for channel in ("depth", "pitch"):
        assert (spun.trace.y[channel] == slept.trace.y[channel]).all()


def test_several_links_spin_too(pair) -> None:
    """``serve --mavlink A --mavlink B --spin-wait US``: the links' wait polls all of them."""
    first, second = free_udp_port(), free_udp_port()
    links = LinkSet(
        [f"udpin:127.0.0.1:{first}", f"udpin:127.0.0.1:{second}"], 255, 191, spin_wait=1e-3
    )
    try:
        assert links.spin_wait == 1e-3
        assert not links.wait(0.002)
        sender, _ = pair
        sender.sendto(b"\xfd", ("127.0.0.1", second))
        assert links.wait(1.0)
        data, (link_number, _) = links.recv_from()
        assert (data, link_number) == (b"\xfd", 2)
    finally:
        links.close()
