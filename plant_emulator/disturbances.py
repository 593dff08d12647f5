"""Hydrodynamic disturbances, added to a channel's output (not to the ballast input).

Each generator is seeded and stepped once per plant sample with the simulated time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


class Disturbance(Protocol):
    def sample(self, t: float) -> float:
        """Disturbance at simulated time ``t`` (s); called once per step, t increasing."""
        ...


@dataclass
class NoDisturbance:
    def sample(self, t: float) -> float:
        return 0.0


#: Breakpoints (time s, amplitude) of the paper's figure 8 "water current wave", drawn with
#: MATLAB's signal builder: a piecewise-linear wave of rises and falls, repeated.
PAPER_WAVE_BREAKPOINTS: tuple[tuple[float, float], ...] = (
    (0.0, 0.0),
    (20.0, 0.0),
    (40.0, 1.0),
    (80.0, 1.0),
    (100.0, -0.5),
    (140.0, -0.5),
    (160.0, 0.5),
    (200.0, 0.0),
)


@dataclass
class PiecewiseCurrentWave:
    """The paper's signal-builder water current: piecewise linear between breakpoints.

    The pattern repeats every ``period`` seconds (the last breakpoint's time); time is
    stretched by ``time_scale`` so the same shape can be slower or faster than the plant.
    """

    amplitude: float = 0.5
    time_scale: float = 1.0
    breakpoints: tuple[tuple[float, float], ...] = PAPER_WAVE_BREAKPOINTS
    _times: np.ndarray = field(init=False, repr=False, compare=False)
    _values: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Built once: this runs every plant step of every channel.
        self._times = np.array([p[0] * self.time_scale for p in self.breakpoints])
        self._values = np.array([p[1] for p in self.breakpoints])

    def sample(self, t: float) -> float:
        times = self._times
        return self.amplitude * float(np.interp(t % times[-1], times, self._values))


@dataclass
class GaussMarkovCurrent:
    """First-order Gauss–Markov current: d⁺ = a·d + σ·√(1−a²)·w, a = exp(−dt/τ).

    Stationary standard deviation ``sigma``, correlation time ``tau`` (s).
    """

    sigma: float = 0.1
    tau: float = 60.0
    seed: int = 0
    value: float = 0.0
    _last_t: float | None = field(default=None, init=False, repr=False)
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def sample(self, t: float) -> float:
        if self._last_t is not None:
            dt = max(t - self._last_t, 0.0)
            a = math.exp(-dt / self.tau)
            self.value = a * self.value + self.sigma * math.sqrt(1.0 - a * a) * float(
                self._rng.standard_normal()
            )
        self._last_t = t
        return self.value


@dataclass
class WaveOrbital:
    """Sum of sines: the orbital motion of surface waves felt at depth.

    Periods (s) and amplitudes are given; phases are drawn from the seed.
    """

    amplitudes: tuple[float, ...] = (0.05, 0.03, 0.02)
    periods: tuple[float, ...] = (60.0, 23.0, 11.0)
    seed: int = 0
    _phases: tuple[float, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if len(self.amplitudes) != len(self.periods):
            raise ValueError("amplitudes and periods must have the same length")
        rng = np.random.default_rng(self.seed)
        self._phases = tuple(float(p) for p in rng.uniform(0, 2 * math.pi, len(self.periods)))

    def sample(self, t: float) -> float:
        total = 0.0
        for a, p, ph in zip(self.amplitudes, self.periods, self._phases, strict=True):
            total += a * math.sin(2 * math.pi * t / p + ph)
        return total


@dataclass
class SumOfDisturbances:
    parts: tuple[Disturbance, ...]

    def sample(self, t: float) -> float:
        total = 0.0
        for part in self.parts:
            total += part.sample(t)
        return total
