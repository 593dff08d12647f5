"""Normalised least-mean-squares (NLMS) parameter update.

    θ ← θ + μ · e · φ / (ε + φᵀφ),   e = y − θᵀφ  (a-priori error)

Normalising by φᵀφ makes the step size independent of the regressor's scale, and the update
is stable (mean-square) for 0 < μ < 2. ε only protects against φ ≈ 0; we use ε = 1e-6 by
default, which is negligible next to φᵀφ for the U-model regressors (the RBF part alone keeps
φᵀφ ≳ 0.5 inside the centre range, and the dynamic model carries a constant bias term of 1).
"""

from __future__ import annotations

from dataclasses import dataclass

from .finite import finite
from .reproducible import dot

__all__ = ["DEFAULT_EPS", "NLMS"]

DEFAULT_EPS = 1e-6


def _check(mu: float, eps: float) -> None:
    if not (finite(mu) and 0.0 < mu < 2.0):
        raise ValueError(f"NLMS step size mu must satisfy 0 < mu < 2, got {mu!r}")
    if not (finite(eps) and eps > 0.0):
        raise ValueError(f"NLMS regulariser eps must be finite and > 0, got {eps!r}")


@dataclass(frozen=True, slots=True)
class NLMS:
    """Validated (μ, ε) pair; ``update`` and ``update_with_terms`` are unchecked."""

    mu: float = 0.5
    eps: float = DEFAULT_EPS

    def __post_init__(self) -> None:
        _check(self.mu, self.eps)

    def update(self, theta: list[float], phi: list[float], error: float) -> list[float]:
        """θ + μ e φ / (ε + φᵀφ) as a new list (lengths are the caller's responsibility)."""
        return self.update_with_terms(theta, phi, error)[0]

    def update_with_terms(
        self, theta: list[float], phi: list[float], error: float
    ) -> tuple[list[float], float, float]:
        """The new θ, with the gain g and φᵀφ it used (the per-sample path; the one place
        the NLMS gain is computed). Plain floats: for ~20-30 parameters a list
        comprehension beats numpy's per-call overhead, and the result is bit-reproducible."""
        phi_sq = dot(phi, phi)
        g = self.mu * error / (self.eps + phi_sq)
        return [t + g * p for t, p in zip(theta, phi)], g, phi_sq  # noqa: B905 - hot path
