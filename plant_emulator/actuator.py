"""Ballast actuator: input limits, rate limits and an optional static pump nonlinearity.

All quantities are in model units (the paper's −2..2 input range is full scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class PumpNonlinearity:
    """Static map applied to the rate-limited input: a dead zone plus a cubic term.

    ``f(u) = s·(|u| − dead_zone)₊ + cubic·u³`` with ``s = sign(u)``. It gives a polynomial
    model in u(t−1) something real to find (the ``nonlinear`` scenario).
    """

    dead_zone: float = 0.15
    cubic: float = 0.15

    def __call__(self, u: float) -> float:
        magnitude = max(abs(u) - self.dead_zone, 0.0)
        return math.copysign(magnitude, u) + self.cubic * u**3


@dataclass
class BallastActuator:
    """Saturates and rate-limits commands, then applies the pump map if any."""

    limit: float = 2.0
    rate_limit: float = 0.5
    nonlinearity: PumpNonlinearity | None = None
    position: float = 0.0

    def apply(self, command: float) -> float:
        """Move toward ``command`` for one step; return the effective input to the dynamics."""
        position = self.position
        if not math.isfinite(command):
            command = position
        # min(max(x, −l), l) as comparisons, which pick the same value (ties and NaN
        # included) without the builtins' calls.
        limit, rate_limit = self.limit, self.rate_limit
        target = -limit if -limit > command else command
        target = limit if limit < target else target
        delta = target - position
        delta = -rate_limit if -rate_limit > delta else delta
        delta = rate_limit if rate_limit < delta else delta
        position += delta
        self.position = position
        nonlinearity = self.nonlinearity
        return nonlinearity(position) if nonlinearity else position

    def effective(self, position: float) -> float:
        return self.nonlinearity(position) if self.nonlinearity else position
