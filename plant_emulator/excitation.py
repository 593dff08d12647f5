"""Excitation the emulator applies to its ballast input when no external command is active.

Amplitudes are in model units and never leave −amplitude..amplitude (default 2, full scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

EXCITATIONS = ("steps", "prbs", "sine", "none")


class Excitation(Protocol):
    def value(self, k: int) -> float:
        """Input at step ``k``; called once per step with k increasing by one."""
        ...


@dataclass
class RandomSteps:
    """Uniform random levels held for a random number of steps in [min_hold, max_hold]."""

    amplitude: float = 2.0
    min_hold: int = 10
    max_hold: int = 40
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)
    _level: float = field(default=0.0, init=False)
    _next_change: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def value(self, k: int) -> float:
        if k >= self._next_change:
            self._level = float(self._rng.uniform(-self.amplitude, self.amplitude))
            self._next_change = k + int(self._rng.integers(self.min_hold, self.max_hold + 1))
        return self._level


@dataclass
class Prbs:
    """Pseudo-random binary sequence from a 9-bit LFSR (x⁹ + x⁵ + 1), each bit held ``hold``."""

    amplitude: float = 1.5
    hold: int = 10
    seed: int = 0
    _register: int = field(init=False)
    _bit: int = field(default=1, init=False)

    def __post_init__(self) -> None:
        self._register = (self.seed % 511) + 1  # any non-zero 9-bit state

    def value(self, k: int) -> float:
        if k % self.hold == 0:
            feedback = ((self._register >> 8) ^ (self._register >> 4)) & 1
            self._register = ((self._register << 1) | feedback) & 0x1FF
            self._bit = feedback
        return self.amplitude if self._bit else -self.amplitude


@dataclass
class Sine:
    amplitude: float = 1.5
    period_steps: float = 80.0

    def value(self, k: int) -> float:
        return self.amplitude * math.sin(2 * math.pi * k / self.period_steps)


@dataclass
class NoExcitation:
    def value(self, k: int) -> float:
        return 0.0


def build_excitation(name: str, seed: int = 0, amplitude: float = 2.0) -> Excitation:
    if name == "steps":
        return RandomSteps(amplitude=amplitude, seed=seed)
    if name == "prbs":
        return Prbs(amplitude=0.75 * amplitude, seed=seed)
    if name == "sine":
        return Sine(amplitude=0.75 * amplitude)
    if name == "none":
        return NoExcitation()
    raise ValueError(f"unknown excitation {name!r}; expected one of {EXCITATIONS}")


def build_channel_excitations(
    name: str, seed: int = 0, amplitude: float = 2.0
) -> dict[str, Excitation]:
    """Independent excitations for the depth and pitch channels, reproducible from ``seed``."""
    return {
        "depth": build_excitation(name, seed=2 * seed, amplitude=amplitude),
        "pitch": build_excitation(name, seed=2 * seed + 1, amplitude=amplitude),
    }
