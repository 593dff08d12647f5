"""Hydrodynamic disturbances, added to a channel's output (not to the ballast input).

Each generator is seeded and stepped once per plant sample with the simulated time.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, field
from itertools import pairwise
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
    The breakpoints' times must not decrease, and the last must be after 0.
    """

    amplitude: float = 0.5
    time_scale: float = 1.0
    breakpoints: tuple[tuple[float, float], ...] = PAPER_WAVE_BREAKPOINTS
    _times: list[float] = field(init=False, repr=False, compare=False)
    _values: list[float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Built once, as floats: this runs every plant step of every channel.
        self._times = [float(p[0] * self.time_scale) for p in self.breakpoints]
        self._values = [float(p[1]) for p in self.breakpoints]
        times = self._times
        if not times or any(b < a for a, b in pairwise(times)) or not times[-1] > 0:
            raise ValueError(f"breakpoint times must not decrease and end after 0: {times}")

    def sample(self, t: float) -> float:
        """``amplitude · np.interp(t mod period, times, values)``, with numpy's arithmetic
        on one point: the breakpoint j with times[j] ≤ x < times[j+1], its value where x is
        on it or outside the times, else slope·(x − times[j]) + values[j] (from the right
        end if that is NaN)."""
        times, values = self._times, self._values
        x = t % times[-1]
        if x != x:  # NaN
            return self.amplitude * x
        j = bisect_right(times, x) - 1
        if j < 0:
            return self.amplitude * values[0]
        if j >= len(times) - 1:
            return self.amplitude * values[-1]
        x_j = times[j]
        if x_j == x:
            return self.amplitude * values[j]
        y_j, y_next = values[j], values[j + 1]
        slope = (y_next - y_j) / (times[j + 1] - x_j)
        y = slope * (x - x_j) + y_j
        if y != y:
            y = slope * (x - times[j + 1]) + y_next
            if y != y and y_j == y_next:
                y = y_j
        return self.amplitude * y


#: Normal draws a ``GaussMarkovCurrent`` takes from its generator at a time: the same
#: sequence as one at a time, without a generator call per step.
NORMALS_BATCH = 256


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
    #: The generator's next draws, last first (``pop`` takes the next).
    _normals: list[float] = field(default_factory=list, init=False, repr=False, compare=False)
    #: (dt, sigma, tau) of the last step and its a and σ·√(1−a²): a plant steps at a
    #: fixed period, so they are computed once.
    _key: tuple[float, float, float] | None = field(
        default=None, init=False, repr=False, compare=False
    )
    _a: float = field(default=0.0, init=False, repr=False, compare=False)
    _gain: float = field(default=0.0, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def sample(self, t: float) -> float:
        if self._last_t is not None:
            dt = max(t - self._last_t, 0.0)
            key = (dt, self.sigma, self.tau)
            if key != self._key:
                a = math.exp(-dt / self.tau)
                self._key, self._a, self._gain = key, a, self.sigma * math.sqrt(1.0 - a * a)
            normals = self._normals
            if not normals:
                normals += reversed(self._rng.standard_normal(NORMALS_BATCH).tolist())
            self.value = self._a * self.value + self._gain * normals.pop()
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
    #: (amplitude, period, phase) of each component, zipped once.
    _terms: tuple[tuple[float, float, float], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.amplitudes) != len(self.periods):
            raise ValueError("amplitudes and periods must have the same length")
        rng = np.random.default_rng(self.seed)
        self._phases = tuple(float(p) for p in rng.uniform(0, 2 * math.pi, len(self.periods)))
        self._terms = tuple(zip(self.amplitudes, self.periods, self._phases, strict=True))

    def sample(self, t: float) -> float:
        total = 0.0
        w = 2 * math.pi * t  # the same for every component
        for a, p, ph in self._terms:
            total += a * math.sin(w / p + ph)
        return total


@dataclass
class SumOfDisturbances:
    parts: tuple[Disturbance, ...]

    def sample(self, t: float) -> float:
        total = 0.0
        for part in self.parts:
            total += part.sample(t)
        return total
