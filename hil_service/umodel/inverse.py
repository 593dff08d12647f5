"""U-model inverse control: solve model(u) = v for the next input, then shape the command.

The solver is a pure function of two callables, f(u) and f'(u), so it can be tested on plain
polynomials; the predictive inverse passes a model's static input map (:mod:`.predictive`).

* Newton–Raphson on the full model (RBF term included, analytic derivative) started from the
  previous input u0 (clamped into [u_min, u_max]): fast and smooth in the common case.
* If Newton fails — non-finite value, |f'| ≤ ``min_slope``, an iterate leaves the actuator
  range, |f − v| grows on 3 consecutive iterations, or no convergence in ``max_iter`` — the
  target is unreachable or the model is non-monotone there, so we return the minimiser of
  |f(u) − v| over the range instead, deterministically: evaluate a dense uniform grid; if
  f − v changes sign on it, a root exists and the one whose cell is nearest u0 is polished
  by bracket-safeguarded Newton; otherwise the best grid point (a bound when the target is
  out of reach) is refined by a stationary-point search (regula falsi on f', golden section
  as backup) in its neighbouring cells. Ties go to u0 (then the lower u), which avoids
  needless jumps when f is flat (e.g. the persistence model).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np

from .finite import finite

__all__ = [
    "CommandShaper",
    "InverseResult",
    "ShapedCommand",
    "solve_inverse",
]

InversePath = Literal["newton", "fallback"]
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass(frozen=True, slots=True, init=False)
class InverseResult:
    """``u`` in range; ``residual`` = f(u) − v; ``iterations`` = Newton updates (newton path)
    or golden-section iterations (fallback path); ``saturated`` = u sits on a range bound
    without meeting the tolerance (target not reachable)."""

    u: float
    path: InversePath
    iterations: int
    residual: float
    saturated: bool

    # Written out, not generated (``init=False``): docs/compiled.md.
    def __init__(
        self, u: float, path: InversePath, iterations: int, residual: float, saturated: bool
    ) -> None:
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "path", path)
        object.__setattr__(self, "iterations", iterations)
        object.__setattr__(self, "residual", residual)
        object.__setattr__(self, "saturated", saturated)


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def _abs_res(f: Callable[[float], float], u: float, v: float) -> float:
    r = f(u) - v
    return abs(r) if finite(r) else math.inf


def _bracketed_root(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    a: float,
    b: float,
    ra: float,
    rb: float,
    tol: float,
    max_iter: int,
) -> tuple[float, int]:
    """Root of f − v in [a, b] with ra·rb ≤ 0: Newton steps kept inside the bracket,
    bisection otherwise (never leaves the cell, converges even where Newton would not)."""
    if ra == 0.0:
        return a, 0
    if rb == 0.0:
        return b, 0
    u = a - ra * (b - a) / (rb - ra)
    best_u, best_r = (a, abs(ra)) if abs(ra) <= abs(rb) else (b, abs(rb))
    it = 0
    while it < max_iter:
        it += 1
        r = f(u) - v
        if not finite(r):
            u = 0.5 * (a + b)
            continue
        if abs(r) < best_r:
            best_u, best_r = u, abs(r)
        if abs(r) <= tol:
            break
        if (r < 0.0) == (ra < 0.0):
            a, ra = u, r
        else:
            b = u
        if b - a <= 1e-15 * (1.0 + abs(a) + abs(b)):
            break
        d = df(u)
        u_new = u - r / d if finite(d) and d != 0.0 else a
        u = u_new if a < u_new < b else 0.5 * (a + b)
    return best_u, it


def _extremum(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    a: float,
    b: float,
    xtol: float,
    max_iter: int,
) -> tuple[float, float, int]:
    """Minimise |f − v| on [a, b] when f − v keeps its sign there (touching or unreachable
    target): the minimiser is a stationary point of f, found by Illinois regula falsi on f'
    when f' changes sign over [a, b], else by golden-section search."""
    da, db = df(a), df(b)
    it = 0
    if finite(da) and finite(db) and da * db < 0.0:
        side = 0
        u = a
        while it < max_iter and (b - a) > xtol:
            it += 1
            u = (a * db - b * da) / (db - da)
            du = df(u)
            if not finite(du) or du == 0.0:
                break
            if (du < 0.0) == (da < 0.0):
                a, da = u, du
                if side == -1:
                    db *= 0.5
                side = -1
            else:
                b, db = u, du
                if side == 1:
                    da *= 0.5
                side = 1
        return u, _abs_res(f, u, v), it
    c = b - _GOLDEN * (b - a)
    d = a + _GOLDEN * (b - a)
    fc, fd = _abs_res(f, c, v), _abs_res(f, d, v)
    while it < max_iter and (b - a) > xtol:
        it += 1
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - _GOLDEN * (b - a)
            fc = _abs_res(f, c, v)
        else:
            a, c, fc = c, d, fd
            d = a + _GOLDEN * (b - a)
            fd = _abs_res(f, d, v)
    return (c, fc, it) if fc <= fd else (d, fd, it)


@lru_cache(maxsize=32)
def _grid(lo: float, hi: float, n: int) -> np.ndarray:
    g = np.linspace(lo, hi, n)
    g.flags.writeable = False
    return g


def _fallback(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    u0: float,
    lo: float,
    hi: float,
    tol: float,
    grid_points: int,
    refine_iter: int,
) -> InverseResult:
    grid = _grid(lo, hi, grid_points)
    vals = np.array([f(u) for u in grid.tolist()], dtype=float)
    r = vals - v
    i, best, ri, cells = _scan_grid(grid, r, u0)
    if cells is not None:
        u, iters = _root_nearest(f, df, v, grid, r, cells, u0, tol, refine_iter)
    else:
        u, iters = _refine_closest(f, df, v, grid, i, best, ri, lo, hi, tol, refine_iter)
    return _unless_u0_is_as_good(f, v, u, u0, lo, hi, tol, iters)


def _scan_grid(
    grid: np.ndarray, r: np.ndarray, u0: float
) -> tuple[int, float, float, np.ndarray | None]:
    """The grid's verdict on f − v (``r``): the cells where it changes sign (a root
    exists), or else the closest grid point i with |f − v| there (``best``) and its signed
    value (``ri``; 0 where not finite). Ties go to the point nearest ``u0``, then to the
    lower u."""
    low, high = float(r.min()), float(r.max())  # NaN anywhere → NaN → the general scan
    if low > 0.0 or high < 0.0:
        # Common case, fast: f − v keeps one sign on the whole grid (no root, nothing NaN).
        i = int(r.argmin()) if low > 0.0 else int(r.argmax())  # lowest u among ties
        best = low if low > 0.0 else -high
        if np.count_nonzero(r == r[i]) > 1:
            ties = np.flatnonzero(r == r[i])
            i = int(ties[int(np.argmin(np.abs(grid[ties] - u0)))])
        return i, best, float(r[i]) if finite(best) else 0.0, None
    finite_r = np.isfinite(r)
    # 1) A sign change on the grid means an exact solution exists: the one nearest u0.
    cells = np.flatnonzero((r[:-1] * r[1:] <= 0.0) & finite_r[:-1] & finite_r[1:])
    if cells.size:
        return 0, 0.0, 0.0, cells
    # 2) No root: minimise |f − v| — best grid point (ties: nearest u0, then lower u)
    a = np.where(finite_r, np.abs(r), np.inf)
    ties = np.flatnonzero(a == a.min())
    i = int(ties[int(np.argmin(np.abs(grid[ties] - u0)))])
    return i, float(a[i]), float(r[i]) if finite_r[i] else 0.0, None


def _root_nearest(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    grid: np.ndarray,
    r: np.ndarray,
    cells: np.ndarray,
    u0: float,
    tol: float,
    refine_iter: int,
) -> tuple[float, int]:
    """The root inside the sign-change cell nearest ``u0``, and the iterations it took."""
    if cells.size == 1:
        i = int(cells[0])
    else:
        mids = 0.5 * (grid[cells] + grid[cells + 1])
        i = int(cells[int(np.argmin(np.abs(mids - u0)))])
    return _bracketed_root(
        f,
        df,
        v,
        float(grid[i]),
        float(grid[i + 1]),
        float(r[i]),
        float(r[i + 1]),
        tol,
        refine_iter,
    )


def _refine_closest(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    grid: np.ndarray,
    i: int,
    best: float,
    ri: float,
    lo: float,
    hi: float,
    tol: float,
    refine_iter: int,
) -> tuple[float, int]:
    """No root: grid point i, refined inside the neighbouring cells unless it is a bound
    that is a one-sided minimum; and the iterations the refinement took."""
    u = float(grid[i])
    iters = 0
    last = grid.size - 1
    refine = 0 < i < last
    if i in (0, last) and best > tol:
        slope = df(u)
        if finite(slope):
            grows_inward = math.copysign(1.0, ri) * slope * (1.0 if i == 0 else -1.0) > 0.0
            refine = not grows_inward and slope != 0.0
    if refine and best > tol:
        ga = float(grid[max(i - 1, 0)])
        gb = float(grid[min(i + 1, last)])
        # |f − v| is flat at a stationary point: 1e-7 of the range in u is plenty.
        uc, rc, iters = _extremum(f, df, v, ga, gb, 1e-7 * (hi - lo), refine_iter)
        if rc < best:
            u = uc
    return u, iters


def _unless_u0_is_as_good(
    f: Callable[[float], float],
    v: float,
    u: float,
    u0: float,
    lo: float,
    hi: float,
    tol: float,
    iters: int,
) -> InverseResult:
    """The fallback's answer ``u``, or ``u0`` itself when it is as close: no needless move
    when f is flat there."""
    res_u0 = _abs_res(f, u0, v)
    res = f(u) - v
    if not finite(res):
        res = math.inf
    if res_u0 <= abs(res):
        u, res = u0, f(u0) - v
        if not finite(res):
            res = math.inf
    saturated = (u <= lo or u >= hi) and abs(res) > tol
    return InverseResult(u, "fallback", iters, res, saturated)


def solve_inverse(
    f: Callable[[float], float],
    df: Callable[[float], float],
    v: float,
    u0: float,
    u_min: float,
    u_max: float,
    *,
    tol: float = 1e-9,
    max_iter: int = 12,
    min_slope: float = 1e-12,
    grid_points: int = 101,
    refine_iter: int = 60,
) -> InverseResult:
    """Find u ∈ [u_min, u_max] with f(u) = v (|f − v| ≤ tol·max(1, |v|)); see module doc.

    A non-finite ``v`` cannot be met: the clamped u0 is returned on the fallback path with
    an infinite residual. A non-finite ``u0`` is replaced by the range midpoint.
    """
    if not (finite(u_min) and finite(u_max) and u_min < u_max):
        raise ValueError("need finite u_min < u_max")
    if grid_points < 2:
        raise ValueError("grid_points must be >= 2")
    u = _clamp(u0, u_min, u_max) if finite(u0) else 0.5 * (u_min + u_max)
    if not finite(v):
        return InverseResult(u, "fallback", 0, math.inf, False)
    tol_abs = tol * max(1.0, abs(v))
    start = u
    prev = math.inf
    worse = 0
    for it in range(max_iter + 1):
        r = f(u) - v
        if not finite(r):
            break
        ar = abs(r)
        if ar <= tol_abs:
            return InverseResult(u, "newton", it, r, False)
        # Near a simple root Newton shrinks |r| every step; repeated growth means it is
        # cycling (e.g. no real root), so stop early and let the fallback decide.
        worse = worse + 1 if ar >= prev else 0
        if worse >= 3:
            break
        prev = ar
        if it == max_iter:
            break
        d = df(u)
        if not (finite(d) and abs(d) > min_slope):
            break
        u_new = u - r / d
        if not (u_min <= u_new <= u_max):
            break
        u = u_new
    return _fallback(f, df, v, start, u_min, u_max, tol_abs, grid_points, refine_iter)


@dataclass(frozen=True, slots=True, init=False)
class ShapedCommand:
    """``saturated``: the request lay outside [u_min, u_max]; ``rate_limited``: the change
    was clipped to ``max_rate``."""

    u: float
    saturated: bool
    rate_limited: bool

    # Written out, not generated (``init=False``): docs/compiled.md.
    def __init__(self, u: float, saturated: bool, rate_limited: bool) -> None:
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "saturated", saturated)
        object.__setattr__(self, "rate_limited", rate_limited)


class CommandShaper:
    """Saturation then rate limiting of the actuator command (state: the last output)."""

    __slots__ = ("_u", "max_rate", "u_max", "u_min")

    def __init__(
        self, u_min: float, u_max: float, max_rate: float | None = None, u_init: float = 0.0
    ) -> None:
        if not (finite(u_min) and finite(u_max) and u_min < u_max):
            raise ValueError("need finite u_min < u_max")
        if max_rate is not None and not (finite(max_rate) and max_rate > 0.0):
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
        if not finite(u_cmd):
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
