"""Gaussian radial-basis layer for the U-model's α₀ term.

Convention (Abbasi et al. 2015, eq. 8)::

    Φ_j(u) = exp(−(u − c_j)² / β²)          (β is a width; no factor 2 in the denominator)
    dΦ_j/du = −2 (u − c_j) / β² · Φ_j(u)

The per-sample paths (``values_list`` for the adaptive update, ``weighted`` for the inverse
solver's Newton iterations) use plain floats and ``math.exp``: for 17 centres that is cheaper
than a handful of numpy dispatches. numpy is used for tests (``values``, ``derivatives``);
the inverse solver's fallback grid is built by :func:`.reproducible.gaussian_columns`.
"""

from __future__ import annotations

import itertools
import math
from bisect import bisect_left, bisect_right
from collections.abc import Sequence

import numpy as np

from .finite import finite

__all__ = ["GaussianRBF", "evenly_spaced_centres"]


def evenly_spaced_centres(n: int, lo: float, hi: float) -> tuple[float, ...]:
    """``n`` centres evenly spaced from ``lo`` to ``hi`` inclusive (the paper uses 17, −2..2)."""
    if n < 1:
        raise ValueError("need at least one centre")
    if not (finite(lo) and finite(hi)) or hi < lo:
        raise ValueError("centre range must be finite with lo <= hi")
    if n == 1:
        return (0.5 * (lo + hi),)
    return tuple(float(c) for c in np.linspace(lo, hi, n))


class GaussianRBF:
    """Fixed-centre Gaussian basis; only the output weights are adapted (by the owner)."""

    __slots__ = ("_c", "_cut", "_inv_b2", "_last", "_sorted", "beta", "centres")

    #: Centres farther than CUTOFF·β from u are skipped in ``weighted``: their basis value is
    #: below exp(−36) ≈ 2e-16, i.e. below double rounding of any comparable-weight term.
    CUTOFF = 6.0

    def __init__(self, centres: Sequence[float], beta: float) -> None:
        cs = tuple(float(c) for c in centres)
        if not cs:
            raise ValueError("need at least one centre")
        if not all(finite(c) for c in cs):
            raise ValueError("centres must be finite")
        if not (finite(beta) and beta > 0.0):
            raise ValueError("beta must be finite and > 0")
        self.centres: tuple[float, ...] = cs
        self.beta = float(beta)
        self._inv_b2 = 1.0 / (self.beta * self.beta)
        self._c = np.asarray(cs, dtype=float)
        self._sorted = all(a <= b for a, b in itertools.pairwise(cs))
        self._cut = self.CUTOFF * self.beta
        self._last: tuple[float, tuple[float, ...]] = (math.nan, ())

    @property
    def size(self) -> int:
        return len(self.centres)

    def values(self, u: float) -> np.ndarray:
        """Φ(u) as a new array (convenience / tests)."""
        d = u - self._c
        return np.exp(-(d * d) * self._inv_b2)

    def derivatives(self, u: float) -> np.ndarray:
        """dΦ/du as a new array."""
        d = u - self._c
        return -2.0 * self._inv_b2 * d * np.exp(-(d * d) * self._inv_b2)

    def values_list(self, u: float) -> list[float]:
        """Φ(u) as a new list of floats (hot path of the adaptive update).

        The last input's values are kept: a held input needs the same Φ(u) again.
        """
        last = self._last
        if last[0] == u:
            return list(last[1])
        k = self._inv_b2
        exp = math.exp
        values = [exp(-(u - c) * (u - c) * k) for c in self.centres]
        self._last = (u, tuple(values))
        return values

    def _window(
        self, u: float, weights: Sequence[float]
    ) -> tuple[Sequence[float], Sequence[float]]:
        """The centres within ±CUTOFF·β of ``u`` and their weights (all when unsorted)."""
        if not self._sorted:
            return self.centres, weights
        lo = bisect_left(self.centres, u - self._cut)
        hi = bisect_right(self.centres, u + self._cut)
        return self.centres[lo:hi], weights[lo:hi]

    def weighted(self, u: float, weights: Sequence[float]) -> tuple[float, float]:
        """(Σ w_j Φ_j(u), Σ w_j dΦ_j/du) with plain floats; the inverse solver's hot path.

        ``weights`` must be indexable in the order of ``centres`` (tuple or list).
        """
        k = self._inv_b2
        s = 0.0
        ds = 0.0
        exp = math.exp
        cs, weights = self._window(u, weights)
        for c, w in zip(cs, weights, strict=True):
            d = u - c
            g = w * exp(-d * d * k)
            s += g
            ds += d * g
        return s, -2.0 * k * ds
