"""Recursive least squares with exponential forgetting and a covariance trace bound.

Plain exponential forgetting (P ← P/λ every step) makes P grow without limit in directions
the regressor does not excite — e.g. when the input is held constant — and the estimator
then "bursts". We use the simplest robust remedy: forgetting is applied only while
trace(P) ≤ trace_max (default n·p0, i.e. never more uncertain than at start). Unexcited
directions therefore stop growing at the bound, excited ones still track with factor λ.
P is re-symmetrised each step to stop round-off from breaking positive definiteness.
Trade-off (documented on purpose): while the bound is active the excited directions are not
forgotten either, so tracking there slows to that of plain least squares until excitation
returns and trace(P) drops below the bound again.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["RLS", "ListRLS"]


#: Defaults of both estimators (the models pass their own).
LAMBDA = 0.999
P0 = 100.0


def _checked(n: int, lam: float, p0: float, trace_max: float | None) -> float:
    """Validate the estimator's settings (both classes); the trace bound to use."""
    if n < 1:
        raise ValueError("RLS needs at least one parameter")
    if not (math.isfinite(lam) and 0.0 < lam <= 1.0):
        raise ValueError(f"forgetting factor must satisfy 0 < lam <= 1, got {lam!r}")
    if not (math.isfinite(p0) and p0 > 0.0):
        raise ValueError("p0 must be finite and > 0")
    tmax = n * p0 if trace_max is None else float(trace_max)
    if not (math.isfinite(tmax) and tmax > 0.0):
        raise ValueError("trace_max must be finite and > 0")
    return tmax


class RLS:
    """In-place RLS update of an external θ; owns the covariance P."""

    __slots__ = ("_eye", "lam", "n", "p", "p0", "trace_max")

    def __init__(
        self, n: int, lam: float = LAMBDA, p0: float = P0, trace_max: float | None = None
    ) -> None:
        tmax = _checked(n, lam, p0, trace_max)
        self.n = n
        self.lam = float(lam)
        self.p0 = float(p0)
        self.trace_max = tmax
        self._eye = np.eye(n)
        self.p = self.p0 * self._eye

    def reset(self) -> None:
        """Back to P = p0·I (used after a divergence)."""
        self.p = self.p0 * self._eye

    def update_(self, theta: np.ndarray, phi: np.ndarray, error: float) -> None:
        """θ += k e with k = Pφ/(λ + φᵀPφ); P ← (P − k φᵀP)/λ_eff."""
        p = self.p
        pphi = p @ phi
        denom = self.lam + float(phi @ pphi)
        if not (math.isfinite(denom) and denom > 0.0):
            self.reset()
            return
        k = pphi / denom
        theta += error * k
        p -= np.outer(k, pphi)
        if float(np.trace(p)) <= self.trace_max:
            p /= self.lam
        p += p.T
        p *= 0.5
        if not math.isfinite(float(np.trace(p))):
            self.reset()


class ListRLS:
    """The same estimator on plain float lists, for the per-sample path of the U-model.

    Why lists: for the ~15 parameters of the dynamic U-model a loop over floats (compiled
    with mypyc) beats numpy's per-call overhead, and every sum runs in a fixed order, so
    the result does not depend on the CPU's BLAS kernels (the controller's decisions are
    replayed bit for bit). Only the upper triangle of P is computed; the lower one is its
    mirror, so P stays exactly symmetric. ``update`` returns the gain Pφ/(λ + φᵀPφ) applied.
    """

    __slots__ = ("lam", "n", "p", "p0", "prior", "trace_max")

    def __init__(
        self,
        n: int,
        lam: float = LAMBDA,
        p0: float = P0,
        trace_max: float | None = None,
        prior: list[list[float]] | None = None,
    ) -> None:
        tmax = _checked(n, lam, p0, trace_max)
        self.n = n
        self.lam = float(lam)
        self.p0 = float(p0)
        self.trace_max = tmax
        #: The covariance P starts from and returns to on a reset (None: p0·I).
        self.prior: list[list[float]] | None = None
        if prior is not None:
            if len(prior) != n or any(len(row) != n for row in prior):
                raise ValueError(f"the prior covariance must be {n} x {n}")
            self.prior = [[float(v) for v in row] for row in prior]
        self.p: list[list[float]] = []
        self.reset()

    def reset(self) -> None:
        """Back to the prior covariance, p0·I unless given (after a divergence)."""
        n = self.n
        if self.prior is not None:
            self.p = [list(row) for row in self.prior]
            return
        self.p = [[self.p0 if i == j else 0.0 for j in range(n)] for i in range(n)]

    def update(
        self,
        theta: list[float],
        phi: list[float],
        error: float,
        into: list[list[float]] | None = None,
    ) -> bool:
        """θ += k·e in place, P ← (P − k·(Pφ)ᵀ)/λ_eff; False (and P reset) when the
        update is not finite. With ``into`` (an n × n list of lists, not ``p``) the new P
        is written there and becomes ``p``, and the old one is left as it was: a caller
        that may undo the update keeps it without copying it."""
        n = self.n
        p = self.p
        out = p if into is None else into
        pphi = [0.0] * n
        for i in range(n):
            row = p[i]
            acc = 0.0
            for j in range(n):
                acc += row[j] * phi[j]
            pphi[i] = acc
        denom = self.lam
        for i in range(n):
            denom += phi[i] * pphi[i]
        if not (math.isfinite(denom) and denom > 0.0):
            self.reset()
            return False
        inv = 1.0 / denom
        k = [v * inv for v in pphi]
        for i in range(n):
            theta[i] += k[i] * error
        trace = 0.0
        for i in range(n):
            trace += p[i][i] - k[i] * pphi[i]
        scale = 1.0 / self.lam if trace <= self.trace_max else 1.0
        for i in range(n):
            row = p[i]
            new_row = out[i]
            ki = k[i]
            for j in range(i, n):
                v = (row[j] - ki * pphi[j]) * scale
                new_row[j] = v
                out[j][i] = v
        self.p = out
        if not math.isfinite(trace):
            self.reset()
            return False
        return True
