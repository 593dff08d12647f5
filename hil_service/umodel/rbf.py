"""Gaussian radial-basis layer for the U-model's α₀ term.

Convention (Abbasi et al. 2015, eq. 8)::

    Φ_j(u) = exp(−(u − c_j)² / β²)          (β is a width; no factor 2 in the denominator)
    dΦ_j/du = −2 (u − c_j) / β² · Φ_j(u)

Two evaluation paths are provided on purpose: a numpy path that fills the regressor vector
used by the adaptive update, and a plain-float path returning Σ w_j Φ_j(u) and its derivative,
which is what the inverse controller evaluates several times per sample (17 ``math.exp``
calls are cheaper than a handful of numpy dispatches).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["GaussianRBF", "evenly_spaced_centres"]


def evenly_spaced_centres(n: int, lo: float, hi: float) -> tuple[float, ...]:
    """``n`` centres evenly spaced from ``lo`` to ``hi`` inclusive (the paper uses 17, −2..2)."""
    if n < 1:
        raise ValueError("need at least one centre")
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
        raise ValueError("centre range must be finite with lo <= hi")
    if n == 1:
        return (0.5 * (lo + hi),)
    return tuple(float(c) for c in np.linspace(lo, hi, n))


class GaussianRBF:
    """Fixed-centre Gaussian basis; only the output weights are adapted (by the owner)."""

    __slots__ = ("_c", "_inv_b2", "beta", "centres")

    def __init__(self, centres: Sequence[float], beta: float) -> None:
        cs = tuple(float(c) for c in centres)
        if not cs:
            raise ValueError("need at least one centre")
        if not all(math.isfinite(c) for c in cs):
            raise ValueError("centres must be finite")
        if not (math.isfinite(beta) and beta > 0.0):
            raise ValueError("beta must be finite and > 0")
        self.centres: tuple[float, ...] = cs
        self.beta = float(beta)
        self._inv_b2 = 1.0 / (self.beta * self.beta)
        self._c = np.asarray(cs, dtype=float)

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

    def values_into(self, u: float, out: np.ndarray) -> None:
        """Write Φ(u) into ``out`` (a view into the regressor) without allocating."""
        np.subtract(u, self._c, out=out)
        np.multiply(out, out, out=out)
        np.multiply(out, -self._inv_b2, out=out)
        np.exp(out, out=out)

    def weighted(self, u: float, weights: Sequence[float]) -> tuple[float, float]:
        """(Σ w_j Φ_j(u), Σ w_j dΦ_j/du) with plain floats; the inverse solver's hot path."""
        k = self._inv_b2
        s = 0.0
        ds = 0.0
        exp = math.exp
        for c, w in zip(self.centres, weights, strict=True):
            d = u - c
            g = w * exp(-d * d * k)
            s += g
            ds += d * g
        return s, -2.0 * k * ds
