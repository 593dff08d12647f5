"""U-model inverse control: solve model(u) = v for the next input, then shape the command.

The solver is a pure function of two callables, f(u) and f'(u), so it can be tested on plain
polynomials and used with any identifier through ``invert_model``.

* Newton–Raphson on the full model (RBF term included, analytic derivative) started from the
  previous input u0 (clamped into [u_min, u_max]): fast and smooth in the common case.
* If Newton fails — non-finite value, |f'| ≤ ``min_slope``, an iterate leaves the actuator
  range, or no convergence in ``max_iter`` — the target is unreachable or the model is
  non-monotone there, so we return the minimiser of |f(u) − v| over the range instead: a
  dense uniform grid, then golden-section refinement around the best grid point. Ties are
  broken towards u0 (then the lower u), which keeps the result deterministic and avoids
  needless jumps when f is flat (e.g. the persistence model).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

__all__ = [
    "CommandShaper",
    "ImcReference",
    "InverseResult",
    "InvertibleModel",
    "ShapedCommand",
    "imc_target",
    "invert_model",
    "solve_inverse",
]

InversePath = Literal["newton", "fallback"]
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True, slots=True)
class InverseResult:
    """``u`` in range; ``residual`` = f(u) − v; ``iterations`` = Newton updates (newton path)
    or golden-section iterations (fallback path); ``saturated`` = u sits on a range bound
    without meeting the tolerance (target not reachable)."""

    u: float
    path: InversePath
    iterations: int
    residual: float
    saturated: bool


class InvertibleModel(Protocol):
    def output_given_input(self, u: float) -> float: ...

    def output_derivative(self, u: float) -> float: ...


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def _abs_res(f: Callable[[float], float], u: float, v: float) -> float:
    r = f(u) - v
    return abs(r) if math.isfinite(r) else math.inf


def _fallback(
    f: Callable[[float], float],
    v: float,
    u0: float,
    lo: float,
    hi: float,
    tol: float,
    grid_points: int,
    refine_iter: int,
) -> InverseResult:
    n = grid_points
    span = hi - lo
    best_u = u0
    best_r = _abs_res(f, u0, v)
    best_k = -1
    for k in range(n):
        u = lo + span * k / (n - 1) if k < n - 1 else hi
        r = _abs_res(f, u, v)
        if r < best_r or (r == best_r and (abs(u - u0), u) < (abs(best_u - u0), best_u)):
            best_u, best_r, best_k = u, r, k
    iters = 0
    if best_r > tol and best_k >= 0:
        # Golden-section search for min |f − v| on the two cells around the best grid point.
        a = lo + span * (best_k - 1) / (n - 1) if best_k > 0 else lo
        b = lo + span * (best_k + 1) / (n - 1) if best_k < n - 1 else hi
        a, b = max(a, lo), min(b, hi)
        c = b - _GOLDEN * (b - a)
        d = a + _GOLDEN * (b - a)
        fc, fd = _abs_res(f, c, v), _abs_res(f, d, v)
        while iters < refine_iter and (b - a) > 1e-15 * (1.0 + abs(a) + abs(b)):
            iters += 1
            if fc <= fd:
                b, d, fd = d, c, fc
                c = b - _GOLDEN * (b - a)
                fc = _abs_res(f, c, v)
            else:
                a, c, fc = c, d, fd
                d = a + _GOLDEN * (b - a)
                fd = _abs_res(f, d, v)
            if min(fc, fd) <= tol:
                break
        u_ref, r_ref = (c, fc) if fc <= fd else (d, fd)
        if r_ref < best_r:
            best_u, best_r = u_ref, r_ref
    res = f(best_u) - v
    if not math.isfinite(res):
        res = math.inf
    saturated = (best_u <= lo or best_u >= hi) and abs(res) > tol
    return InverseResult(best_u, "fallback", iters, res, saturated)


def solve_inverse(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    u0: float,
    u_min: float,
    u_max: float,
    *,
    tol: float = 1e-9,
    max_iter: int = 20,
    min_slope: float = 1e-12,
    grid_points: int = 201,
    refine_iter: int = 80,
) -> InverseResult:
    """Find u ∈ [u_min, u_max] with f(u) = v (|f − v| ≤ tol·max(1, |v|)); see module doc.

    A non-finite ``v`` cannot be met: the clamped u0 is returned on the fallback path with
    an infinite residual. A non-finite ``u0`` is replaced by the range midpoint.
    """
    if not (math.isfinite(u_min) and math.isfinite(u_max) and u_min < u_max):
        raise ValueError("need finite u_min < u_max")
    if grid_points < 2:
        raise ValueError("grid_points must be >= 2")
    u = _clamp(u0, u_min, u_max) if math.isfinite(u0) else 0.5 * (u_min + u_max)
    if not math.isfinite(v):
        return InverseResult(u, "fallback", 0, math.inf, False)
    tol_abs = tol * max(1.0, abs(v))
    start = u
    for it in range(max_iter + 1):
        r = f(u) - v
        if not math.isfinite(r):
            break
        if abs(r) <= tol_abs:
            return InverseResult(u, "newton", it, r, False)
        if it == max_iter:
            break
        d = df(u)
        if not (math.isfinite(d) and abs(d) > min_slope):
            break
        u_new = u - r / d
        if not (u_min <= u_new <= u_max):
            break
        u = u_new
    return _fallback(f, v, start, u_min, u_max, tol_abs, grid_points, refine_iter)


def invert_model(
    model: InvertibleModel,
    v: float,
    u0: float,
    u_min: float,
    u_max: float,
    **kwargs: float,
) -> InverseResult:
    """``solve_inverse`` on a model's ŷ(t+1)(u) and its analytic derivative."""
    return solve_inverse(
        model.output_given_input, model.output_derivative, v, u0, u_min, u_max, **kwargs
    )


@dataclass(frozen=True, slots=True)
class ShapedCommand:
    """``saturated``: the request lay outside [u_min, u_max]; ``rate_limited``: the change
    was clipped to ``max_rate``."""

    u: float
    saturated: bool
    rate_limited: bool


class CommandShaper:
    """Saturation then rate limiting of the actuator command (state: the last output)."""

    __slots__ = ("_u", "max_rate", "u_max", "u_min")

    def __init__(
        self, u_min: float, u_max: float, max_rate: float | None = None, u_init: float = 0.0
    ) -> None:
        if not (math.isfinite(u_min) and math.isfinite(u_max) and u_min < u_max):
            raise ValueError("need finite u_min < u_max")
        if max_rate is not None and not (math.isfinite(max_rate) and max_rate > 0.0):
            raise ValueError("max_rate must be None or finite and > 0")
        self.u_min = float(u_min)
        self.u_max = float(u_max)
        self.max_rate = None if max_rate is None else float(max_rate)
        self._u = _clamp(float(u_init), self.u_min, self.u_max)

    @property
    def u(self) -> float:
        return self._u

    def reset(self, u: float = 0.0) -> None:
        self._u = _clamp(float(u), self.u_min, self.u_max)

    def shape(self, u_cmd: float) -> ShapedCommand:
        """Next command; a non-finite request holds the previous output."""
        if not math.isfinite(u_cmd):
            return ShapedCommand(self._u, False, False)
        sat = u_cmd < self.u_min or u_cmd > self.u_max
        u = _clamp(u_cmd, self.u_min, self.u_max)
        limited = False
        if self.max_rate is not None:
            lo, hi = self._u - self.max_rate, self._u + self.max_rate
            if u < lo or u > hi:
                u = _clamp(u, lo, hi)
                limited = True
        self._u = u
        return ShapedCommand(u, sat, limited)


def imc_target(filtered_setpoint: float, y: float, y_hat: float) -> float:
    """IMC target v = r_f − (y − ŷ): the model must aim off by the current mismatch.

    A non-finite y or ŷ contributes no correction (the target stays finite if r_f is).
    """
    mismatch = y - y_hat
    return filtered_setpoint - mismatch if math.isfinite(mismatch) else filtered_setpoint


class ImcReference:
    """First-order reference filter r_f ← a·r_f + (1 − a)·r plus the IMC mismatch term.

    ``a`` ∈ [0, 1): 0 = no filtering; larger = smoother, slower reference. The filter starts
    from ``initial`` if given, else from the first measured output (bumpless start).
    """

    __slots__ = ("_rf", "a")

    def __init__(self, a: float = 0.9, initial: float | None = None) -> None:
        if not (math.isfinite(a) and 0.0 <= a < 1.0):
            raise ValueError("filter coefficient a must be in [0, 1)")
        self.a = float(a)
        self._rf = None if initial is None or not math.isfinite(initial) else float(initial)

    @property
    def value(self) -> float | None:
        return self._rf

    def reset(self, value: float | None = None) -> None:
        self._rf = None if value is None or not math.isfinite(value) else float(value)

    def filter(self, setpoint: float, start: float | None = None) -> float:
        """Advance the filter one sample and return r_f (non-finite setpoints are ignored)."""
        rf = self._rf
        if rf is None:
            rf = start if start is not None and math.isfinite(start) else setpoint
            if not math.isfinite(rf):
                rf = 0.0
        if math.isfinite(setpoint):
            rf = self.a * rf + (1.0 - self.a) * setpoint
        self._rf = rf
        return rf

    def target(self, setpoint: float, y: float, y_hat: float) -> float:
        """v = filtered setpoint − (y − ŷ), with ŷ the a-priori prediction of this y."""
        return imc_target(self.filter(setpoint, start=y), y, y_hat)
