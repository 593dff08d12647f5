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
