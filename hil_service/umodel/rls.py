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

import numpy as np
from librt.vecs import vec
from mypy_extensions import i64

from .finite import finite

__all__ = ["RLS", "ListRLS"]


#: Defaults of both estimators (the models pass their own).
LAMBDA = 0.999
P0 = 100.0


def _checked(n: int, lam: float, p0: float, trace_max: float | None) -> float:
    """Validate the estimator's settings (both classes); the trace bound to use."""
    if n < 1:
        raise ValueError("RLS needs at least one parameter")
    if not (finite(lam) and 0.0 < lam <= 1.0):
        raise ValueError(f"forgetting factor must satisfy 0 < lam <= 1, got {lam!r}")
    if not (finite(p0) and p0 > 0.0):
        raise ValueError("p0 must be finite and > 0")
    tmax = n * p0 if trace_max is None else float(trace_max)
    if not (finite(tmax) and tmax > 0.0):
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
        if not (finite(denom) and denom > 0.0):
            self.reset()
            return
        k = pphi / denom
        theta += error * k
        p -= np.outer(k, pphi)
        if float(np.trace(p)) <= self.trace_max:
            p /= self.lam
        p += p.T
        p *= 0.5
        if not finite(float(np.trace(p))):
            self.reset()


class ListRLS:
    """The same estimator on unboxed float vectors, for the per-sample path of the U-model.

    Why not numpy: for the ~15 parameters of the dynamic U-model a loop over floats
    (compiled with mypyc) beats numpy's per-call overhead, and every sum runs in a fixed
    order, so the result does not depend on the CPU's BLAS kernels (the controller's
    decisions are replayed bit for bit). P is one row-major ``vec[float]`` (``librt``, the
    runtime library of mypyc): compiled, its elements are C doubles, where a list of lists
    boxes and unboxes every one of the n² values it touches (an update at n = 17: 7.3 µs
    with lists, 1.4 µs with the vector and ``i64`` indices).
    Only the upper triangle of P is computed; the lower one is its mirror, so P stays
    exactly symmetric. ``update`` returns the gain Pφ/(λ + φᵀPφ) applied.
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
        #: The covariance P starts from and returns to on a reset (None: p0·I), row-major.
        self.prior: vec[float] | None = None
        if prior is not None:
            if len(prior) != n or any(len(row) != n for row in prior):
                raise ValueError(f"the prior covariance must be {n} x {n}")
            self.prior = vec[float]([float(v) for row in prior for v in row])
        #: P, n × n row-major: P[i][j] is ``p[i * n + j]``.
        self.p: vec[float] = vec[float]()
        self.reset()

    def reset(self) -> None:
        """Back to the prior covariance, p0·I unless given (after a divergence)."""
        n = self.n
        if self.prior is not None:
            self.p = vec[float](self.prior)
            return
        self.p = vec[float]([self.p0 if i == j else 0.0 for i in range(n) for j in range(n)])

    def blank(self) -> vec[float]:
        """An n × n buffer of zeros, row-major: a spare for ``update(..., into=)``."""
        return vec[float]([0.0] * (self.n * self.n))

    def covariance(self) -> list[list[float]]:
        """P as a list of rows (a copy)."""
        n: i64 = self.n
        p = self.p
        return [[p[i * n + j] for j in range(n)] for i in range(n)]

    def scale(self, factors: list[float]) -> None:
        """P[i][j] *= factors[i] · factors[j]: P in new units of the parameters."""
        n: i64 = self.n
        p = self.p
        for i in range(n):
            fi = factors[i]
            base = i * n
            for j in range(n):
                p[base + j] *= fi * factors[j]

    def update(
        self,
        theta: list[float],
        phi: list[float],
        error: float,
        into: vec[float] | None = None,
    ) -> bool:
        """θ += k·e in place, P ← (P − k·(Pφ)ᵀ)/λ_eff; False (and P reset) when the
        update is not finite. With ``into`` (an n × n buffer from ``blank``, not ``p``)
        the new P is written there and becomes ``p``, and the old one is left as it was:
        a caller that may undo the update keeps it without copying it."""
        n: i64 = self.n
        p = self.p
        out = p if into is None else into
        x = vec[float](phi)
        pphi = vec[float]([0.0] * n)
        for i in range(n):
            base = i * n
            acc = 0.0
            for j in range(n):
                acc += p[base + j] * x[j]
            pphi[i] = acc
        denom = self.lam
        for i in range(n):
            denom += x[i] * pphi[i]
        if not (finite(denom) and denom > 0.0):
            self.reset()
            return False
        inv = 1.0 / denom
        k = vec[float]([0.0] * n)
        for i in range(n):
            k[i] = pphi[i] * inv
        for i in range(n):
            theta[i] += k[i] * error
        trace = 0.0
        for i in range(n):
            trace += p[i * n + i] - k[i] * pphi[i]
        scale = 1.0 / self.lam if trace <= self.trace_max else 1.0
        for i in range(n):
            ki = k[i]
            base = i * n
            for j in range(i, n):
                v = (p[base + j] - ki * pphi[j]) * scale
                out[base + j] = v
                out[j * n + i] = v
        self.p = out
        if not finite(trace):
            self.reset()
            return False
        return True
