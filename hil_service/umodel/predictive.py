"""Predictive U-model inverse: the next input from an optimisation over a horizon.

At every sample the identified U-model gives its multi-step map (:class:`.ModelDynamics`):
linear in past outputs, a polynomial of each input lag. The controller

1. reads the lag polynomials as one static input map times a linear filter (a rank-one
   factorisation of the lag × power coefficient matrix: w = N(u), y = G(q)·w; exact for a
   Hammerstein plant, the best rank-one fit otherwise);
2. derives its horizons from the identified linear part: the prediction horizon is the
   settling time of G's step response (clamped to ``[min_horizon, max_horizon]``), and
   the input is planned in blocks that start at 1, 2, 4, … samples (geometric up to the
   horizon, at most ``max_blocks``): fine where the plan is applied next, coarse where
   only its level matters;
3. predicts the output with every future input held at the applied one (the free
   response of the internal model, plus the disturbance estimate), adds each block's
   effect through G's step response, and minimises Σ (ŷ − r)² + ρ Σ Δw² over the block
   levels inside the actuator's range (the first block also inside its rate limit): a
   box-constrained QP, solved exactly by a primal active-set method. The cost starts
   where the response to a move peaks the wrong way (``cost_start``) and sees every
   sample of the blocks shorter than its stride (``cost_points``);
4. root-solves N(u) = w for the first block (the U-model inverse step, with the solver's
   fallback where there is no real root).

Offset-free tracking (internal model control): an internal copy of the model runs on its
own outputs and the applied inputs; the measured output's departure from it, low-passed
with a time constant of a share of the horizon (``disturbance_share``), is the output
disturbance, held constant over the horizon. A slow estimate on purpose: a
non-minimum-phase plant answers a fast correction with its wrong-way response.

Guards: non-finite model coefficients, a degenerate input map or a non-finite plan give
"hold" (the applied input), never an exception or a non-finite command.
"""

from __future__ import annotations

import math

from .dynamics import ModelDynamics, StaticMap
from .inverse import solve_inverse

__all__ = [
    "PredictiveInverse",
    "PredictiveSettings",
    "cost_points",
    "settling_horizon",
    "step_response",
]

#: Power-iteration sweeps of the rank-one factorisation (a 3×3 symmetric matrix).
_POWER_SWEEPS = 30


class PredictiveSettings:
    """Scale-free constants of the predictive inverse (no plant's figure among them)."""

    __slots__ = (
        "band",
        "cost_points",
        "disturbance_share",
        "max_blocks",
        "max_horizon",
        "min_horizon",
        "move_weight",
        "refresh",
    )

    def __init__(
        self,
        min_horizon: int = 5,
        max_horizon: int = 1000,
        band: float = 0.05,
        max_blocks: int = 8,
        move_weight: float = 0.03,
        disturbance_share: float = 0.5,
        refresh: int = 50,
        cost_points: int = 120,
    ) -> None:
        if not 2 <= min_horizon <= max_horizon:
            raise ValueError("need 2 <= min_horizon <= max_horizon")
        if not 0.0 < band < 1.0:
            raise ValueError("band must be in (0, 1)")
        if max_blocks < 2:
            raise ValueError("max_blocks must be >= 2")
        if not (math.isfinite(move_weight) and move_weight >= 0.0):
            raise ValueError("move_weight must be finite and >= 0")
        if not (math.isfinite(disturbance_share) and disturbance_share > 0.0):
            raise ValueError("disturbance_share must be finite and > 0")
        if refresh < 1:
            raise ValueError("refresh must be >= 1")
        if cost_points < 1:
            raise ValueError("cost_points must be >= 1")
        self.min_horizon = int(min_horizon)
        self.max_horizon = int(max_horizon)
        self.band = float(band)
        self.max_blocks = int(max_blocks)
        self.move_weight = float(move_weight)
        self.disturbance_share = float(disturbance_share)
        self.refresh = int(refresh)
        #: At most this many points of the horizon enter the cost (evenly spaced, the last
        #: one always).
        self.cost_points = int(cost_points)


def block_starts(horizon: int, max_blocks: int) -> list[int]:
    """First samples of the input blocks: 1 (the command), then geometrically spaced up to
    the horizon (ratio 2, or larger so that there are at most ``max_blocks``): fine where
    the plan is applied next, coarse where only its level matters."""
    ratio = 2.0
    if max_blocks > 2:
        ratio = max(ratio, math.exp(math.log(max(horizon, 2)) / (max_blocks - 1)))
    starts = [1]
    edge = 1.0
    while True:
        edge *= ratio
        start = round(edge)
        if start >= horizon:
            break
        if start > starts[-1]:
            starts.append(start)
    if len(starts) == 1 and horizon > 1:
        starts.append(2)
    return starts


def cost_points(
    horizon: int, stride: int, starts: list[int], first: int = 1
) -> tuple[list[int], list[float]]:
    """The samples j of the horizon whose predicted error enters the cost, newest first,
    and each one's weight (the samples it stands for, in strides).

    Every ``stride``-th sample from the horizon down, and every sample while the input
    blocks are shorter than a stride: a block's level moves the output at once (on the
    ArduSub depth channel by −2.1 m per unit within one sample, a wrong-way response that
    lasts as long as the block), so a block between two cost points could pulse unseen.
    The plan then kept an unseen pulse in its second block and the applied first block
    near the held input, every sample again (a stall 0.8 m short for 450 samples;
    docs/control.md, "Blocks the cost does not see"). A point stands for the samples down
    to the next one, so the sum stays a consistent approximation of the whole horizon's.
    """
    dense = 0
    for b in range(len(starts)):
        end = starts[b + 1] if b + 1 < len(starts) else horizon
        if end - starts[b] >= stride:
            break
        dense = end
    dense = min(dense, horizon)
    first = max(1, min(first, horizon))
    points = list(range(horizon, max(dense, first - 1), -stride))
    points += list(range(min(dense, points[-1] - 1 if points else horizon), first - 1, -1))
    weights: list[float] = []
    for p in range(len(points)):
        below = points[p + 1] if p + 1 < len(points) else first - 1
        weights.append(1.0 if points[p] - below >= stride else (points[p] - below) / stride)
    return points, weights


def cost_start(response: list[float], horizon: int) -> int:
    """The first sample of the horizon whose error enters the cost (GPC's minimum costing
    horizon N1): 1, or the sample m at which the step response peaks the wrong way (5 on
    ArduSub and glider depth: −2.13 after one sample, −2.44 after five).

    Before it the output moves the wrong way whatever the plan does now. The first
    block acts from sample 2, so its own wrong-way peak is at m + 1 and its jump is seen at
    one point of the cost: a partial charge. Measured both ways (docs/control.md, "Blocks
    the cost does not see"): from m + 1 (the jump never charged) the plan was bolder and
    disturbed glider depth 3.8 % (5,000 samples) and 7.3 % (20,000) worse; from m, 1.9 %
    and 2.6 %; a cost from sample 1 holds the steady-state input and never kicks (paper
    depth 33 % worse)."""
    final = response[-1] if response else 0.0
    if not (math.isfinite(final) and final != 0.0):
        return 1
    worst = 0.0
    at = 0
    for m in range(min(horizon, len(response))):
        wrong = -response[m] if final > 0.0 else response[m]
        if wrong > worst:
            worst, at = wrong, m
    return at if at > 0 else 1


def step_response(ar: list[float], gains: list[float], n: int) -> list[float]:
    """s(0 … n−1): the output j samples after w steps from 0 to 1 (s(0) = 0: no
    feedthrough), for y(t) = Σ c_i y(t−i) + Σ_L g_L w(t−L)."""
    na = len(ar)
    nb = len(gains)
    out: list[float] = []
    forcing = 0.0
    for j in range(n):
        if 1 <= j <= nb:
            forcing += gains[j - 1]
        acc = forcing
        for i in range(na):
            if j - 1 - i >= 0:
                acc += ar[i] * out[j - 1 - i]
        out.append(acc)
    return out


def plan_matrices(
    response: list[float], starts: list[int], points: list[int], weights: list[float]
) -> tuple[list[list[float]], list[float], list[list[float]]]:
    """Per cost point, each block's weighted effect on ŷ(k+j) (the columns) and the held
    input's step s(j − 1) (the onset); and the output cost's Hessian Σ_p w_p·col·colᵀ."""
    nblocks = len(starts)
    columns: list[list[float]] = []
    onset: list[float] = []
    hessian = [[0.0] * nblocks for _ in range(nblocks)]
    for p in range(len(points)):
        j = points[p]
        weight = weights[p]
        # Block b's level acts on ŷ(k+j) through s(j − start_b) − s(j − start_{b+1})
        # (s(m) = 0 for m ≤ 0: an input acts one sample later).
        col = [0.0] * nblocks
        for b in range(nblocks):
            first = j - starts[b]
            on = response[first] if first > 0 else 0.0
            off = 0.0
            if b + 1 < nblocks:
                after = j - starts[b + 1]
                off = response[after] if after > 0 else 0.0
            col[b] = on - off
        # Stored weighted: the QP's linear term is Σ_p weight·col·residual.
        columns.append([weight * c for c in col])
        first0 = j - starts[0]
        onset.append(response[first0] if first0 > 0 else 0.0)
        for a in range(nblocks):
            wa = weight * col[a]
            for b in range(nblocks):
                hessian[a][b] += wa * col[b]
    return columns, onset, hessian


def add_move_penalty(hessian: list[list[float]], move_weight: float) -> float:
    """Add the move penalty ρ Σ (W_b − W_{b−1})² (W_{−1} = the applied input's level) to
    ``hessian`` in place, ρ scaled to the output cost's size; returns ρ."""
    nblocks = len(hessian)
    trace = 0.0
    for b in range(nblocks):
        trace += hessian[b][b]
    rho = move_weight * (trace / nblocks + 1e-12)
    for b in range(nblocks):
        hessian[b][b] += rho if b + 1 == nblocks else 2.0 * rho
        if b + 1 < nblocks:
            hessian[b][b + 1] -= rho
            hessian[b + 1][b] -= rho
    return rho


def free_response_terms(
    ar: list[float], lags: int, n: int, points: list[int]
) -> tuple[list[float], list[list[float]]]:
    """1/A(q) at the cost points, for the free response in closed form
    (``PredictiveInverse._free_response``): S_A(j), the running sum of the impulse response
    h_A, and h_A(j − l) for l = 1 … L, L = max(na, lags − 1, 1)."""
    na = len(ar)
    lead = max(na, lags - 1, 1)
    impulse: list[float] = []
    for m in range(n):
        acc = 1.0 if m == 0 else 0.0
        for i in range(na):
            if m - 1 - i >= 0:
                acc += ar[i] * impulse[m - 1 - i]
        impulse.append(acc)
    running = [0.0]
    for m in range(n):
        running.append(running[-1] + impulse[m])
    step = [running[j] for j in points]
    impulses = [
        [impulse[j - d] if j - d >= 0 else 0.0 for d in range(1, lead + 1)] for j in points
    ]
    return step, impulses


def settling_horizon(response: list[float], band: float, lo: int, hi: int) -> int:
    """The first sample after which the step response stays within ``band`` of its last
    value (the response is ``hi`` long), clamped to [lo, hi]; ``hi`` when it does not
    settle or is not finite."""
    n = len(response)
    if n == 0:
        return lo
    final = response[-1]
    if not math.isfinite(final) or final == 0.0:
        return hi
    # Not settled if it still moves at the end: compare with the value a tenth earlier.
    check = response[n - 1 - n // 10]
    tol = band * abs(final)
    if abs(check - final) > tol:
        return hi
    last = 0
    for j in range(n):
        if abs(response[j] - final) > tol:
            last = j + 1
    return lo if last < lo else hi if last > hi else last


def factorise(dyn: ModelDynamics, u_lo: float, u_hi: float) -> tuple[list[float], StaticMap] | None:
    """Lag gains g_L and the static map N with P_L(u) ≈ g_L·N(u); N scaled to a mean slope
    of one over [u_lo, u_hi]. None when the map is degenerate (no input effect yet)."""
    polys = dyn.lag_polys
    m = 0
    for poly in polys:
        m = max(m, len(poly))
    if m == 0:
        return None
    rows = [poly + [0.0] * (m - len(poly)) for poly in polys]
    # Θᵀ Θ (m × m), then its dominant eigenvector by power iteration from e_1.
    gram = [[0.0] * m for _ in range(m)]
    for row in rows:
        for i in range(m):
            ri = row[i]
            for j in range(m):
                gram[i][j] += ri * row[j]
    v = [1.0] + [0.0] * (m - 1)
    for _ in range(_POWER_SWEEPS):
        w = [0.0] * m
        for i in range(m):
            acc = 0.0
            for j in range(m):
                acc += gram[i][j] * v[j]
            w[i] = acc
        norm = 0.0
        for x in w:
            norm += x * x
        norm = math.sqrt(norm)
        if not (math.isfinite(norm) and norm > 0.0):
            return None
        w = [x / norm for x in w]
        moved = 0.0
        for i in range(m):
            moved = max(moved, abs(w[i] - v[i]))
        v = w
        if moved < 1e-14:
            break
    gains = []
    for row in rows:
        acc = 0.0
        for i in range(m):
            acc += row[i] * v[i]
        gains.append(acc)
    shape = StaticMap(v, dyn.poly_scale)
    if dyn.rbf is not None and gains[0] != 0.0:
        # The paper model's RBF layer acts on lag 1 only: N carries it, scaled by 1/g_1.
        shape = StaticMap(v, dyn.poly_scale, dyn.rbf, dyn.rbf_weights, 1.0 / gains[0])
    slope = (shape.value(u_hi) - shape.value(u_lo)) / (u_hi - u_lo)
    if not (math.isfinite(slope) and abs(slope) > 1e-12):
        return None
    poly = [x / slope for x in v]
    gains = [g * slope for g in gains]
    if dyn.rbf is not None and gains[0] != 0.0:
        return gains, StaticMap(poly, dyn.poly_scale, dyn.rbf, dyn.rbf_weights, 1.0 / gains[0])
    return gains, StaticMap(poly, dyn.poly_scale)


def monotone_range(shape: StaticMap, lo: float, hi: float, points: int = 64) -> tuple[float, float]:
    """The widest interval of [lo, hi] around its middle on which N rises (N is scaled to a
    mean slope of +1, so a rising map is the invertible one); [lo, hi] when N does not rise
    at the middle (nothing better is known)."""
    step = (hi - lo) / points
    mid = points // 2
    if not shape.derivative(lo + mid * step) > 0.0:
        return lo, hi
    a = mid
    while a > 0 and shape.derivative(lo + (a - 1) * step) > 0.0:
        a -= 1
    b = mid
    while b < points and shape.derivative(lo + (b + 1) * step) > 0.0:
        b += 1
    return lo + a * step, lo + b * step


def _reachable(u0: float, reach: float, lo: float, hi: float) -> tuple[float, float]:
    """The inputs within ``reach`` of ``u0`` inside [lo, hi]; when none is (``u0`` outside
    [lo, hi] by more than ``reach``), the one point ``reach`` towards it."""
    a = max(lo, u0 - reach)
    b = min(hi, u0 + reach)
    if a <= b:
        return a, b
    p = u0 + reach if u0 < lo else u0 - reach
    return p, p


def _solve_linear(a: list[list[float]], b: list[float]) -> list[float] | None:
    """x with a·x = b by Gaussian elimination with partial pivoting (a and b are
    consumed); None when a is singular to working precision."""
    k = len(b)
    for col in range(k):
        piv = col
        for r in range(col + 1, k):
            if abs(a[r][col]) > abs(a[piv][col]):
                piv = r
        if not abs(a[piv][col]) > 1e-300:
            return None
        if piv != col:
            a[col], a[piv] = a[piv], a[col]
            b[col], b[piv] = b[piv], b[col]
        pivot_row = a[col]
        for r in range(col + 1, k):
            row = a[r]
            factor = row[col] / pivot_row[col]
            if factor != 0.0:
                for c in range(col, k):
                    row[c] -= factor * pivot_row[c]
                b[r] -= factor * b[col]
    x = [0.0] * k
    for r in range(k - 1, -1, -1):
        acc = b[r]
        row = a[r]
        for c in range(r + 1, k):
            acc -= row[c] * x[c]
        x[r] = acc / row[r]
    return x


def _solve_box_qp(
    h: list[list[float]],
    f: list[float],
    lo: list[float],
    hi: list[float],
    warm: list[int] | None = None,
) -> tuple[list[float], list[int]]:
    """argmin ½ xᵀHx + fᵀx over lo ≤ x ≤ hi (H symmetric positive definite): a primal
    active-set method (Nocedal & Wright, §16.5) from the centre of the box. Each
    iteration solves for the free variables, steps until a bound blocks, and releases
    the bound whose multiplier has the wrong sign once no step is left; finite, exact to
    rounding, deterministic. Returns the best point reached if the iteration limit hits,
    and the working set (0 free, −1 at lo, +1 at hi): given back as ``warm`` on the next
    sample, the last plan's active bounds, it usually leaves one or two iterations."""
    n = len(f)
    state = [0] * n
    if warm is not None and len(warm) == n:
        state = list(warm)
    x = [lo[i] if state[i] < 0 else hi[i] if state[i] > 0 else 0.5 * (lo[i] + hi[i])
         for i in range(n)]  # fmt: skip
    for _ in range(8 * n + 8):
        grad = [0.0] * n
        for i in range(n):
            acc = f[i]
            row = h[i]
            for j in range(n):
                acc += row[j] * x[j]
            grad[i] = acc
        free = [i for i in range(n) if state[i] == 0]
        step = [0.0] * n
        moved = False
        if free:
            sol = _solve_linear(
                [[h[i][j] for j in free] for i in free], [-grad[i] for i in free]
            )
            if sol is None:
                return x, state
            for r in range(len(free)):
                step[free[r]] = sol[r]
            scale = 0.0
            for i in range(n):
                scale = max(scale, abs(x[i]), hi[i] - lo[i])
            moved = any(abs(v) > 1e-14 * (1.0 + scale) for v in step)
        if moved:
            alpha = 1.0
            block = -1
            for i in free:
                v = step[i]
                if v < 0.0 and x[i] + v < lo[i]:
                    t = (lo[i] - x[i]) / v
                    if t < alpha:
                        alpha, block = t, i
                elif v > 0.0 and x[i] + v > hi[i]:
                    t = (hi[i] - x[i]) / v
                    if t < alpha:
                        alpha, block = t, i
            for i in free:
                x[i] += alpha * step[i]
            if block >= 0:
                if step[block] < 0.0:
                    x[block], state[block] = lo[block], -1
                else:
                    x[block], state[block] = hi[block], 1
            continue
        # No step left on this face: release the bound that most wants to move inward.
        worst = -1
        worst_value = 0.0
        for i in range(n):
            # At lo the gradient must be ≥ 0, at hi ≤ 0 (multipliers of the right sign).
            g = grad[i] if state[i] == -1 else -grad[i] if state[i] == 1 else 0.0
            if g < worst_value:
                worst, worst_value = i, g
        if worst < 0:
            return x, state
        state[worst] = 0
    return x, state


class PredictiveInverse:
    """The controller state of one channel: horizons, the plan's fixed matrices (derived
    again every ``refresh`` samples) and the disturbance estimate."""

    __slots__ = (
        "_age",
        "_columns",
        "_disturbance",
        "_free_ar",
        "_free_impulse",
        "_free_step",
        "_hessian",
        "_horizon",
        "_onset",
        "_plan_model",
        "_plan_state",
        "_points",
        "_range",
        "_rho",
        "_shape",
        "_sim",
        "_starts",
        "rate",
        "settings",
        "u_max",
        "u_min",
    )

    def __init__(
        self, u_min: float, u_max: float, rate: float, settings: PredictiveSettings | None = None
    ) -> None:
        if not (math.isfinite(u_min) and math.isfinite(u_max) and u_min < u_max):
            raise ValueError("need finite u_min < u_max")
        if not (math.isfinite(rate) and rate > 0.0):
            raise ValueError("rate must be finite and > 0")
        self.u_min = float(u_min)
        self.u_max = float(u_max)
        self.rate = float(rate)
        self.settings = settings or PredictiveSettings()
        self._horizon = 0
        self._age = 0
        self._disturbance = 0.0
        self._points: list[int] = []  # cost points j (ŷ(k+j))
        self._columns: list[list[float]] = []  # per point: effect of each block's level
        self._onset: list[float] = []  # per point: s(j − 1), the held input's step
        self._hessian: list[list[float]] = []
        # The free response in closed form at the cost points (see ``_free_response``):
        # the AR part it was derived for, S_A(j) and h_A(j − l) for l = 1 … L.
        self._free_ar: list[float] = []
        self._free_step: list[float] = []
        self._free_impulse: list[list[float]] = []
        self._rho = 0.0
        self._shape: StaticMap | None = None  # the input map N the plan was derived with
        self._range = (self.u_min, self.u_max)  # where N rises (see ``monotone_range``)
        self._starts: list[int] = []  # first sample of each input block
        self._plan_state: list[int] | None = None  # the last plan's active bounds
        self._plan_model: ModelDynamics | None = None  # the model of the last derivation
        self._sim: list[float] | None = None  # internal model's outputs y_m(k), y_m(k−1), …

    @property
    def horizon(self) -> int:
        return self._horizon

    @property
    def disturbance(self) -> float:
        return self._disturbance

    def reset(self) -> None:
        """Forget the internal model and the disturbance (after a gap in the telemetry)."""
        self._disturbance = 0.0
        self._sim = None
        self._plan_state = None

    def track(self, dyn: ModelDynamics, y: float) -> None:
        """Advance the internal model by the sample whose output ``y`` the identifier has
        just learnt from (``dyn`` is the model after that step), and the disturbance
        estimate d ← d + α·(y − y_m − d), α = 1/(1 + disturbance_share·horizon).

        The internal model runs on its own outputs and the applied inputs (internal model
        control): the prediction carries the measured output's departure from it as a
        constant, so tracking is offset-free whatever the model's error at steady state.
        It restarts from the measured outputs when it has none or stops being finite.
        """
        na = len(dyn.ar)
        sim = self._sim
        if sim is None or len(sim) != na or not math.isfinite(y):
            self._sim = list(dyn.outputs[:na])
            return
        y_m = dyn.one_step(sim)
        if not math.isfinite(y_m) or not math.isfinite(y - y_m):
            self._sim = list(dyn.outputs[:na])
            self._disturbance = 0.0
            return
        if na:
            sim.pop()
            sim.insert(0, y_m)
        self._age += 1
        horizon = self.horizon_for(dyn)
        alpha = 1.0 / (1.0 + self.settings.disturbance_share * horizon)
        self._disturbance += alpha * (y - y_m - self._disturbance)

    def horizon_for(self, dyn: ModelDynamics) -> int:
        """The prediction horizon of these dynamics (derived now if never derived), e.g.
        for the health report's multi-step accuracy before control starts; 0 when the
        model has no usable input map yet."""
        stale = self._horizon == 0 or self._age >= self.settings.refresh
        if stale and dyn.is_finite():
            factors = factorise(dyn, self.u_min, self.u_max)
            if factors is not None:
                self._derive(dyn, factors[0])
                self._shape = factors[1]
                self._range = monotone_range(factors[1], self.u_min, self.u_max)
        return self._horizon

    def _derive(self, dyn: ModelDynamics, gains: list[float]) -> None:
        """Horizon, blocks, cost points, their columns and the Hessian, from the
        identified linear part: they change as slowly as the model does. The model's
        coefficients are kept (``_plan_model``): until the next derivation the free
        response is this model's, so that the whole prediction is one model's."""
        ar = dyn.ar
        self._plan_model = ModelDynamics(
            list(ar),
            dyn.bias,
            [list(poly) for poly in dyn.lag_polys],
            dyn.poly_scale,
            [],
            [],
            dyn.rbf,
            dyn.rbf_weights,
        )
        s = self.settings
        response = step_response(ar, gains, s.max_horizon)
        n = settling_horizon(response, s.band, s.min_horizon, s.max_horizon)
        starts = block_starts(n, s.max_blocks)
        stride = max(1, -(-n // s.cost_points))
        points, weights = cost_points(n, stride, starts, cost_start(response, n))
        columns, onset, hessian = plan_matrices(response, starts, points, weights)
        rho = add_move_penalty(hessian, s.move_weight)
        self._free_ar = list(ar)
        self._free_step, self._free_impulse = free_response_terms(ar, len(gains), n, points)
        self._horizon = n
        self._points = points
        self._columns = columns
        self._onset = onset
        self._hessian = hessian
        self._rho = rho
        self._starts = starts
        self._age = 0

    def _free_response(self, dyn: ModelDynamics, u_now: float, outputs: list[float]) -> list[float]:
        """ŷ(k+j) at the cost points j with the input held at ``u_now``, from ``outputs``
        (newest first), in closed form: y(k+j) = E·S_A(j) + Σ_{l=1..L} h_A(j − l)·d(l),
        where E is the constant forcing once every input lag sees the held input and d(l)
        the departure from it at the first L samples: the forcing's own (older inputs)
        plus the past outputs' share Σ_{i≥l} c_i·y(k+l−i). The same numbers as running
        the recursion over the horizon (``ModelDynamics.simulate_held``; tested), in
        points × (L + 1) operations instead of horizon × (na + 1)."""
        ar = self._free_ar
        na = len(ar)
        impulses = self._free_impulse
        lead = len(impulses[0]) if impulses else 0
        terms, constant = dyn.input_forcing(u_now, lead)
        departures = [terms[d] - constant for d in range(lead)]
        for step in range(1, min(lead, na) + 1):
            acc = 0.0
            for i in range(step, na + 1):
                index = i - step
                if index < len(outputs):
                    acc += ar[i - 1] * outputs[index]
            departures[step - 1] += acc
        free: list[float] = []
        steps = self._free_step
        for p in range(len(impulses)):
            acc = constant * steps[p]
            row = impulses[p]
            for d in range(lead):
                acc += row[d] * departures[d]
            free.append(acc)
        return free

    def decide(
        self, dyn: ModelDynamics, u_applied: float, setpoint: float
    ) -> tuple[float, str, bool]:
        """(next input, path, saturated): path "newton"/"fallback" is the inverse step's,
        "hold" means the plan could not be made (the applied input is kept)."""
        lo_u, hi_u = self.u_min, self.u_max
        u0 = u_applied if math.isfinite(u_applied) else 0.5 * (lo_u + hi_u)
        u0 = lo_u if u0 < lo_u else hi_u if u0 > hi_u else u0
        if not (math.isfinite(setpoint) and dyn.is_finite()):
            return u0, "hold", False
        # The factorisation, horizons and plan matrices change as slowly as the model:
        # derived again every ``refresh`` samples, the same N for the plan and the inverse.
        shape = self._shape
        if shape is None or self._horizon == 0 or self._age >= self.settings.refresh:
            factors = factorise(dyn, lo_u, hi_u)
            if factors is None:
                return u0, "hold", False
            self._derive(dyn, factors[0])
            shape = self._shape = factors[1]
            self._range = monotone_range(shape, lo_u, hi_u)
        # Plan only where the identified map rises: a polynomial fitted on the inputs seen
        # can turn over beyond them, and there a larger level needs a *smaller* input, so
        # the plan's bounds and the inverse trap the input at a limit (measured on the
        # ArduSub test: pitch held at −2 against a positive gain, 0.5 rad off).
        lo_u, hi_u = self._range
        sim = self._sim
        if sim is None or len(sim) != len(dyn.ar):
            sim = list(dyn.outputs[: len(dyn.ar)])
        # The free response plus the output disturbance estimate. The free response is the
        # model of the last derivation's (its coefficients, today's input history, from the
        # internal model's outputs), as the block columns are: the current model's input
        # forcing run through the AR part of an older one predicts a steady state that
        # drifts as the identifier trades bias, input polynomial and AR coefficients in
        # closed loop (measured: a saw tooth of period ``refresh``, 3.8x the oracle's IAE
        # on a random plant with a dead zone; docs/control.md).
        plan_model = self._plan_model
        if plan_model is None:
            return u0, "hold", False
        plan_model.inputs = dyn.inputs
        plan_model.outputs = dyn.outputs
        free = self._free_response(plan_model, u0, sim)
        disturbance = self._disturbance
        w0 = shape.value(u0)
        nblocks = len(self._hessian)
        f = [0.0] * nblocks
        columns = self._columns
        onset = self._onset
        points = self._points
        for p in range(len(points)):
            resid = free[p] + disturbance - w0 * onset[p] - setpoint
            col = columns[p]
            for b in range(nblocks):
                f[b] += col[b] * resid
        f[0] -= self._rho * w0
        # Each block's level within what the actuator can reach by the block's start
        # (amplitude, and the rate limit from the applied input), in the map's units.
        lo: list[float] = []
        hi: list[float] = []
        for start in self._starts:
            a_u, b_u = _reachable(u0, self.rate * start, lo_u, hi_u)
            a_w = shape.value(a_u)
            b_w = shape.value(b_u)
            lo.append(min(a_w, b_w))
            hi.append(max(a_w, b_w))
        first_lo, first_hi = _reachable(u0, self.rate, lo_u, hi_u)
        for value in f:
            if not math.isfinite(value):
                return u0, "hold", False
        plan, self._plan_state = _solve_box_qp(self._hessian, f, lo, hi, self._plan_state)
        target = plan[0]
        if not math.isfinite(target):
            return u0, "hold", False
        if not first_lo < first_hi:
            # Outside the rising range by more than a step: the one reachable input towards
            # it (``_reachable``), nothing to solve.
            return first_lo, "fallback", first_lo <= self.u_min or first_lo >= self.u_max
        # The inverse step: the input whose static map gives the planned level.
        result = solve_inverse(shape.value, shape.derivative, target, u0, first_lo, first_hi)
        u = result.u
        if not math.isfinite(u):
            return u0, "hold", False
        saturated = u <= self.u_min or u >= self.u_max
        return u, result.path, saturated
