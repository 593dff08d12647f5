"""Predictive U-model inverse: the next input from an optimisation over a horizon.

At every sample the identified U-model gives its multi-step map (:class:`.ModelDynamics`):
linear in past outputs, a polynomial of each input lag. The controller

1. reads the lag polynomials as one static input map times a linear filter (w = N(u),
   y = G(q)·w: a rank-one factorisation of the lag × power coefficient matrix, exact for
   a Hammerstein plant; the model's steady-state map where that one rises over more of
   the range, ``factorise``);
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
   where the response to a move peaks the wrong way (``cost_start``), sees every
   sample of the blocks shorter than its stride (``cost_points``), and runs to twice the
   horizon, so that it sees the last block's response settle too (a cost ending with
   the blocks would see only the wrong-way start of a non-minimum-phase plant's last
   blocks, and the plan could use them to move the output while its first block settles
   on the far side of the setpoint);
4. root-solves N(u) = w for the first block (the U-model inverse step, with the solver's
   fallback where there is no real root).

Offset-free tracking (internal model control): an internal copy of the model runs on its
own outputs and the applied inputs; the measured output's departure from it, low-passed
with a time constant of a share of the response time (``disturbance_share``; the
horizon, or the step response's arrival time when that is shorter: a lightly damped plant
settles long after it arrives, and the residual's level is known once it has), is the
output disturbance, held constant over the horizon. A slow estimate on purpose: a
non-minimum-phase plant answers a fast correction with its wrong-way response. Slower
still where that departure is noise: of that pace and 2 … 64 times slower, the estimate
that has predicted the departure best is used (``track``), so a white residual is averaged
rather than fed back.

Guards: non-finite model coefficients, a degenerate input map or a non-finite plan give
"hold" (the applied input), never an exception or a non-finite command.

One module over 500 lines: the plan's tracking state, its disturbance estimate and the
decision read and change the same per-channel state on every sample, and are compiled
together; the horizon, the box QP and the root solver are modules of their own.
"""

from __future__ import annotations

import math

from librt.vecs import vec

from .box_qp import solve_box_qp
from .dynamics import ModelDynamics, StaticMap
from .finite import finite
from .horizon import (
    LinearTerm,
    add_move_penalty,
    arrival_time,
    block_starts,
    cost_points,
    cost_start,
    free_response_terms,
    lead_of,
    plan_matrices,
    project,
    settling_horizon,
    step_response,
)
from .inverse import solve_inverse
from .residual_forecast import ResidualForecast

__all__ = [
    "PredictiveInverse",
    "PredictiveSettings",
    "block_starts",
    "cost_points",
    "cost_start",
    "factorise",
    "monotone_range",
    "settling_horizon",
    "step_response",
]

#: Power-iteration sweeps of the rank-one factorisation (a 3×3 symmetric matrix).
_POWER_SWEEPS = 30

#: An input this share of the actuator's range from a limit is at the limit (``_at_limit``).
LIMIT_TOLERANCE = 1e-9

#: The disturbance estimate's candidate paces: the horizon's (``disturbance_share``) and
#: 2, 4, … 2^(n−1) times slower (see ``PredictiveInverse.track``).
DISTURBANCE_PACES = 7


class PredictiveSettings:
    """Scale-free constants of the predictive inverse (no plant's figure among them)."""

    __slots__ = (
        "band",
        "cancel_near_pairs",
        "cost_points",
        "disturbance_forecast",
        "disturbance_share",
        "horizon_arrivals",
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
        disturbance_forecast: float = 0.25,
        horizon_arrivals: float = 4.0,
        cancel_near_pairs: bool = True,
    ) -> None:
        if not 2 <= min_horizon <= max_horizon:
            raise ValueError("need 2 <= min_horizon <= max_horizon")
        if not 0.0 < band < 1.0:
            raise ValueError("band must be in (0, 1)")
        if max_blocks < 2:
            raise ValueError("max_blocks must be >= 2")
        if not (finite(move_weight) and move_weight >= 0.0):
            raise ValueError("move_weight must be finite and >= 0")
        if not (finite(disturbance_share) and disturbance_share > 0.0):
            raise ValueError("disturbance_share must be finite and > 0")
        if refresh < 1:
            raise ValueError("refresh must be >= 1")
        if cost_points < 1:
            raise ValueError("cost_points must be >= 1")
        if not (finite(disturbance_forecast) and 0.0 <= disturbance_forecast <= 1.0):
            raise ValueError("disturbance_forecast must be in [0, 1]")
        if not (finite(horizon_arrivals) and (horizon_arrivals == 0.0 or horizon_arrivals >= 1.0)):
            raise ValueError("horizon_arrivals must be 0 (no cap) or finite and >= 1")
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
        #: Plan with a forecast of the disturbance over the horizon (``residual_forecast``)
        #: while its one-step errors' mean square is below this share of the level's, as
        #: far ahead as it has beaten the level; 0: never (the level held over the horizon).
        self.disturbance_forecast = float(disturbance_forecast)
        #: The horizon at most this many arrival times of the step response (0: the
        #: settling time alone). A response that arrives in T samples and then rings for
        #: far longer is, on the plants measured (docs/control.md, "A horizon of a few
        #: arrival times"), a disturbance's oscillation the identifier has put in its AR
        #: part, and a plan over that ring trades the next samples for a far future.
        self.horizon_arrivals = float(horizon_arrivals)
        #: Where the record shows the identified G's near pole–zero pairs wrong
        #: (``PredictiveInverse.reduced``), the arrival time is taken from G without them
        #: (``cancellation.reduced_model``): a disturbance's mode in the AR part that nearly
        #: cancels against a zero (docs/control.md, "Near pole–zero cancellations").
        self.cancel_near_pairs = bool(cancel_near_pairs)


def _steady_state_direction(rows: list[list[float]], m: int) -> list[float] | None:
    """The unit direction of Σ_L P_L's coefficients; None when the lags cancel there (its
    norm below 10⁻⁶ of the lags' own)."""
    total = [0.0] * m
    size = 0.0
    for row in rows:
        for i in range(m):
            total[i] += row[i]
            size += row[i] * row[i]
    norm = 0.0
    for x in total:
        norm += x * x
    norm = math.sqrt(norm)
    if not (finite(norm) and norm > 1e-6 * math.sqrt(size)):
        return None
    return [x / norm for x in total]


def _dominant_direction(rows: list[list[float]], m: int) -> list[float] | None:
    """The dominant right singular vector of the lag × power matrix: ΘᵀΘ (m × m), then its
    dominant eigenvector by power iteration from e_1."""
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
        if not (finite(norm) and norm > 0.0):
            return None
        w = [x / norm for x in w]
        moved = 0.0
        for i in range(m):
            moved = max(moved, abs(w[i] - v[i]))
        v = w
        if moved < 1e-14:
            break
    return v


def _rising_share(shape: StaticMap, u_lo: float, u_hi: float) -> float:
    """The share of 64 equal steps across [u_lo, u_hi] over which ``shape`` moves the way
    of its mean slope."""
    step = (u_hi - u_lo) / 64
    before = shape.value(u_lo)
    sign = 1.0 if shape.value(u_hi) >= before else -1.0
    rising = 0
    for i in range(1, 65):
        after = shape.value(u_lo + i * step)
        if sign * (after - before) > 0.0:
            rising += 1
        before = after
    return rising / 64


def factorise(dyn: ModelDynamics, u_lo: float, u_hi: float) -> tuple[list[float], StaticMap] | None:
    """Lag gains g_L and the static map N with P_L(u) ≈ g_L·N(u); N scaled to a mean slope
    of one over [u_lo, u_hi]. None when the map is degenerate (no input effect yet).

    N is the dominant singular pair of the lag × power matrix (the best rank-one fit of
    the coefficients), g_L each lag's projection on it: exact for a Hammerstein model.
    A model whose lags differ in shape (a Wiener plant's) can have a best rank-one map
    that falls where the model's own steady-state map, Σ_L P_L, rises: the plan then
    needs a smaller input for a larger level and drives the input to a limit. N is then
    the direction of Σ_L P_L instead (with it Σ_L g_L·N = Σ_L P_L: the factorised model
    settles where the model does), when that map rises over more of the range. Not
    always: where the AR part is near an integrator the lags nearly cancel at steady
    state, and Σ_L P_L is left with their noise in the higher powers (docs/control.md,
    "The input map N")."""
    polys = dyn.lag_polys
    m = 0
    for poly in polys:
        m = max(m, len(poly))
    if m == 0:
        return None
    rows = [poly + [0.0] * (m - len(poly)) for poly in polys]
    v = _dominant_direction(rows, m)
    if v is None:
        return None
    if dyn.rbf is None and len(rows) > 1:
        steady = _steady_state_direction(rows, m)
        if steady is not None and _rising_share(
            StaticMap(steady, dyn.poly_scale), u_lo, u_hi
        ) > _rising_share(StaticMap(v, dyn.poly_scale), u_lo, u_hi):
            v = steady
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
    if not (finite(slope) and abs(slope) > 1e-12):
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


class PredictiveInverse:
    """The controller state of one channel: horizons, the plan's fixed matrices (derived
    again every ``refresh`` samples) and the disturbance estimate."""

    __slots__ = (
        "_age",
        "_columns",
        "_disturbance",
        "_estimates",
        "_forecast",
        "_forecast_lead",
        "_forecast_u",
        "_forecast_v",
        "_free_ar",
        "_hessian",
        "_horizon",
        "_lead",
        "_linear",
        "_onset",
        "_phase",
        "_plan_model",
        "_plan_state",
        "_points",
        "_range",
        "_response_time",
        "_rho",
        "_scores",
        "_shape",
        "_sim",
        "_starts",
        "rate",
        "reduced",
        "settings",
        "u_max",
        "u_min",
    )

    def __init__(
        self,
        u_min: float,
        u_max: float,
        rate: float,
        settings: PredictiveSettings | None = None,
        phase: int = 0,
    ) -> None:
        """``phase``: the first derivation counts as ``phase`` samples old, so that the
        next comes that much sooner; a service gives its vehicles different phases, so
        that a fleet that started together does not derive all its plans on one sample."""
        if not (finite(u_min) and finite(u_max) and u_min < u_max):
            raise ValueError("need finite u_min < u_max")
        if not (finite(rate) and rate > 0.0):
            raise ValueError("rate must be finite and > 0")
        self.u_min = float(u_min)
        self.u_max = float(u_max)
        self.rate = float(rate)
        self.settings = settings or PredictiveSettings()
        #: G's step response without the near pole–zero pairs that the record contradicts,
        #: from the channel's last verdict on them (``ChannelPipeline``); None: G whole.
        #: Where set, its arrival time, not G's, sets the horizon's cap, the disturbance
        #: estimate's pace and the cost's start.
        self.reduced: vec[float] | None = None
        self._horizon = 0
        # The disturbance estimate's time scale: the shorter of the horizon and the step
        # response's arrival time (``arrival_time``), derived with the horizon.
        self._response_time = 0
        self._age = 0
        self._phase = max(int(phase), 0)  # taken by the first derivation only
        self._disturbance = 0.0
        # One estimate per candidate pace and the squared errors with which each, held
        # from the sample before, predicted the residual since the internal model started.
        self._estimates = [0.0] * DISTURBANCE_PACES
        self._scores = [0.0] * DISTURBANCE_PACES
        self._forecast: ResidualForecast | None = (
            ResidualForecast() if self.settings.disturbance_forecast > 0.0 else None
        )
        # The held forecast's weights projected on the columns (``_linear_term``), for the
        # trusted lead they were projected with (-1: none since the last derivation).
        self._forecast_lead = -1
        self._forecast_u: list[float] = []
        self._forecast_v: list[float] = []
        self._points: list[int] = []  # cost points j (ŷ(k+j))
        #: Per cost point, each block's (weighted) effect on it: points × blocks, row-major.
        self._columns = vec[float]()
        self._onset: list[float] = []  # per point: s(j − 1), the held input's step
        self._hessian = vec[float]()  # the QP's, blocks × blocks, row-major
        # The free response in closed form at the cost points (see ``_forcing``): the AR
        # part it was derived for; S_A(j) and h_A(j − l) enter only through ``_linear``.
        self._free_ar: list[float] = []
        self._lead = 0  # L, the number of departures d(l)
        # The linear term's parts, the columns projected once per derivation: Σ_p col_p
        # times S_A(j_p), times each h_A(j_p − l), times 1 and times the onset.
        self._linear = LinearTerm([], [], [], [])
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
        self._forget_disturbance()
        self._sim = None
        self._plan_state = None

    def track(self, dyn: ModelDynamics, y: float) -> None:
        """Advance the internal model by the sample whose output ``y`` the identifier has
        just learnt from (``dyn`` is the model after that step), and the disturbance
        estimate (``_estimate_disturbance``).

        The internal model runs on its own outputs and the applied inputs (internal model
        control): the prediction carries the measured output's departure from it as a
        constant, so tracking is offset-free whatever the model's error at steady state.
        It restarts from the measured outputs when it has none or stops being finite.
        """
        na = len(dyn.ar)
        sim = self._sim
        if sim is None or len(sim) != na or not finite(y):
            self._sim = list(dyn.outputs[:na])
            if self._forecast is not None:
                self._forecast.skip()
            return
        y_m = dyn.one_step(sim)
        if not finite(y_m) or not finite(y - y_m):
            self._sim = list(dyn.outputs[:na])
            self._forget_disturbance()
            return
        if na:
            sim.pop()
            sim.insert(0, y_m)
        self._age += 1
        self.horizon_for(dyn)  # derives the response time again when it is due
        share = self.settings.disturbance_share
        residual = y - y_m
        previous = self._disturbance
        self._estimate_disturbance(residual, 1.0 / (1.0 + share * self._response_time))
        if self._forecast is not None:
            self._forecast.observe(residual, self._disturbance, previous)

    def coast(self, dyn: ModelDynamics) -> None:
        """Advance the internal model by a sample whose output was lost (``dyn`` holds the
        input that produced it): on its own outputs, as ever; the disturbance estimate,
        with nothing measured, holds, and so does the forecast's fit (its lead checks move
        on by the sample)."""
        if self._forecast is not None:
            self._forecast.skip()
        na = len(dyn.ar)
        sim = self._sim
        if sim is None or len(sim) != na:
            return  # the next ``track`` starts it from the history
        y_m = dyn.one_step(sim)
        if not finite(y_m):
            self._sim = None
            return
        if na:
            sim.pop()
            sim.insert(0, y_m)
        self._age += 1

    def _estimate_disturbance(self, residual: float, alpha: float) -> None:
        """The output disturbance: the residual y − y_m low-passed, d ← d + α·(y − y_m − d),
        at the pace that has predicted the residual best.

        Candidates: α = 1/(1 + disturbance_share·min(horizon, arrival time)) and 2, 4, …
        times slower. Each is scored by the squared error with which its estimate, held from
        the sample before, predicted this residual (summed since the internal model
        started); the lowest score wins, the fastest on a tie. The estimate is the
        residual's predicted level over the horizon, so the pace that predicts it best is
        the one to plan with: a residual that wanders (a current, a model error at a new
        level) is followed at the horizon's pace, a white one (noise the model cannot
        predict) is averaged, and correcting it, which only adds the estimate's own noise to
        the output's, stops. For a random walk plus white noise every horizon ranks the
        paces alike (the k-step error is the one-step error plus the walk's k − 1 steps)."""
        estimates = self._estimates
        scores = self._scores
        best = 0
        for i in range(len(estimates)):
            error = residual - estimates[i]
            scores[i] += error * error
            estimates[i] += alpha * error
            alpha *= 0.5
            if scores[i] < scores[best]:
                best = i
        self._disturbance = estimates[best]

    def _forget_disturbance(self) -> None:
        if self._forecast is not None:
            self._forecast = ResidualForecast()
            self._forecast.hold(self._points)
            self._forecast_lead = -1
        self._disturbance = 0.0
        for i in range(len(self._estimates)):
            self._estimates[i] = 0.0
            self._scores[i] = 0.0

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
        arrival = arrival_time(response, s.band, s.min_horizon, s.max_horizon)
        shown = response
        reduced = self.reduced
        if s.cancel_near_pairs and reduced is not None:
            shown = reduced
            arrival = arrival_time(shown, s.band, s.min_horizon, s.max_horizon)
        if s.horizon_arrivals > 0.0:
            n = min(n, max(s.min_horizon, int(s.horizon_arrivals * arrival)))
        starts = block_starts(n, s.max_blocks)
        span = min(2 * n, s.max_horizon)
        stride = max(1, -(-span // s.cost_points))
        points, weights = cost_points(span, stride, starts, cost_start(shown, n))
        columns, onset, hessian = plan_matrices(response, starts, points, weights)
        nblocks = len(starts)
        rho = add_move_penalty(hessian, nblocks, s.move_weight)
        self._free_ar = list(ar)
        free_step, free_impulse = free_response_terms(ar, len(gains), span, points)
        self._lead = lead_of(free_impulse)
        self._linear = LinearTerm(
            project(columns, nblocks, free_step),
            [
                project(columns, nblocks, [row[d] for row in free_impulse])
                for d in range(self._lead)
            ],
            project(columns, nblocks, [1.0] * len(points)),
            project(columns, nblocks, onset),
        )
        self._horizon = n
        self._response_time = min(n, arrival)
        self._points = points
        if self._forecast is not None:
            self._forecast.hold(points)
        self._forecast_lead = -1
        self._columns = columns
        self._onset = onset
        self._hessian = hessian
        self._rho = rho
        self._starts = starts
        self._age = self._phase % max(s.refresh, 1)
        self._phase = 0

    def _forcing(
        self, dyn: ModelDynamics, u_now: float, outputs: list[float]
    ) -> tuple[float, list[float]]:
        """The free response's inputs. With the input held at ``u_now``, ŷ(k+j) at the cost
        points is, in closed form, E·S_A(j) + Σ_{l=1..L} h_A(j − l)·d(l): E, the constant
        forcing once every input lag sees the held input, and d(l), the departure from it
        at the first L samples, the forcing's own (older inputs) plus the past outputs'
        share Σ_{i≥l} c_i·y(k+l−i), from ``outputs`` (newest first). The same numbers as
        running the recursion over the horizon (``ModelDynamics.simulate_held``; tested),
        in points × (L + 1) operations instead of horizon × (na + 1)."""
        ar = self._free_ar
        na = len(ar)
        lead = self._lead
        terms, constant = dyn.input_forcing(u_now, lead)
        departures = [terms[d] - constant for d in range(lead)]
        for step in range(1, min(lead, na) + 1):
            acc = 0.0
            for i in range(step, na + 1):
                index = i - step
                if index < len(outputs):
                    acc += ar[i - 1] * outputs[index]
            departures[step - 1] += acc
        return constant, departures

    def decide(
        self, dyn: ModelDynamics, u_applied: float, setpoint: float
    ) -> tuple[float, str, bool]:
        """(next input, path, saturated): path "newton"/"fallback" is the inverse step's,
        "hold" means the plan could not be made (the applied input is kept)."""
        lo_u, hi_u = self.u_min, self.u_max
        u0 = u_applied if finite(u_applied) else 0.5 * (lo_u + hi_u)
        u0 = lo_u if u0 < lo_u else hi_u if u0 > hi_u else u0
        if not (finite(setpoint) and dyn.is_finite()):
            return u0, "hold", False
        shape = self._current_shape(dyn)
        plan_model = self._plan_model
        if shape is None or plan_model is None:
            return u0, "hold", False
        # Plan only where the identified map rises: a polynomial fitted on the inputs seen
        # can turn over beyond them, and there a larger level needs a *smaller* input, so
        # the plan's bounds and the inverse trap the input at a limit (measured on the
        # ArduSub test: pitch held at −2 against a positive gain, 0.5 rad off).
        lo_u, hi_u = self._range
        w0 = shape.value(u0)
        f = self._linear_term(dyn, plan_model, u0, w0, setpoint)
        for value in f:
            if not finite(value):
                return u0, "hold", False
        lo, hi = self._block_bounds(shape, u0, lo_u, hi_u)
        plan, self._plan_state = solve_box_qp(self._hessian, f, lo, hi, self._plan_state)
        target = plan[0]
        if not finite(target):
            return u0, "hold", False
        return self._inverse_step(shape, target, u0, lo_u, hi_u)

    def _current_shape(self, dyn: ModelDynamics) -> StaticMap | None:
        """The input map N of the plan, derived again (with the horizons and the plan
        matrices) every ``refresh`` samples: they change as slowly as the model, and the
        plan and the inverse use the same N. None when the map is degenerate."""
        shape = self._shape
        if shape is None or self._horizon == 0 or self._age >= self.settings.refresh:
            factors = factorise(dyn, self.u_min, self.u_max)
            if factors is None:
                return None
            self._derive(dyn, factors[0])
            shape = self._shape = factors[1]
            self._range = monotone_range(shape, self.u_min, self.u_max)
        return shape

    def _linear_term(
        self,
        dyn: ModelDynamics,
        plan_model: ModelDynamics,
        u0: float,
        w0: float,
        setpoint: float,
    ) -> list[float]:
        """The QP's linear term: the blocks' columns against the predicted error with the
        input held at ``u0`` (free response + disturbance estimate − setpoint), and the
        move penalty's pull towards the applied level ``w0``.

        The free response is the model of the last derivation's (its coefficients, today's
        input history, from the internal model's outputs), as the block columns are: the
        current model's input forcing run through the AR part of an older one predicts a
        steady state that drifts as the identifier trades bias, input polynomial and AR
        coefficients in closed loop (measured: a saw tooth of period ``refresh``, 3.8x the
        oracle's IAE on a random plant with a dead zone; docs/control.md)."""
        sim = self._sim
        if sim is None or len(sim) != len(dyn.ar):
            sim = list(dyn.outputs[: len(dyn.ar)])
        plan_model.inputs = dyn.inputs
        plan_model.outputs = dyn.outputs
        # Σ_p col_p·(free_p + disturbance − w0·onset_p − setpoint), with the free response
        # E·S_A(j) + Σ_l h_A(j − l)·d(l) (``_forcing``): each part's projection on the
        # columns is fixed between derivations (``LinearTerm``), so a sample costs blocks ×
        # (L + 3) operations, not points × (L + blocks).
        constant, departures = self._forcing(plan_model, u0, sim)
        linear = self._linear
        level = self._disturbance - setpoint
        step, ones, onset = linear.step, linear.ones, linear.onset
        forecast = self._forecast
        if forecast is not None and forecast.confident(self.settings.disturbance_forecast):
            # The disturbance forecast at each cost point on top of the level:
            # x̂(k+j) = u(j)·x(k) + v(j)·x(k−1), whose projections are fixed while the
            # coefficients and the trusted lead are.
            trusted = forecast.trusted_lead()
            if trusted != self._forecast_lead:
                u, v = forecast.weights(self._points, trusted)
                self._forecast_u = project(self._columns, len(step), u)
                self._forecast_v = project(self._columns, len(step), v)
                self._forecast_lead = trusted
            x1, x2 = forecast.state()
            pu, pv = self._forecast_u, self._forecast_v
            f = [
                constant * step[b] + level * ones[b] + x1 * pu[b] + x2 * pv[b] - w0 * onset[b]
                for b in range(len(step))
            ]
        else:
            f = [constant * step[b] + level * ones[b] - w0 * onset[b] for b in range(len(step))]
        for d in range(len(departures)):
            row = linear.impulses[d]
            departure = departures[d]
            for b in range(len(f)):
                f[b] += row[b] * departure
        f[0] -= self._rho * w0
        return f

    def _block_bounds(
        self, shape: StaticMap, u0: float, lo_u: float, hi_u: float
    ) -> tuple[list[float], list[float]]:
        """Each block's level within what the actuator can reach by the block's start
        (amplitude, and the rate limit from the applied input), in the map's units."""
        lo: list[float] = []
        hi: list[float] = []
        for start in self._starts:
            a_u, b_u = _reachable(u0, self.rate * start, lo_u, hi_u)
            a_w = shape.value(a_u)
            b_w = shape.value(b_u)
            lo.append(min(a_w, b_w))
            hi.append(max(a_w, b_w))
        return lo, hi

    def _inverse_step(
        self, shape: StaticMap, target: float, u0: float, lo_u: float, hi_u: float
    ) -> tuple[float, str, bool]:
        """The input whose static map gives the planned first level ``target``, within a
        rate step of ``u0``: (input, path, saturated)."""
        first_lo, first_hi = _reachable(u0, self.rate, lo_u, hi_u)
        if not first_lo < first_hi:
            # Outside the rising range by more than a step: the one reachable input towards
            # it (``_reachable``), nothing to solve.
            return first_lo, "fallback", self._at_limit(first_lo)
        result = solve_inverse(shape.value, shape.derivative, target, u0, first_lo, first_hi)
        u = result.u
        if not finite(u):
            return u0, "hold", False
        return u, result.path, self._at_limit(u)

    def _at_limit(self, u: float) -> bool:
        """Whether ``u`` is at an actuator limit. To within rounding: a plan held at its
        bound, map(limit), is inverted to within the map's last bits of the limit, and an
        input an ulp inside it is as saturated as the limit itself."""
        tolerance = LIMIT_TOLERANCE * (self.u_max - self.u_min)
        return u <= self.u_min + tolerance or u >= self.u_max - tolerance
