"""Two services whose ``--sysid`` ranges overlap behind one Zenoh router: the one that starts
serving a vehicle whose liveliness token the other already holds says so on stderr and
counts it, and both keep serving (docs/fleet.md, "Several services, one fleet").

In process: a router session and one client session per service on loopback endpoints
(scouting off, ``zenoh_config``'s defaults), each service wired as ``serve`` wires it
(``builder.wire``) and fed its vehicles' MAVLink frames."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from hil_service.builder import Wired, wire
from hil_service.config import ServiceConfig
from hil_service.listeners.zenoh import ZenohPublisher
from hil_service.listeners.zenoh_config import ZenohOptions, open_session
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols import keys
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec
from tests.conftest import free_tcp_port

TIMEOUT = 10.0  # s; every wait polls and ends as soon as its condition holds


def wait_until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def warning(vehicle: str) -> str:
    return (
        f"glider-hil serve: vehicle {vehicle} is also served by another service on this "
        "Zenoh network (overlapping --sysid ranges?)"
    )


class Network:
    """A Zenoh router and the services and observers connected to it as clients."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.router = open_session(ZenohOptions(mode="router", listen=(self.endpoint,)))
        self.sessions: list[Any] = []
        self.services: list[Wired] = []
        self.observer = self.client()

    def client(self) -> Any:
        session = open_session(ZenohOptions(mode="client", connect=(self.endpoint,)))
        self.sessions.append(session)
        return session

    def service(self, system_ids: tuple[int, ...]) -> Wired:
        """A service for ``system_ids`` (``serve --sysid``), on a session of its own."""
        wired = wire(ServiceConfig(system_ids=system_ids), session=self.client())
        self.services.append(wired)
        return wired

    def holders_seen(self, system_id: int) -> bool:
        """Whether the router holds a token for ``system_id`` (any service's)."""
        replies = self.observer.liveliness().get(keys.service(system_id), timeout=TIMEOUT)
        return any(reply.ok is not None for reply in replies)

    def close(self) -> None:
        for wired in self.services:
            wired.notifier.stop()
        for session in [*self.sessions, self.router]:
            session.close()


@pytest.fixture
def network() -> Iterator[Network]:
    net = Network()
    try:
        yield net
    finally:
        net.close()


def zenoh_listener(wired: Wired) -> ZenohPublisher:
    [listener] = [x for x in wired.notifier.listeners if isinstance(x, ZenohPublisher)]
    return listener


class Vehicles:
    """Emulated vehicles on one service's link, stepped together."""

    def __init__(self, wired: Wired, system_ids: tuple[int, ...]) -> None:
        self.wired = wired
        self.system_ids = system_ids
        self.plants = {s: GliderPlant(PlantConfig(), system_id=s) for s in system_ids}
        self.codecs = {s: MavlinkCodec(s, 1) for s in system_ids}
        self.mapping = TelemetryMapping()

    def step(self) -> None:
        """One complete step of each vehicle, its datagrams handed to the service."""
        for system_id in self.system_ids:
            sample = self.plants[system_id].step(0.0, 0.0)
            for message in self.mapping.encode_telemetry(sample):
                self.wired.service.process_datagram(self.codecs[system_id].pack(message))
        assert set(self.system_ids) <= set(self.wired.service.vehicles)

    def samples(self) -> int:
        return self.wired.service.source.assembler.counters.samples


def feed(wired: Wired, system_ids: tuple[int, ...]) -> Vehicles:
    """The vehicles' first step: each one appears on the service."""
    vehicles = Vehicles(wired, system_ids)
    vehicles.step()
    return vehicles


def answered(wired: Wired, system_ids: tuple[int, ...]) -> dict[int, bool | None]:
    """Per vehicle: whether another service held its token, once the network has answered."""
    listener = zenoh_listener(wired)
    wait_until(
        lambda: all(listener.served_elsewhere(s) is not None for s in system_ids),
        f"the answers about {system_ids}",
    )
    return {s: listener.served_elsewhere(s) for s in system_ids}


def test_the_second_service_of_a_vehicle_warns_and_counts_and_both_keep_serving(
    network: Network, capsys: pytest.CaptureFixture[str]
) -> None:
    first = network.service((1, 2, 3))
    first_fleet = feed(first, (1, 2, 3))
    assert answered(first, (1, 2, 3)) == {1: False, 2: False, 3: False}
    for system_id in (1, 2, 3):
        wait_until(lambda s=system_id: network.holders_seen(s), f"vehicle {system_id}'s token")

    second = network.service((2, 3, 4))
    second_fleet = feed(second, (2, 3, 4))
    assert answered(second, (2, 3, 4)) == {2: True, 3: True, 4: False}

    assert zenoh_listener(second).counters() == {"vehicles_served_elsewhere": 2}
    assert zenoh_listener(first).counters() == {"vehicles_served_elsewhere": 0}
    # Every vehicle's health says it, under the service's own counters.
    assert second.service.health(4)["service_wide"]["vehicles_served_elsewhere"] == 2
    assert first.service.health(1)["service_wide"]["vehicles_served_elsewhere"] == 0
    lines = capsys.readouterr().err.splitlines()
    assert sorted(lines) == [warning("2"), warning("3")], lines

    # Neither service stopped: the next step of every vehicle is still assembled by both.
    for fleet in (first_fleet, second_fleet):
        fleet.step()
        assert fleet.samples() == 6
    assert capsys.readouterr().err == ""  # said once per vehicle, not per sample


def test_services_with_disjoint_ranges_say_nothing(
    network: Network, capsys: pytest.CaptureFixture[str]
) -> None:
    first = network.service((1, 2))
    feed(first, (1, 2))
    assert answered(first, (1, 2)) == {1: False, 2: False}
    for system_id in (1, 2):
        wait_until(lambda s=system_id: network.holders_seen(s), f"vehicle {system_id}'s token")

    second = network.service((3, 4))
    feed(second, (3, 4))
    assert answered(second, (3, 4)) == {3: False, 4: False}

    for wired in (first, second):
        assert zenoh_listener(wired).counters() == {"vehicles_served_elsewhere": 0}
    assert capsys.readouterr().err == ""


def test_a_vehicle_on_a_link_is_named_by_its_key_id(network: Network) -> None:
    """``serve --vehicle-ids link``: the warning names the vehicle as its keys do (``2-7``)."""
    vehicle = keys.vehicle_id(2, 7)
    said: list[str] = []
    holders = [
        ZenohPublisher(network.client(), wire(ServiceConfig()).inbox, warn=said.append)
        for _ in range(2)
    ]
    try:
        holders[0].on_vehicle(vehicle, dict)
        wait_until(lambda: network.holders_seen(vehicle), "the first holder's token")
        holders[1].on_vehicle(vehicle, dict)
        wait_until(lambda: holders[1].served_elsewhere(vehicle) is not None, "the answer")
        assert said == [warning("2-7")]
        assert holders[0].served_elsewhere(vehicle) is False
    finally:
        for holder in holders:
            holder.stop()
