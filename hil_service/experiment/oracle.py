"""The oracle: a constrained receding-horizon controller that knows the plant.

A yardstick for the inverse controller, not a product: it is given the plant's
own state-space model (for the emulator, the stabilised inner loop of
``plant_emulator/models.py``; for ``--scenario random``, the drawn plant), the actuator's
amplitude and rate limits and its static pump map, and nothing else. It sees no future
setpoint and no future disturbance.

Each sample k (after the vehicle reported y(k) and the position u(k) applied during step k):

1. The model's state is advanced with the applied input, so x̂(k+1) is exact for an exact
   model (the plant starts at rest, as the emulator's does).
2. The output disturbance is estimated from the measured output: the residual
   y(k) − trim − ŷ_model(k) is low-passed with time constant ``disturbance_tau`` samples
   and held constant over the horizon, or (``disturbance_trend`` > 0) extrapolated along
   its slope, the change of d̂ per sample low-passed with that time constant (a generic
   ramp model of a current: no knowledge of the realisation). Slow on purpose where the
   plant has a non-minimum-phase zero: reacting fast to a disturbance through it costs
   more IAE than it saves.
3. An LP (HiGHS, through ``highspy``) chooses the effective inputs v(k+1 …) under
   move blocking (``blocks``: the input is held over each block) to minimise the predicted
   Σ_j |ŷ(k+1+j) − r(k)| over the horizon, subject to the amplitude limit, the rate limit
   between blocks and the set of positions reachable from u(k) at each block's start.
   Each |ŷ − r| is the sum of a positive and a negative part tied to the prediction by an
   equality row, and each rate limit one ranged row: half the rows of bounding one slack
   from both sides, which is what a simplex's work per iteration and HiGHS's fixed cost
   per run grow with.
4. The first block's input, mapped back through the pump map, is the command.

The setpoint is held at its current value over the horizon (no preview).

The LP's matrix and costs never change from one sample to the next: only the row bounds
(the predicted free response, the input now) and the block bounds do. So one HiGHS
model is built per controller (``_LpModel``) and each sample updates those bounds and
re-solves from the previous optimal basis (dual simplex warm start): the same LP that
``scipy.optimize.linprog(method="highs")`` would solve from scratch, at a fraction of the
cost (building and presolving a model every sample would be mostly per-call overhead).
Before HiGHS is run at all, the last optimum's basis is tried on the new row and column
bounds (``lp_basis``): a settled depth loop's LP keeps its basis on most samples, and HiGHS
spends about 0.15 ms on a depth run that needs no iteration, against about 50 µs for the
check.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import highspy
import numpy as np
from numpy.typing import NDArray

from hil_service.experiment.lp_basis import OptimalBasis, from_basic_variables

Array = NDArray[np.float64]


def identity(u: float) -> float:
    return u


@dataclass(frozen=True)
class KnownPlant:
    """x⁺ = A x + B v, y = trim + C x + D v, v = pump(u), u the actuator position."""

    a: Array
    b: Array
    c: Array
    d: float = 0.0
    trim: float = 0.0
    pump: Callable[[float], float] = identity
    u_limit: float = 2.0
    rate_limit: float = 0.5

    def __post_init__(self) -> None:
        n = self.a.shape[0]
        if self.a.shape != (n, n) or self.b.shape != (n,) or self.c.shape != (n,):
            raise ValueError("A must be n×n, B and C length n")
        radius = float(np.max(np.abs(np.linalg.eigvals(self.a)))) if n else 0.0
        if not radius < 1.0:
            raise ValueError(f"the oracle needs a stable model (spectral radius {radius:.6f})")
        if not (self.u_limit > 0 and self.rate_limit > 0):
            raise ValueError("u_limit and rate_limit must be positive")

    @property
    def order(self) -> int:
        return int(self.a.shape[0])

    def invert_pump(self, v: float, near: float) -> float:
        """The position u in the actuator range with pump(u) = v (clamped), nearest ``near``.

        The pump map is monotone non-decreasing; bisection finds the least and the greatest
        preimage, and a flat stretch (a dead zone) answers the point of it nearest ``near``.
        """
        lo, hi = -self.u_limit, self.u_limit
        if self.pump is identity:
            return min(max(v, lo), hi)
        if v <= self.pump(lo):
            return lo
        if v >= self.pump(hi):
            return hi
        least = _bisect(self.pump, v, lo, hi, strict=True)
        greatest = _bisect(self.pump, v, lo, hi, strict=False)
        return min(max(near, least), greatest)


def _bisect(f: Callable[[float], float], v: float, lo: float, hi: float, strict: bool) -> float:
    """Least u with f(u) ≥ v (``strict``) or greatest u with f(u) ≤ v, f non-decreasing."""
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = f(mid) < v if strict else f(mid) <= v
        if below:
            lo = mid
        else:
            hi = mid
    return hi if strict else lo


#: Tighter than HiGHS's default 1e-7: a settled loop's error is of the order of the
#: tolerance, and over 20,000 samples that adds up on pitch (IAE ≈ 10).
LP_OPTIONS: dict[str, bool | float | str] = {
    "primal_feasibility_tolerance": 1e-10,
    "dual_feasibility_tolerance": 1e-10,
    "output_flag": False,  # a library: nothing on the console
    "threads": 1,  # one LP per controller; campaigns run missions in parallel processes
}
INF = float(highspy.kHighsInf)
#: The last optimum's basis is taken again when no bound or row is violated by more than
#: this: HiGHS's own primal feasibility tolerance (``LP_OPTIONS``).
PRIMAL_TOLERANCE = 1e-10
#: HiGHS drops matrix entries of at most this magnitude (its ``small_matrix_value``) and
#: answers the model with a warning. A fast plant's step response over a long horizon has
#: such entries (0.33¹⁹ ≈ 8·10⁻¹⁰), so the LP drops them itself: HiGHS and the basis check
#: (``lp_basis``) then solve the same LP.
SMALL_MATRIX_VALUE = 1e-9
#: The basis is factorised after a HiGHS run while its running hit rate (the share of
#: solves it answered, averaged with this gain) is at least MIN_HIT_RATE, and otherwise on
#: every PROBE_EVERY-th run, so that a rate that has fallen can recover.
HIT_RATE_GAIN = 1.0 / 16.0
MIN_HIT_RATE = 0.25
PROBE_EVERY = 32

_LIBC = ctypes.CDLL(None)


@contextlib.contextmanager
def _stdout_to_devnull() -> Iterator[None]:
    """File descriptor 1 onto /dev/null for the duration, C's stdio buffers flushed on
    both sides: constructing a ``highspy.Highs`` writes HiGHS's banner from C++ straight onto
    stdout, before any option can turn it off, and a program whose stdout is JSON
    (``experiment --json``) must not carry it. Python's own pending output is written
    first; what any thread writes to stdout during the construction is lost."""
    if sys.stdout is not None:
        sys.stdout.flush()
    _LIBC.fflush(None)
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        _LIBC.fflush(None)  # what HiGHS buffered goes to /dev/null, not to the real stdout
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _quiet_highs() -> highspy.Highs:
    """A ``highspy.Highs`` with nothing on the console and no Python callback: the
    public class registers one for every solve (for its interrupt and logging events),
    which a controller that solves once per sample does not use."""
    with _stdout_to_devnull():
        highs = highspy.Highs()
    highs.disableCallbacks()
    for name, value in LP_OPTIONS.items():
        highs.setOptionValue(name, value)
    return highs


class _LpModel:
    """min cᵀx s.t. r_lo ≤ A x ≤ r_hi, lo ≤ x ≤ hi, with A and c fixed: one persistent
    HiGHS model whose row and column bounds change per solve, each solve warm-started from
    the last basis."""

    def __init__(
        self,
        cost: Array,
        a: Array,
        row_lower: Array,
        row_upper: Array,
        lower: Array,
        upper: Array,
    ):
        rows, cols = a.shape
        self.rows, self.cols = rows, cols
        self.highs = _quiet_highs()
        lp = highspy.HighsLp()
        lp.num_col_, lp.num_row_ = cols, rows
        lp.col_cost_ = np.asarray(cost, dtype=np.float64)
        lp.col_lower_ = np.asarray(lower, dtype=np.float64)
        lp.col_upper_ = np.asarray(upper, dtype=np.float64)
        lp.row_lower_ = np.asarray(row_lower, dtype=np.float64)
        lp.row_upper_ = np.asarray(row_upper, dtype=np.float64)
        matrix = np.asarray(a, dtype=np.float64)
        matrix = np.where(np.abs(matrix) <= SMALL_MATRIX_VALUE, 0.0, matrix)
        starts: list[int] = [0]
        indices: list[int] = []
        values: list[float] = []
        for j in range(cols):
            nonzero = np.flatnonzero(matrix[:, j])
            indices.extend(int(i) for i in nonzero)
            values.extend(float(v) for v in matrix[nonzero, j])
            starts.append(len(indices))
        lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
        lp.a_matrix_.num_col_, lp.a_matrix_.num_row_ = cols, rows
        lp.a_matrix_.start_ = np.array(starts, dtype=np.int32)
        lp.a_matrix_.index_ = np.array(indices, dtype=np.int32)
        lp.a_matrix_.value_ = np.array(values, dtype=np.float64)
        if self.highs.passModel(lp) != highspy.HighsStatus.kOk:
            raise ValueError("HiGHS refused the oracle's LP")
        self._row_index = np.arange(rows, dtype=np.int32)
        self._col_index = np.arange(cols, dtype=np.int32)
        self._a = matrix
        self._lower = np.array(lower, dtype=np.float64)
        self._upper = np.array(upper, dtype=np.float64)
        self._basis: OptimalBasis | None = None
        self.reused = 0  # solves answered by the last optimum's basis
        # How often the last optimum's basis answers (a running mean): an LP whose every
        # solve moves the basis (the pitch oracle's) would pay for factorising it for
        # nothing, so below MIN_HIT_RATE it is factorised only every PROBE_EVERY runs.
        self._hit_rate = 1.0
        self._since_probe = 0

    def forget(self) -> None:
        """No warm start from before: the next solve is a fresh one."""
        self.highs.clearSolver()
        self._basis = None
        self._hit_rate = 1.0
        self._since_probe = 0

    def solve(
        self,
        row_lower: Array,
        row_upper: Array,
        col_index: NDArray[np.int32],
        lower: Array,
        upper: Array,
    ) -> Array | None:
        """The optimal x with ``row_lower`` ≤ A x ≤ ``row_upper`` and the bounds of columns
        ``col_index`` set to [``lower``, ``upper``] (the other columns keep theirs); None when
        HiGHS finds no optimum. The last optimum's basis answers when it is still primal
        feasible (``lp_basis``); HiGHS is run, from that basis, when it is not."""
        self._lower[col_index] = lower
        self._upper[col_index] = upper
        if self._basis is not None:
            x = self._basis.primal(row_lower, row_upper, self._lower, self._upper, PRIMAL_TOLERANCE)
            self._hit_rate += ((x is not None) - self._hit_rate) * HIT_RATE_GAIN
            if x is not None:
                self.reused += 1
                return x
        highs = self.highs
        highs.changeRowsBounds(  # type: ignore[attr-defined]  # not in highspy's stubs
            self.rows, self._row_index, row_lower, row_upper
        )
        # Every column's bounds: a solve the basis answered may have changed some that
        # this one does not give, and HiGHS has not seen them.
        highs.changeColsBounds(self.cols, self._col_index, self._lower, self._upper)
        self._basis = None
        if highs.run() != highspy.HighsStatus.kOk:
            return None
        if highs.getModelStatus() != highspy.HighsModelStatus.kOptimal:
            return None
        x = np.asarray(highs.getSolution().col_value, dtype=np.float64)
        self._since_probe += 1
        if self._hit_rate >= MIN_HIT_RATE or self._since_probe >= PROBE_EVERY:
            self._since_probe = 0
            self._basis = self._optimal_basis(x, row_lower, row_upper)
        return x

    def _optimal_basis(self, x: Array, row_lower: Array, row_upper: Array) -> OptimalBasis | None:
        """HiGHS's optimal basis at ``x``, factorised; None where the shortcut cannot use
        it (a singular or ill-conditioned square part)."""
        status, basic = self.highs.getBasicVariables()  # type: ignore[attr-defined]  # not in highspy's stubs
        if status != highspy.HighsStatus.kOk:
            return None
        try:
            return from_basic_variables(
                self._a, basic, x, self._lower, self._upper, row_lower, row_upper
            )
        except ValueError:
            return None


#: Mean predicted |y − r| (output units) below which holding the input counts as optimal.
#: Rounding-level only: with 1e-7 a "settled" loop kept errors up to 1e-7 per sample, which
#: over 20,000 samples added 0.0011 to the paper pitch IAE (10.7825 instead of 10.7814).
SETTLED_TOLERANCE = 1e-12


@dataclass(frozen=True)
class OracleSettings:
    """Horizon (samples), move blocks (their lengths; the last block is held to the end of
    the horizon), disturbance filter time constant (samples), and the cost stride (the
    predicted |y − r| is summed every ``cost_stride`` samples, weighted by the stride, to
    keep the LP small on long horizons)."""

    horizon: int = 400
    blocks: tuple[int, ...] = (1, 1, 2, 4, 8, 16, 32)
    disturbance_tau: float = 60.0
    cost_stride: int = 1
    move_weight: float = 0.0  # cost per unit |Δv| between blocks (0: IAE alone)
    # The last block holds the input whose steady state is the setpoint (less d̂), so a
    # plan cannot leave the output off target just beyond the horizon.
    terminal: bool = False
    # Weight of the predicted error j samples ahead: discount**j (1: all alike).
    discount: float = 1.0
    # Time constant (samples) of the low-passed slope of d̂ that extrapolates the disturbance
    # over the horizon (0: d̂ held constant).
    disturbance_trend: float = 0.0
    # The error is costed on every sample before this one, on every cost_stride-th after it
    # (0: the stride from the start).
    stride_from: int = 0

    def __post_init__(self) -> None:
        if self.horizon < 2:
            raise ValueError(f"horizon must be at least 2, got {self.horizon}")
        if not self.blocks or any(b < 1 for b in self.blocks):
            raise ValueError("blocks must be positive lengths")
        if sum(self.blocks) > self.horizon:
            raise ValueError("the blocks must fit in the horizon")
        if not self.disturbance_tau >= 0:
            raise ValueError("disturbance_tau must be ≥ 0 (0: no filtering)")
        if self.cost_stride < 1:
            raise ValueError("cost_stride must be ≥ 1")
        if self.stride_from < 0:
            raise ValueError("stride_from must be ≥ 0")
        if not self.disturbance_trend >= 0:
            raise ValueError("disturbance_trend must be ≥ 0 (0: no trend)")


def _responses(
    plant: KnownPlant, horizon: int, blocks: tuple[int, ...]
) -> tuple[Array, Array, Array]:
    """For the outputs y(k+1+j), j = 0 … H−1: the free response rows C·A^j, the response to
    a unit input held over each move block, and the blocks' first samples."""
    p, n = plant, plant.order
    # The impulse response h_0 = D, h_m = C A^{m−1} B.
    free = np.empty((horizon, n))
    impulse = np.empty(horizon)
    impulse[0] = p.d
    row = p.c.copy()
    for j in range(horizon):
        free[j] = row
        if j + 1 < horizon:
            impulse[j + 1] = float(row @ p.b)
        row = row @ p.a
    starts = np.cumsum((0, *blocks))[:-1]
    ends = [*starts[1:], horizon]
    step = np.cumsum(impulse)  # response to a unit step applied at j = 0
    forced = np.zeros((horizon, len(starts)))
    for b, (j0, j1) in enumerate(zip(starts, ends, strict=True)):
        for j in range(j0, horizon):
            # Σ_{i=j0}^{min(j, j1−1)} h_{j−i}
            upper = step[j - j0]
            lower = step[j - j1] if j >= j1 else 0.0
            forced[j, b] = upper - lower
    return free, forced, starts


def _cost_rows(settings: OracleSettings, horizon: int) -> tuple[Array, Array]:
    """The rows (j of y(k+1+j)) whose error is costed, and the samples each stands for.

    y(k+1) is already decided. Every sample up to ``stride_from``, then every
    ``cost_stride``-th one, each weighted by the samples it stands for.
    """
    s = settings
    dense = np.arange(1, min(max(s.stride_from, 1), horizon))
    sparse = np.arange(dense[-1] + 1 if dense.size else 1, horizon, s.cost_stride)
    cost_rows = np.concatenate((dense, sparse))
    spans = np.concatenate((np.ones(dense.size), np.full(sparse.size, s.cost_stride)))
    return cost_rows, spans


def _constraint_matrix(forced: Array, nb: int, nt: int, moves: bool) -> Array:
    """A of the LP's r_lo ≤ A x ≤ r_hi over (V, e⁺, e⁻[, m]): the tracking rows
    forced·V − e⁺ + e⁻ = gap (e⁺ + e⁻ is |forced·V − gap| at an optimum), the block
    differences V_b − V_{b−1} within the rate limit, and with a move weight
    ±(V_b − V_{b−1}) − m_b ≤ 0."""
    nm = nb if moves else 0
    eye_t = np.eye(nt)
    diff = np.eye(nb) - np.eye(nb, k=-1)  # V_b − V_{b−1}; row 0 is V_0 (v(k) in its bounds)
    rows = [
        np.hstack((forced, -eye_t, eye_t, np.zeros((nt, nm)))),
        np.hstack((diff, np.zeros((nb, 2 * nt + nm)))),
    ]
    if moves:
        rows += [
            np.hstack((diff, np.zeros((nb, 2 * nt)), -np.eye(nb))),
            np.hstack((-diff, np.zeros((nb, 2 * nt)), -np.eye(nb))),
        ]
    return np.vstack(rows)


def _steepest_pump_slope(plant: KnownPlant) -> float:
    """Steepest slope of the pump map, so that the rate limit holds in v as well."""
    grid = np.linspace(-plant.u_limit, plant.u_limit, 401)
    values = np.array([plant.pump(float(u)) for u in grid])
    return max(float(np.max(np.diff(values) / np.diff(grid))), 1e-9)


@dataclass
class OracleController:
    """Receding-horizon LP control of one channel of a known plant."""

    plant: KnownPlant
    settings: OracleSettings = field(default_factory=OracleSettings)
    solves: int = 0
    failures: int = 0
    skipped: int = 0  # samples where holding the input was already an optimum

    def __post_init__(self) -> None:
        p, s = self.plant, self.settings
        n, horizon = p.order, s.horizon
        free, forced, starts = _responses(p, horizon, s.blocks)
        cost_rows, spans = _cost_rows(s, horizon)
        self._free = free[cost_rows]
        self._ahead = cost_rows + 1.0  # samples from k to each costed output
        self._forced = forced[cost_rows]
        self._starts = starts
        nb, nt = len(starts), cost_rows.size
        self._nb, self._nt = nb, nt
        # Variables: block inputs V (nb), the tracking error's positive and negative parts
        # e⁺ and e⁻ (nt each), and with a move weight move slacks m (nb) with
        # m_b ≥ |V_b − V_{b−1}|.
        self._moves = s.move_weight > 0
        nm = nb if self._moves else 0
        weights = spans * np.power(s.discount, cost_rows.astype(float))
        cost = np.concatenate((np.zeros(nb), weights, weights, np.full(nm, s.move_weight)))
        self._a = _constraint_matrix(self._forced, nb, nt, self._moves)
        self._hold_gain = self._forced.sum(axis=1)  # the outputs' response to a held input
        self._dc_gain = float(p.c @ np.linalg.solve(np.eye(n) - p.a, p.b)) + p.d
        if s.terminal and abs(self._dc_gain) < 1e-12:
            raise ValueError("a terminal input needs a non-zero DC gain")
        self._cost = cost
        self._block_index = np.arange(nb, dtype=np.int32)
        self._slope = _steepest_pump_slope(p)
        self._reach = p.rate_limit * (starts.astype(float) + 1.0)
        # The row bounds, refilled per solve; the rows that never change set once: the
        # rate limit on the block differences, and the move rows' ≤ 0.
        self._rate = p.rate_limit * self._slope
        rows = self._a.shape[0]
        self._row_lower = np.full(rows, -INF)
        self._row_upper = np.zeros(rows)
        self._row_lower[nt : nt + nb] = -self._rate
        self._row_upper[nt : nt + nb] = self._rate
        self._lp = _LpModel(
            cost,
            self._a,
            self._row_lower,
            self._row_upper,
            np.concatenate((np.full(nb, -INF), np.zeros(2 * nt + nm))),
            np.full(nb + 2 * nt + nm, INF),
        )
        self.reset()

    def reset(self) -> None:
        self._lp.forget()  # a reset run is a fresh one
        self.state = np.zeros(self.plant.order)
        self.disturbance = 0.0
        self.slope = 0.0
        self._seen = False
        self._last_plan: Array | None = None

    def observe(self, y: float, u_applied: float) -> None:
        """Advance the model with the input applied during this step; update d̂."""
        p = self.plant
        if not (math.isfinite(y) and math.isfinite(u_applied)):
            return  # counted by the caller; the model keeps its last state
        v = p.pump(u_applied)
        residual = y - p.trim - float(p.c @ self.state) - p.d * v
        tau = self.settings.disturbance_tau
        before = self.disturbance
        if not self._seen or tau <= 0:
            self.disturbance = residual
        else:
            self.disturbance += (residual - self.disturbance) / tau
        trend = self.settings.disturbance_trend
        if trend > 0 and self._seen:
            self.slope += (self.disturbance - before - self.slope) / trend
        self._seen = True
        self.state = p.a @ self.state + p.b * v

    def command(self, setpoint: float, u_applied: float) -> float:
        """The position to command for the next step (call after ``observe``)."""
        p = self.plant
        nb, nt = self._nb, self._nt
        free = self._free @ self.state + p.trim + self.disturbance
        if self.settings.disturbance_trend > 0:
            free = free + self.slope * self._ahead
        gap = setpoint - free
        v_now = p.pump(u_applied)
        # Holding the input already predicts (next to) no error over the horizon: the cost
        # cannot go below zero, so holding is an optimum and the LP is skipped (most of a
        # settled, undisturbed run).
        hold_error = gap - self._hold_gain * v_now
        if float(np.sum(np.abs(hold_error))) <= SETTLED_TOLERANCE * nt:
            self.skipped += 1
            return u_applied
        # The positions reachable at each block's first sample, as bounds on v.
        lower = np.maximum(u_applied - self._reach, -p.u_limit)
        upper = np.minimum(u_applied + self._reach, p.u_limit)
        if p.pump is not identity:
            lower = np.array([p.pump(float(u)) for u in lower])
            upper = np.array([p.pump(float(u)) for u in upper])
        if self.settings.terminal:
            v_ss = (setpoint - p.trim - self.disturbance) / self._dc_gain
            v_ss = min(max(v_ss, float(lower[-1])), float(upper[-1]))
            lower[-1] = upper[-1] = v_ss
        # The row bounds: the gap on the tracking rows, the rate limit about v(k) on the
        # first block's row, and with a move weight ±v(k) on the first move rows.
        row_lower, row_upper = self._row_lower, self._row_upper
        row_lower[:nt] = gap
        row_upper[:nt] = gap
        row_lower[nt] = v_now - self._rate
        row_upper[nt] = v_now + self._rate
        if self._moves:
            row_upper[nt + nb] = v_now
            row_upper[nt + 2 * nb] = -v_now
        self.solves += 1
        x = self._lp.solve(row_lower, row_upper, self._block_index, lower, upper)
        if x is None:
            self.failures += 1
            v_next = v_now
        else:
            v_next = float(x[0])
            if nb > 1 and p.pump is not identity:
                # On a flat stretch of the pump map (a dead zone) every position of it gives
                # v_next: take the one furthest along the plan's way, so that a plan that
                # crosses the dead zone does not wait at its edge.
                ahead = float(x[nb - 1]) - v_next
                if ahead != 0.0:
                    return p.invert_pump(v_next, u_applied + math.copysign(p.rate_limit, ahead))
        return p.invert_pump(v_next, u_applied)
