"""Named scenarios: which actuator and which disturbances each channel gets."""

from __future__ import annotations

from plant_emulator.actuator import BallastActuator, PumpNonlinearity
from plant_emulator.disturbances import (
    Disturbance,
    GaussMarkovCurrent,
    NoDisturbance,
    PiecewiseCurrentWave,
    SumOfDisturbances,
    WaveOrbital,
)

SCENARIOS = ("paper", "disturbed", "nonlinear")

#: Output units per unit of disturbance shape: m for depth, rad for pitch.
DISTURBANCE_SCALE = {"depth": 1.0, "pitch": 0.02}


def build_actuator(scenario: str, limit: float = 2.0, rate_limit: float = 0.5) -> BallastActuator:
    check_scenario(scenario)
    nonlinearity = PumpNonlinearity() if scenario == "nonlinear" else None
    return BallastActuator(limit=limit, rate_limit=rate_limit, nonlinearity=nonlinearity)


def build_disturbance(scenario: str, channel: str, seed: int = 0) -> Disturbance:
    """The paper's current wave, a Gauss–Markov current and wave orbital motion, summed.

    Only the ``disturbed`` scenario has them; seeds differ per channel so the two channels'
    random parts are independent but reproducible.
    """
    check_scenario(scenario)
    if scenario != "disturbed":
        return NoDisturbance()
    scale = DISTURBANCE_SCALE[channel]
    channel_seed = seed * 2 + (0 if channel == "depth" else 1)
    return SumOfDisturbances(
        (
            PiecewiseCurrentWave(amplitude=0.5 * scale, time_scale=2.0),
            GaussMarkovCurrent(sigma=0.2 * scale, tau=120.0, seed=channel_seed),
            WaveOrbital(
                amplitudes=(0.05 * scale, 0.03 * scale, 0.02 * scale), seed=channel_seed + 1000
            ),
        )
    )


def check_scenario(scenario: str) -> None:
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; expected one of {SCENARIOS}")


#: Plant changes an emulated vehicle can undergo mid-run (``emulate --change``): the
#: channel's effective input multiplied by this from a given step on.
PLANT_CHANGES = {"flip": -1.0, "gain5": 5.0}


class ChangingActuator:
    """A channel's actuator whose effective input is multiplied by ``factor`` from step
    ``at`` on (0-based, counted in ``apply`` calls): a plant whose input sign flips, or
    whose gain grows, after identification. Everything else is the wrapped actuator's."""

    def __init__(self, inner: BallastActuator, factor: float, at: int) -> None:
        self.inner = inner
        self.factor = float(factor)
        self.at = int(at)
        self.steps = 0

    def __getattr__(self, name: str) -> object:
        return getattr(self.inner, name)

    def apply(self, command: float) -> float:
        effective = self.inner.apply(command)
        changed = self.steps >= self.at
        self.steps += 1
        return effective * self.factor if changed else effective
