"""One-step prediction scores: NMSE and skill versus persistence, windowed and cumulative.

NMSE = mean((y − ŷ)²) / var(y); skill = 1 − MSE_model / MSE_persistence, so 0 means no
better than "y(t) = y(t−1)" and 1 means perfect.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field


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
    _recent: deque[tuple[float, float]] = field(default_factory=deque)
    _recent_e2: float = 0.0
    _recent_p2: float = 0.0

    def add(self, y: float, error: float, persistence_error: float) -> None:
        self.count += 1
        e2, p2 = error * error, persistence_error * persistence_error
        self._recent.append((e2, p2))
        self._recent_e2 += e2
        self._recent_p2 += p2
        if len(self._recent) > self.window:
            old_e2, old_p2 = self._recent.popleft()
            self._recent_e2 -= old_e2
            self._recent_p2 -= old_p2
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
        if len(self._recent) < 2 or self._recent_p2 <= 0:
            return None
        return 1.0 - max(self._recent_e2, 0.0) / self._recent_p2

    def summary(self) -> dict[str, float | int | None]:
        return {
            "samples": self.count,
            "nmse": _round(self.nmse()),
            "persistence_nmse": _round(self.persistence_nmse()),
            "skill": _round(self.skill()),
            "recent_skill": _round(self.recent_skill()),
        }


def _round(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(f"{value:.6g}")
