"""Lockstep is each vehicle's own (docs/lockstep.md): a vehicle gets ``SYSTEM_TIME`` releases
only once its own heartbeat announced lockstep, or with ``serve --lockstep``; an
announcement from a system the service does not serve changes nothing and is counted.

Each test runs ``HilService`` in process on a link whose far end is a local socket, which
keeps what the service sends: the service sends as the vehicle it talks to (its
companion), so a frame's system id says which vehicle it was for.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.service import HilService
from protocols.lockstep import lockstep_heartbeat, released_time
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec, MavMessage, system_of
from protocols.samples import TelemetrySample
from tests.test_safety_gate import SentFrames

MAPPING = TelemetryMapping()
STEPS = 10


def releases(sent: SentFrames) -> dict[int, list[int]]:
    """The steps released by ``SYSTEM_TIME`` so far, by the vehicle they went to."""
    codec = MavlinkCodec(255, 0)
    released: dict[int, list[int]] = {}
    for data in sent.frames:
        for message in codec.parse(data, datagram=True):
            step = released_time(message)
            if step is not None:
                released.setdefault(system_of(message), []).append(step)
    return released


@pytest.fixture
def sent() -> Iterator[SentFrames]:
    frames = SentFrames()
    yield frames
    frames.close()


class Vehicle:
    """A glider on the service's link, fed to the service in process."""

    def __init__(self, service: HilService, system_id: int):
        self.service = service
        self.system_id = system_id
        self.codec = MavlinkCodec(system_id, 1)

    def send(self, message: MavMessage) -> None:
        self.service.process_datagram(self.codec.pack(message))

    def announce(self) -> None:
        self.send(lockstep_heartbeat())

    def step(self, k: int, pitch: float = 0.0) -> None:
        sample = TelemetrySample(self.system_id, k * 1000, 15.0, pitch, 0.1, -0.1)
        for message in MAPPING.encode_telemetry(sample):
            self.send(message)


def _service(sent: SentFrames, **config: object) -> HilService:
    # Control off: the service commands nothing, so each step it releases is a SYSTEM_TIME.
    return HilService(ServiceConfig(**config), Listener(), Inbox(), link=sent.link)  # type: ignore[arg-type]


def _stream(vehicles: list[Vehicle], steps: range) -> None:
    for k in steps:
        for vehicle in vehicles:
            vehicle.step(k)


@pytest.mark.parametrize(
    ("config", "stranger"),
    [
        ({"system_ids": (1,)}, 2),  # not in the --sysid list
        ({}, 0),  # no vehicle id: the broadcast system id
        ({"max_vehicles": 1}, 2),  # beyond the vehicle cap, vehicle 1 holding the slot
    ],
    ids=["not-listed", "not-a-vehicle-id", "beyond-the-cap"],
)
def test_a_strangers_announcement_does_not_lockstep_a_served_vehicle(
    sent: SentFrames, config: dict[str, object], stranger: int
) -> None:
    service = _service(sent, **config)
    vehicle = Vehicle(service, 1)
    vehicle.step(0)  # vehicle 1 takes its slot first
    Vehicle(service, stranger).announce()
    _stream([vehicle], range(1, STEPS))
    assert releases(sent) == {}
    summary = service.summary()
    assert summary["lockstep"] == {
        "active": False, "announced": False, "releases": 0, "released_by_command": 0,
        "released_refused": 0,
    }  # fmt: skip
    assert summary["counters"]["lockstep_announcements_ignored"] == 1
    assert "lockstep" not in service.health(1)


def test_of_two_vehicles_only_the_one_that_announced_is_released(sent: SentFrames) -> None:
    service = _service(sent)
    announcing, silent = Vehicle(service, 1), Vehicle(service, 2)
    announcing.announce()
    _stream([announcing, silent], range(STEPS))
    # A refused step (pitch beyond ±π) is released to the vehicle in lockstep only.
    announcing.step(STEPS, pitch=4.0)
    silent.step(STEPS, pitch=4.0)
    assert releases(sent) == {1: [k * 1000 for k in range(STEPS + 1)]}
    assert service.health(1)["lockstep"] == {
        "active": True, "announced": True, "releases": STEPS + 1, "released_by_command": 0,
        "released_refused": 1,
    }  # fmt: skip
    assert "lockstep" not in service.health(2)
    summary = service.summary()
    assert summary["lockstep"] == service.health(1)["lockstep"]
    assert summary["counters"]["lockstep_announcements_ignored"] == 0


def test_serve_lockstep_releases_every_served_vehicle_without_an_announcement(
    sent: SentFrames,
) -> None:
    service = _service(sent, lockstep=True, system_ids=(1, 2))
    vehicles = [Vehicle(service, 1), Vehicle(service, 2)]
    Vehicle(service, 3).announce()  # not served: ignored, counted
    _stream(vehicles, range(STEPS))
    steps = [k * 1000 for k in range(STEPS)]
    assert releases(sent) == {1: steps, 2: steps}
    for system_id in (1, 2):
        assert service.health(system_id)["lockstep"] == {
            "active": True, "announced": False, "releases": STEPS, "released_by_command": 0,
            "released_refused": 0,
        }  # fmt: skip
    summary = service.summary()
    assert summary["lockstep"] == {
        "active": True, "announced": False, "releases": 2 * STEPS, "released_by_command": 0,
        "released_refused": 0,
    }  # fmt: skip
    assert summary["counters"]["lockstep_announcements_ignored"] == 1


def test_announcements_of_systems_that_never_stream_do_not_lockstep_the_service(
    sent: SentFrames,
) -> None:
    """Systems that announce while slots are free but send no telemetry are no vehicles in
    lockstep: the served vehicle gets no release, the summary says lockstep is off, and
    what the service keeps for them stays within the vehicle cap."""
    service = _service(sent, max_vehicles=2)
    for stranger in range(10, 20):
        Vehicle(service, stranger).announce()
    _stream([Vehicle(service, 1), Vehicle(service, 2)], range(STEPS))
    for stranger in range(10, 20):  # their heartbeats go on, the slots taken by now
        Vehicle(service, stranger).announce()
    assert releases(sent) == {}
    assert service.summary()["lockstep"] == {
        "active": False, "announced": False, "releases": 0, "released_by_command": 0,
        "released_refused": 0,
    }  # fmt: skip
    assert "lockstep" not in service.health(1) and "lockstep" not in service.health(2)
    assert len(service.source.responders) <= 2  # type: ignore[attr-defined]
