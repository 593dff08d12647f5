"""H-step-ahead forecast under a constant future input, for the inverse controller.

Why not the one-step inverse alone: both stabilised glider channels keep the plant's
non-minimum-phase zeros (depth: z = 1.0045; pitch: a pair of modulus 1.105 and z = −2.57),
and the exact one-step inverse of a non-minimum-phase model is unstable (its input grows
until it saturates). Holding the next input constant and asking the model where the output
will be ``horizon`` steps ahead turns that into a well-posed root-finding problem that
tends to the static inverse as the horizon grows and to the paper's one-step inverse as it
shrinks.

Timing: after ``step`` at sample k the model's history holds y(k) and u(k−1); u(k) has
already been applied (the vehicle reported it), so a command sent now acts from u(k+1) on.
The forecast runs the model from k with u(k) = ``u_applied`` and u(k+1 …) = u, and returns
ŷ(k+H). Every U-model here is linear in its past outputs and a sum of static maps of each
input lag, so ŷ(k+H) = offset + Σ_m gain_m·map_m(u). Every map of the package's U-models is
a polynomial in the same scaled input plus, for lag 1, the RBF layer, so the sum collapses
into one ``HorizonMap`` (offset + gain·RBF + one polynomial) built from a single lfilter run
per sample; Newton then costs one RBF pass per iterate. The tests check it against a
step-by-step simulation of the model.

Why the fallback began so often (``experiment --bench``: pitch/dynamic 39 %, depth/paper 92 %):
in about 89 % (pitch) and 99 % (depth/paper) of those samples f(u) − v has no root in the
actuator range: the H-step map is non-monotone in u and the target lies beyond its interior
extremum (the paper model cannot represent the depth integrator; the pitch model after a
300-sample burn-in is strongly non-monotone). The answer is then that extremum, which Newton
on f − v cannot reach; where a root exists Newton fails only on steps that leave the range
or on slow convergence (~4 % of samples). So the fallback was made cheap instead.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import lru_cache
from operator import sub
from typing import Any

import numpy as np
from scipy.signal import lfilter

from .rbf import GaussianRBF
from .reproducible import dot, row_sum

#: The cached design array of a model's grid: [Φ_1(u)…Φ_J(u), x, …, x^degree] as rows.
DesignRows = Callable[[np.ndarray, int], np.ndarray]

_ONE = np.ones(1)  # lfilter numerator


class HorizonMap:
    """ŷ(k+H) as a function of the held input u, in closed form::

        ŷ(k+H)(u) = offset + rbf_gain·Σ_j w_j Φ_j(u) + Σ_i p_i·x^i,   x = poly_scale·u

    For the package's U-models every lag map is an RBF layer (lag 1 only) plus a polynomial
    in the same scaled input, so the gain-weighted sum of the maps collapses to one RBF
    term and one polynomial whose coefficients are computed once per solve: a Newton step
    costs one RBF evaluation and one Horner pass, and the fallback grid is one product of
    a cached design array with the coefficient column.
    """

    __slots__ = (
        "_coef",
        "_curvatures",
        "_design",
        "_poly",
        "_rbf",
        "_scale",
        "_seen",
        "_weights",
        "offset",
        "rbf_gain",
    )

    def __init__(
        self,
        rbf: GaussianRBF,
        poly_scale: float,
        design: DesignRows,
        offset: float,
        rbf_gain: float,
        weights: Sequence[float],
        poly: Sequence[float],
    ) -> None:
        self._design = design
        self._rbf = rbf
        self._scale = poly_scale
        self.offset = offset
        self.rbf_gain = rbf_gain
        self._weights = weights
        self._poly = tuple(poly)  # p_1 … p_P
        self._coef: np.ndarray | None = None
        # One solve asks for the same points more than once (Newton's start is compared
        # with the fallback's answer at the end, value and slope come in pairs): remember
        # every point of this solve; a map lives for one solve only.
        self._seen: dict[float, tuple[float, float]] = {}
        self._curvatures: dict[float, float] | None = None  # made on first use (fallback)

    @property
    def poly(self) -> tuple[float, ...]:
        return self._poly

    def evaluate(self, u: float) -> tuple[float, float]:
        """(ŷ(k+H)(u), dŷ(k+H)/du)."""
        seen = self._seen.get(u)
        if seen is not None:
            return seen
        s, ds = self._rbf.weighted(u, self._weights)
        scale = self._scale
        x = u * scale
        f = df = 0.0
        for a in reversed(self._poly):
            df = df * x + f
            f = f * x + a
        df = df * x + f
        g = self.rbf_gain
        seen = (self.offset + g * s + f * x, g * ds + df * scale)
        self._seen[u] = seen
        return seen

    def value(self, u: float) -> float:
        return self.evaluate(u)[0]

    def derivative(self, u: float) -> float:
        return self.evaluate(u)[1]

    def curvature(self, u: float) -> float:
        """d²ŷ(k+H)/du² (the fallback's stationary-point search takes Newton steps on f').

        Value and slope come out of the same pass over the centres and are remembered, so
        asking for the curvature first makes the slope at the same point free.
        """
        curvatures = self._curvatures
        if curvatures is None:
            curvatures = self._curvatures = {}
        known = curvatures.get(u)
        if known is not None:
            return known
        s, ds, d2s = self._rbf.weighted_curvature(u, self._weights)
        scale = self._scale
        x = u * scale
        # Horner on q with P(x) = x·q(x): P' = q + x·q', P'' = 2q' + x·q''; h2 = q''/2.
        q = h1 = h2 = 0.0
        for a in reversed(self._poly):
            h2 = h2 * x + h1
            h1 = h1 * x + q
            q = q * x + a
        g = self.rbf_gain
        curvature = g * d2s + (2.0 * h1 + 2.0 * x * h2) * scale * scale
        curvatures[u] = curvature
        if u not in self._seen:
            self._seen[u] = (self.offset + g * s + q * x, g * ds + (h1 * x + q) * scale)
        return curvature

    def values(self, us: np.ndarray) -> np.ndarray:
        """``value`` on an array at once (the inverse solver's fallback grid).

        Element-wise products and a fixed-order row sum only (see :mod:`.reproducible`).
        """
        rows = self._design(us, len(self._poly))
        coef = self._coef
        if coef is None:
            g = self.rbf_gain
            coef = np.array([g * w for w in self._weights] + list(self._poly))[:, None]
            self._coef = coef
        total = row_sum(rows * coef)
        total += self.offset
        return total


#: Up to this horizon the step response is a Python loop: for a handful of samples scipy's
#: call overhead (arrays in and out) costs more than the arithmetic.
SHORT_HORIZON = 16


def _short_step_response(ar: Sequence[float], horizon: int) -> list[float]:
    """The unit-step response of 1 / (1 − Σ c_i z⁻ⁱ), s(0..horizon−1), with the very
    operations of scipy's ``lfilter`` (transposed direct form II, numerator [1, 0, …]), so
    the same bits as the long-horizon path (a test compares them)."""
    a = [-c for c in ar]
    last = len(a) - 1
    z = [0.0] * len(a)
    out = []
    for _ in range(horizon):
        y = z[0] + 1.0  # z₀ + b₀·x with b₀ = x = 1
        for i in range(last):
            z[i] = z[i + 1] + 0.0 - y * a[i]  # z_{i+1} + x·b_{i+1} − y·a_{i+1}, b_{i+1} = 0
        z[last] = 0.0 - y * a[last]
        out.append(y)
    return out


@lru_cache(maxsize=8)
def _unit_step(horizon: int) -> np.ndarray:
    step = np.ones(horizon)
    step.flags.writeable = False
    return step


def horizon_response(
    ar: Sequence[float],
    outputs: Sequence[float],
    impulses: list[float],
    bias: float,
    horizon: int,
    n_gains: int,
) -> tuple[float, list[float]]:
    """Known response and input gains of ŷ(t) = Σ_i c_i·ŷ(t−i) + forcing(t) over the horizon.

    ``ar`` = c_1, c_2, …; ``outputs`` = y(k), y(k−1), …; forcing(k+1+n) = bias + impulses[n]
    (bias alone after the listed samples; the list is consumed). Returns ŷ(k+H) and, for
    each input lag L = 1..``n_gains``, the sum of the first H−L impulse-response samples,
    i.e. the unit-step response s at H−L−1.

    One lfilter run gives s, and h(n) = s(n) − s(n−1); the rest is a few scalar products.
    The constant forcing contributes bias·s(H−1) and impulses[n] contributes
    impulses[n]·h(H−1−n). The past outputs enter through the filter state that reproduces
    them (b = [1]: z_m = Σ_{i≥m} c_{i+1}·y(k−i+m)), and an initial state z_m acts on the
    output exactly like an input impulse at n = m.
    """
    n = len(ar)
    extra = impulses
    if len(extra) < n:
        extra += [0.0] * (n - len(extra))
    if n:
        past = list(outputs[:n])
        if len(past) < n:
            past += [0.0] * (n - len(past))
        for m in range(n):
            extra[m] += dot(ar[m:], past)
    # Only the end of s is needed: h(H−1−n) for n < len(extra) and s(H−1−L) for the gains.
    first = horizon - 1 - max(len(extra), n_gains)
    if first < 0:
        first = 0
    if n and horizon <= SHORT_HORIZON:
        tail = [0.0, *_short_step_response(ar, horizon)[first:]]
    elif n:
        denominator = np.array([1.0, *[-c for c in ar]])
        tail = [0.0, *lfilter(_ONE, denominator, _unit_step(horizon))[first:].tolist()]
    else:
        tail = [0.0] + [1.0] * (horizon - first)
    # s(i) = tail[i − first + 1]; tail[0] = s(first − 1), only ever read as s(−1) = 0.
    end = horizon - first  # position of s(H − 1)
    # h(H−1−i) = s(H−1−i) − s(H−2−i) for i = 0, 1, … (map stops with the shorter list).
    known = bias * tail[end] + dot(extra, map(sub, tail[end:0:-1], tail[end - 1 :: -1]))
    if n_gains < horizon:  # s(H−1−L) for L = 1..n_gains
        return known, tail[end - 1 : end - 1 - n_gains : -1]
    return known, [tail[end - lag] if lag < horizon else 0.0 for lag in range(1, n_gains + 1)]


def forecast_model(model: Any, u_applied: float, horizon: int) -> HorizonMap:
    """ŷ(k+``horizon``) of a U-model as a ``HorizonMap`` (the model's own ``horizon_map``).

    Checked in the tests against a step-by-step simulation of the model (horizons 2–150).
    """
    if horizon < 2:
        raise ValueError("horizon must be >= 2: y(k+1) no longer depends on the command")
    method = getattr(model, "horizon_map", None)
    if method is None:
        raise TypeError(f"no H-step forecast for {type(model).__name__}")
    result: HorizonMap = method(u_applied, horizon)
    return result
