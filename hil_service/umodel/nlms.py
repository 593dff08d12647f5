"""Normalised least-mean-squares (NLMS) parameter update.

    θ ← θ + μ · e · φ / (ε + φᵀφ),   e = y − θᵀφ  (a-priori error)

Normalising by φᵀφ makes the step size independent of the regressor's scale, and the update
is stable (mean-square) for 0 < μ < 2. ε only protects against φ ≈ 0; we use ε = 1e-6 by
default, which is negligible next to φᵀφ for the U-model regressors (the RBF part alone keeps
φᵀφ ≳ 0.5 inside the centre range, and the dynamic model carries a constant bias term of 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["DEFAULT_EPS", "NLMS", "nlms_gain", "nlms_update"]

DEFAULT_EPS = 1e-6


def _check(mu: float, eps: float) -> None:
    if not (math.isfinite(mu) and 0.0 < mu < 2.0):
        raise ValueError(f"NLMS step size mu must satisfy 0 < mu < 2, got {mu!r}")
    if not (math.isfinite(eps) and eps > 0.0):
        raise ValueError(f"NLMS regulariser eps must be finite and > 0, got {eps!r}")


def nlms_gain(phi: np.ndarray, error: float, mu: float, eps: float = DEFAULT_EPS) -> float:
    """Scalar g such that the update is θ ← θ + g·φ."""
    return mu * error / (eps + float(np.dot(phi, phi)))


def nlms_update(
    theta: np.ndarray, phi: np.ndarray, error: float, mu: float, eps: float = DEFAULT_EPS
) -> np.ndarray:
    """Pure NLMS update: returns a new θ, leaves the inputs untouched."""
    _check(mu, eps)
    return theta + nlms_gain(phi, error, mu, eps) * phi


@dataclass(frozen=True, slots=True)
class NLMS:
    """Validated (μ, ε) pair with an in-place update for the per-sample path."""

    mu: float = 0.5
    eps: float = DEFAULT_EPS

    def __post_init__(self) -> None:
        _check(self.mu, self.eps)

    def update_(self, theta: np.ndarray, phi: np.ndarray, error: float) -> None:
        """In-place θ += μ e φ / (ε + φᵀφ) (no allocation besides numpy scalars)."""
        g = self.mu * error / (self.eps + float(np.dot(phi, phi)))
        theta += g * phi
