"""A fleet's health is published one vehicle at a time, spread over the health period, not
as one burst of every vehicle that the samples arriving meanwhile would wait for (issue 17:
the 100-vehicle latency tail)."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections import Counter
from collections.abc import Callable
from itertools import pairwise
from typing import Any

from hil_service.config import ServiceConfig
from hil_service.inputs import Inbox
from hil_service.listeners import Listener
from hil_service.service import COMPANION_POLL, HilService
from protocols import keys
from protocols.mavlink_io import Link

STEP = 0.01  # s between two ticks, as a busy service's loop calls tick after each datagram


class CaptureBus(Listener):
    def __init__(self, clock: Callable[[], float]):
        self.clock = clock
        self.health: list[tuple[float, int]] = []  # (time, system id)

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        parsed = keys.parse(key)
        assert parsed is not None and parsed.kind == keys.HEALTH
        self.health.append((self.clock(), parsed.system_id))


def run(vehicles: list[int], seconds: float, late: tuple[int, ...] = ()) -> list[tuple[float, int]]:
    """Tick every STEP for ``seconds``; the ``late`` vehicles appear half way through."""
    wall = [0.0]
    bus = CaptureBus(lambda: wall[0])
    service = HilService(ServiceConfig(), bus, Inbox(), clock=lambda: wall[0])
    for system_id in vehicles:
        service._vehicle(system_id)  # as its first sample does
    ticks = round(seconds / STEP)
    for tick in range(ticks):
        wall[0] = tick * STEP
        if tick == ticks // 2:
            for system_id in late:
                service._vehicle(system_id)
        service.tick()
    return bus.health


def test_each_vehicle_once_a_period_and_never_two_in_one_tick():
    fleet = list(range(1, 11))
    health = run(fleet, 3.0)
    times = [t for t, _ in health]
    assert len(times) == len(set(times)), "two vehicles' health in one tick: a burst"
    for system_id in fleet:
        mine = [t for t, i in health if i == system_id]
        assert len(mine) == 3, (system_id, mine)
        gaps = [b - a for a, b in pairwise(mine)]
        assert all(abs(gap - 1.0) <= STEP + 1e-9 for gap in gaps), (system_id, gaps)
    # Spread evenly: one vehicle every period / 10.
    gaps = [b - a for a, b in pairwise(times)]
    assert max(gaps) <= 0.1 + STEP + 1e-9


def test_a_vehicle_that_appears_later_gets_its_turn():
    health = run([1, 2], 4.0, late=(3, 4))
    for system_id in (3, 4):
        mine = [t for t, i in health if i == system_id]
        assert mine and min(mine) >= 2.0
    late_times = sorted(t for t, i in health if t >= 2.5)
    assert {i for t, i in health if t >= 2.5} == {1, 2, 3, 4}
    assert len(late_times) == len(set(late_times))


def test_a_service_far_behind_does_not_burst_to_catch_up():
    wall = [0.0]
    bus = CaptureBus(lambda: wall[0])
    service = HilService(ServiceConfig(), bus, Inbox(), clock=lambda: wall[0])
    for system_id in range(1, 51):
        service._vehicle(system_id)
    service.tick()
    wall[0] = 10.0  # no tick for 10 s (a stalled loop): 500 turns missed, each vehicle once
    service.tick()
    at_ten = [i for t, i in bus.health if t == 10.0]
    assert sorted(at_ten) == list(range(1, 51))
    wall[0] = 10.0 + STEP  # then paced again from now: none due yet, one at 10 + 1/50 s
    service.tick()
    assert [i for t, i in bus.health if t > 10.0] == []
    wall[0] = 10.0 + 0.02
    service.tick()
    assert len([i for t, i in bus.health if t > 10.0]) == 1


def test_companions_are_polled_when_something_is_due_not_every_tick():
    wall = [0.0]
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    link = Link(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}")
    try:
        service = HilService(
            ServiceConfig(), CaptureBus(lambda: wall[0]), Inbox(), link=link, clock=lambda: wall[0]
        )
        for system_id in range(1, 51):
            service._vehicle(system_id)
        polled = Counter()
        for system_id, companion in service.companions.items():
            real = companion.poll

            def counting(now: float, real: Any = real, system_id: int = system_id) -> Any:
                polled[system_id] += 1
                return real(now)

            companion.poll = counting
        for tick in range(400):  # 4 datagrams a sample, a sample every 2.5 ms: 1 s
            wall[0] = tick * 0.0025
            service.tick()
        # Once each in that second: for the first heartbeat (a lockstep companion sends
        # nothing else), not at every tick or every COMPANION_POLL.
        assert polled == Counter(range(1, 51))
        heartbeats = [c.counters.heartbeats for c in service.companions.values()]
        assert heartbeats == [1] * 50
        wall[0] = 1.0 + 2 * COMPANION_POLL
        service.tick()  # the heartbeats still go out, one per vehicle a second
        assert [c.counters.heartbeats for c in service.companions.values()] == [2] * 50
        assert polled == Counter({system_id: 2 for system_id in range(1, 51)})
    finally:
        link.close()
        vehicle.close()


def test_a_verb_imports_its_own_modules_only():
    """`fleet` (or `router`) started next to a running fleet used to import every verb's
    modules, matplotlib and python-control included: seconds of CPU the fleet waited for."""
    code = (
        "import sys; from hil_service.cli import build_parser; "
        "args = build_parser('fleet').parse_args(['fleet', '--json']); "
        "print(args.verb, sorted(m for m in ('matplotlib', 'control', 'scipy', 'plant_emulator') "
        "if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    assert out.split() == ["fleet", "[]"], out


def test_a_service_spreads_its_vehicles_structure_choices_over_its_fleet() -> None:
    # Each channel chooses its structure once (12-25 ms of CPU); vehicles that appeared
    # together choose `phase mod S` samples late, S = max(100, fleet / 2), the fleet being
    # --max-vehicles or the --sysid list, whichever is more (pipeline.choice_spread).
    def delays(config: ServiceConfig, ids: list[int]) -> list[int]:
        service = HilService(config, CaptureBus(lambda: 0.0), Inbox(), clock=lambda: 0.0)
        for vehicle_id in ids:
            service._vehicle(vehicle_id)  # as its first sample does
        return [v.pipeline.channels["depth"]._choice_delay for v in service.vehicles.values()]

    links = [(i // 250 + 1) * 256 + i % 250 + 1 for i in range(501)]  # (link, system id)
    large = delays(ServiceConfig(vehicle_ids="link", max_vehicles=1000), links)
    assert large[:3] == [0, 1, 2] and large[437] == 437 and large[500] == 0
    listed = delays(ServiceConfig(system_ids=tuple(range(1, 251))), list(range(1, 131)))
    assert listed[129] == 129 % 125
    assert delays(ServiceConfig(), list(range(1, 102)))[100] == 0  # 32 vehicles: 100 samples
