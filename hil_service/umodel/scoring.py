"""Prediction scores: one-step NMSE and skill versus persistence, windowed and cumulative;
multi-step accuracy of the free-running model over the control horizon.

NMSE = mean((y − ŷ)²) / var(y); skill = 1 − MSE_model / MSE_persistence, so 0 means no
better than "y(t) = y(t−1)" and 1 means perfect. Free-run fit (system identification's
"simulation fit") = 100·(1 − ‖y − ŷ_sim‖ / ‖y − mean(y)‖).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from .finite import finite


@dataclass
class ErrorStats:
    """Running sums over all samples after ``burn_in``, plus a sliding window."""

    burn_in: int = 0
    window: int = 500
    count: int = 0
    _n: int = 0
    _sum_e2: float = 0.0
    _sum_p2: float = 0.0
    _sum_y: float = 0.0
    _sum_y2: float = 0.0
    # The window's squares in two deques of floats, not one of pairs: floats are not
    # objects the garbage collector traverses, and a fleet keeps two of these a vehicle.
    _recent_errors: deque[float] = field(default_factory=deque)
    _recent_persistence: deque[float] = field(default_factory=deque)
    _recent_e2: float = 0.0
    _recent_p2: float = 0.0

    def add(self, y: float, error: float, persistence_error: float) -> None:
        self.count += 1
        e2, p2 = error * error, persistence_error * persistence_error
        self._recent_errors.append(e2)
        self._recent_persistence.append(p2)
        self._recent_e2 += e2
        self._recent_p2 += p2
        if len(self._recent_errors) > self.window:
            self._recent_e2 -= self._recent_errors.popleft()
            self._recent_p2 -= self._recent_persistence.popleft()
        if self.count <= self.burn_in:
            return
        self._n += 1
        self._sum_e2 += error * error
        self._sum_p2 += persistence_error * persistence_error
        self._sum_y += y
        self._sum_y2 += y * y

    def _normalised(self, sum_squares: float) -> float | None:
        """Mean square over the variance of y, both after burn-in."""
        if self._n < 2:
            return None
        mean = self._sum_y / self._n
        variance = max(self._sum_y2 / self._n - mean * mean, 1e-300)
        return (sum_squares / self._n) / variance

    def nmse(self) -> float | None:
        return self._normalised(self._sum_e2)

    def persistence_nmse(self) -> float | None:
        return self._normalised(self._sum_p2)

    def skill(self) -> float | None:
        if self._n < 2 or self._sum_p2 <= 0:
            return None
        return 1.0 - self._sum_e2 / self._sum_p2

    def recent_skill(self) -> float | None:
        if len(self._recent_errors) < 2 or self._recent_p2 <= 0:
            return None
        return 1.0 - max(self._recent_e2, 0.0) / self._recent_p2

    def summary(self) -> dict[str, float | int | None]:
        return {
            "samples": self.count,
            "nmse": significant(self.nmse()),
            "persistence_nmse": significant(self.persistence_nmse()),
            "skill": significant(self.skill()),
            "recent_skill": significant(self.recent_skill()),
        }


def significant(value: float | None) -> float | None:
    """Six significant digits for a report (an NMSE of 3e-8 must not print as 0); None for
    a missing or non-finite value."""
    return None if value is None or not finite(value) else float(f"{value:.6g}")


def normalised_square_error(y: list[float], error: list[float]) -> float | None:
    """Σe² / Σ(y − ȳ)²: the NMSE of a prediction whose error is ``error`` = y − ŷ.

    The one definition of the multi-step figures: the k-step NMSE, and through
    ``fit_from_nmse`` the free-run fit, in ``experiment``, ``report`` (through
    ``hil_service.umodel.multistep``) and ``health`` (``MultiStepStats``). None for
    fewer than two samples, a non-finite y or error, or a flat output (no scale to judge
    the prediction by). Fixed-order sums: the same figures on every run. Lists, not any
    sequence: compiled, a list's items are read without a generic call each, and a
    fleet's health takes these sums for every vehicle.
    """
    n = len(y)
    if len(error) != n:
        raise ValueError(f"y and error differ in length: {n} and {len(error)}")
    if n < 2:
        return None
    mean = 0.0
    for value in y:
        mean += value
    mean /= n
    spread = 0.0
    squares = 0.0
    for i in range(n):
        deviation = y[i] - mean
        e = error[i]
        spread += deviation * deviation
        squares += e * e
    if not (finite(spread) and finite(squares)):
        return None
    if not spread > 1e-12 * n * (1.0 + mean * mean):
        return None  # a flat output: no scale to judge the fit by
    return squares / spread


def fit_from_nmse(nmse: float | None) -> float | None:
    """Free-run fit % = 100·(1 − ‖y − ŷ_sim‖ / ‖y − ȳ‖) = 100·(1 − √NMSE)."""
    return None if nmse is None else 100.0 * (1.0 - math.sqrt(nmse))


class MultiStepStats:
    """Rolling accuracy of the model's free run: the pipeline restarts a frozen copy of the
    model from the measured outputs every ``horizon`` samples and feeds it the applied
    inputs, so each ŷ_sim is a 1…horizon-step-ahead prediction. Over the last ``window``
    samples: NMSE and fit % of ``normalised_square_error`` and ``fit_from_nmse``.

    The sums are taken when asked (health is published at 1 Hz), not kept running: a
    free run that blew up must not leave its rounding in the figures after it has left
    the window."""

    __slots__ = ("_errors", "_outputs", "window")

    #: A free-run error beyond this (or not finite) counts as this: the fit is then very
    #: negative, and the squares stay finite.
    ERROR_CAP = 1e100

    def __init__(self, window: int = 500) -> None:
        self.window = window
        # Two deques of floats, not one of (y, e) pairs, as in ErrorStats.
        self._outputs: deque[float] = deque(maxlen=window)
        self._errors: deque[float] = deque(maxlen=window)

    def add(self, y: float, y_sim: float) -> None:
        if not finite(y):
            return
        e = y - y_sim
        if not (finite(e) and abs(e) < self.ERROR_CAP):
            e = self.ERROR_CAP
        self._outputs.append(y)
        self._errors.append(e)

    def nmse(self) -> float | None:
        return normalised_square_error(list(self._outputs), list(self._errors))

    def fit(self) -> float | None:
        return fit_from_nmse(self.nmse())

    def summary(self, horizon: int) -> dict[str, float | int | None]:
        nmse = self.nmse()
        return {
            "multistep_horizon": horizon,
            "multistep_nmse": significant(nmse),
            "multistep_fit": significant(fit_from_nmse(nmse)),
        }
