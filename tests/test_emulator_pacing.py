"""The emulator's real-time loop against a stalled host: a clock that jumps, on a link that
records when each step went out (in process, no sockets: the clock is the subject)."""

from __future__ import annotations

import pytest

from plant_emulator.autopilot import Autopilot, AutopilotConfig
from plant_emulator.plant import GliderPlant, PlantConfig

SPEED = 10.0
PERIOD = PlantConfig().period  # simulated s
STALL_AT = 50  # plant steps
STALL_S = 15 * PERIOD / SPEED  # wall seconds the host stops for: 15 steps' worth


class Level:
    def value(self, k: int) -> float:
        return 0.0


class PausedHost:
    """A clock that moves a microsecond a reading and otherwise only while the emulator
    waits on its link, and jumps ``STALL_S`` once, when the ``STALL_AT``th step has gone out."""

    datagram = True

    def __init__(self) -> None:
        self.now = 100.0
        self.stalled = False
        self.reads: list[float] = []  # the clock at each wait on the link

    def clock(self) -> float:
        self.now += 1e-6
        return self.now

    def wait(self, timeout: float) -> bool:
        self.reads.append(self.now)
        self.now += timeout
        return False

    def recv(self) -> bytes:
        return b""

    def send(self, data: bytes) -> None:
        pass

    def on_step(self, autopilot: Autopilot) -> None:
        if autopilot.stats.steps == STALL_AT and not self.stalled:
            self.stalled = True
            self.now += STALL_S


def _run(max_lag_steps: int) -> tuple[Autopilot, PausedHost, list[float]]:
    host = PausedHost()
    steps_at: list[float] = []
    config = AutopilotConfig(speed=SPEED, duration=100 * PERIOD, max_lag_steps=max_lag_steps)
    autopilot = Autopilot(
        GliderPlant(PlantConfig(seed=1)),
        host,  # type: ignore[arg-type]
        {"depth": Level(), "pitch": Level()},
        config,
        clock=host.clock,
    )

    def on_step(sample: object) -> None:
        steps_at.append(host.now)
        host.on_step(autopilot)

    autopilot.on_step = on_step
    autopilot.run()
    return autopilot, host, steps_at


def _longest_burst(steps_at: list[float], reads: list[float]) -> int:
    """The most steps taken with no wait on the link between them."""
    longest = run = 0
    waits = iter(sorted(reads))
    upcoming = next(waits, None)
    for t in steps_at:
        read_since = False
        while upcoming is not None and upcoming <= t:
            read_since = True
            upcoming = next(waits, None)
        run = 1 if read_since else run + 1
        longest = max(longest, run)
    return longest


def test_a_stalled_host_slips_the_schedule_instead_of_bursting():
    autopilot, host, steps_at = _run(max_lag_steps=3)
    assert autopilot.stats.steps == 100
    # The vehicle's time paused through the stall, from the step that fell due a period
    # after it began: 14 steps.
    assert autopilot.stats.slips == 1
    assert autopilot.stats.slipped_s == pytest.approx(STALL_S * SPEED - PERIOD, abs=0.01)
    # The link is read between steps after the stall as before it: no burst of steps the
    # commands could not follow.
    assert _longest_burst(steps_at, host.reads) <= 2
    # The steps keep their pace around the stall: 99 intervals of period/speed, one of
    # them (the step due during the stall) stretched to the stall's end.
    wall = (99 - 1) * PERIOD / SPEED + STALL_S
    assert steps_at[-1] - steps_at[0] == pytest.approx(wall, abs=0.01)


def test_without_slipping_the_same_stall_steps_the_plant_in_a_burst():
    # The schedule caught up (the lag allowed is longer than the stall): 15 steps' worth
    # of deadlines passed, and the emulator steps through them without reading the link.
    autopilot, host, steps_at = _run(max_lag_steps=1000)
    assert autopilot.stats.slips == 0
    assert _longest_burst(steps_at, host.reads) >= 15


def test_the_lag_allowed_is_at_least_a_step():
    with pytest.raises(ValueError, match="max_lag_steps"):
        AutopilotConfig(max_lag_steps=0)
