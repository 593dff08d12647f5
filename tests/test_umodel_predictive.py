"""The predictive U-model inverse: its pieces, its guards, and a plant it was not tuned on."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from hil_service.umodel import build_model
from hil_service.umodel.box_qp import flat_matrix, solve_box_qp
from hil_service.umodel.dynamics import ModelDynamics
from hil_service.umodel.finite import all_finite, finite
from hil_service.umodel.horizon import arrival_time, free_response_terms
from hil_service.umodel.predictive import (
    PredictiveInverse,
    factorise,
    settling_horizon,
    step_response,
)
from hil_service.umodel.residual_forecast import ResidualForecast


def test_step_response_of_a_first_order_lag() -> None:
    # y(t) = 0.5 y(t−1) + 2 w(t−1): s(j) = 4·(1 − 0.5^j)
    s = step_response([0.5], [2.0], 6)
    assert list(s) == pytest.approx([4.0 * (1.0 - 0.5**j) for j in range(6)])


def test_settling_horizon_follows_the_pole() -> None:
    fast = settling_horizon(step_response([0.5], [1.0], 400), 0.05, 2, 400)
    slow = settling_horizon(step_response([0.98], [1.0], 400), 0.05, 2, 400)
    assert fast == 5  # 0.5^5 < 0.05 < 0.5^4
    assert 140 <= slow <= 150  # 0.98^148 ≈ 0.05
    unstable = settling_horizon(step_response([1.01], [1.0], 400), 0.05, 2, 400)
    assert unstable == 400


def test_arrival_time_is_short_where_a_lightly_damped_response_rings() -> None:
    # Poles 0.95·e^(±0.3i): the response reaches its level in a few samples and rings
    # about it for ~50; settling counts the ringing, arrival does not.
    r, w = 0.95, 0.3
    ringing = step_response([2 * r * math.cos(w), -r * r], [1.0], 400)
    settled = settling_horizon(ringing, 0.05, 2, 400)
    arrived = arrival_time(ringing, 0.05, 2, 400)
    assert arrived <= 20 < 50 <= settled
    # A monotone response arrives when it settles.
    smooth = step_response([0.9], [1.0], 400)
    assert arrival_time(smooth, 0.05, 2, 400) == settling_horizon(smooth, 0.05, 2, 400)


def test_factorise_recovers_a_hammerstein_map() -> None:
    shape = [0.8, 0.0, 0.15]  # N(x) = 0.8x + 0.15x³
    gains = [0.3, -0.2, 0.05]
    dyn = ModelDynamics([0.6], 0.0, [[g * c for c in shape] for g in gains], 0.5, [0.0], [0.0, 0.0])
    factors = factorise(dyn, -2.0, 2.0)
    assert factors is not None
    g, n = factors
    # P_L(u) = g_L·N(u) for every lag and input, whatever scale N was given.
    for lag, u in itertools.product(range(1, 4), (-1.7, -0.2, 0.9, 2.0)):
        assert g[lag - 1] * n.value(u) == pytest.approx(dyn.lag_value(lag, u), abs=1e-12)
    # N is scaled to a mean slope of one over the actuator range.
    assert (n.value(2.0) - n.value(-2.0)) / 4.0 == pytest.approx(1.0)


def test_factorise_keeps_the_models_steady_state_where_the_lags_differ_in_shape() -> None:
    # Lags of different shapes (a Wiener plant's U-model): the fast lag bends one way, the
    # slow lags the other. Σ_L P_L(u) = 0.6u + 0.075u³ rises everywhere; the best rank-one
    # fit of the coefficients (the dominant singular pair) gives a map that falls towards
    # both limits and a steady state 0.5 off there.
    polys = [[-1.0, 0.0, 0.6], [0.9, 0.0, -0.3], [0.7, 0.0, -0.15]]
    dyn = ModelDynamics([0.5], 0.0, polys, 0.5, [0.0], [0.0, 0.0])
    factors = factorise(dyn, -2.0, 2.0)
    assert factors is not None
    g, n = factors
    for u in (-2.0, -1.1, -0.3, 0.0, 0.4, 1.3, 2.0):
        steady = sum(dyn.lag_value(lag, u) for lag in range(1, 4))
        assert sum(g) * n.value(u) == pytest.approx(steady, abs=1e-12)
        assert n.derivative(u) > 0.0  # rising where the model's steady state rises


def test_factorise_refuses_a_model_without_input_effect() -> None:
    dyn = ModelDynamics([0.9], 0.0, [[0.0, 0.0], [0.0, 0.0]], 1.0, [1.0], [0.0])
    assert factorise(dyn, -2.0, 2.0) is None


@pytest.mark.parametrize("seed", range(6))
def test_box_qp_is_the_minimum_over_the_box(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(3, 3))
    h = (a @ a.T + 0.1 * np.eye(3)).tolist()
    f = rng.normal(size=3).tolist()
    lo, hi = [-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]
    flat = flat_matrix(h)
    x, state = solve_box_qp(flat, f, lo, hi)
    assert solve_box_qp(flat, f, lo, hi, state)[0] == pytest.approx(x)  # warm start
    assert solve_box_qp(flat, f, lo, hi, [1, -1, 1])[0] == pytest.approx(x)  # a wrong one
    assert all(lo[i] - 1e-12 <= x[i] <= hi[i] + 1e-12 for i in range(3))

    def cost(v: np.ndarray) -> float:
        return float(0.5 * v @ np.array(h) @ v + np.array(f) @ v)

    grid = np.stack(np.meshgrid(*[np.linspace(lo[i], hi[i], 41) for i in range(3)]), -1).reshape(
        -1, 3
    )
    assert cost(np.array(x)) <= min(cost(v) for v in grid) + 1e-9


def _dynamics(ar: list[float], polys: list[list[float]], y: float) -> ModelDynamics:
    return ModelDynamics(ar, 0.0, polys, 0.5, [y] * len(ar), [0.0] * (len(polys) - 1))


EDGES = [0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
         -1.7976931348623157e308, 1.0, -3.5, math.inf, -math.inf, math.nan]  # fmt: skip


@pytest.mark.parametrize("x", EDGES)
def test_finite_agrees_with_math_isfinite(x: float) -> None:
    assert finite(x) is math.isfinite(x)
    assert all_finite([1.0, x, -2.0]) is math.isfinite(x)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_model_is_finite_only_when_every_coefficient_and_history_value_is(bad: float) -> None:
    def dyn() -> ModelDynamics:
        return ModelDynamics([0.5, 0.1], 0.2, [[1.0, -0.1], [0.5, 0.0]], 0.5, [1.0, 1e300], [-3.0])

    assert dyn().is_finite()
    for part in ("ar", "outputs", "inputs", "lag_polys"):
        broken = dyn()
        values = getattr(broken, part)
        (values[-1] if part == "lag_polys" else values)[-1] = bad
        assert not broken.is_finite(), part
    broken = dyn()
    broken.bias = bad
    assert not broken.is_finite()


@pytest.mark.parametrize(
    "dyn",
    [
        _dynamics([math.nan], [[1.0], [0.5]], 0.0),
        _dynamics([0.9], [[0.0], [0.0]], 0.0),
        _dynamics([0.9], [[1e308], [-1e308]], 1e308),
    ],
    ids=["nan", "no-input-effect", "overflow"],
)
def test_guards_give_a_finite_command(dyn: ModelDynamics) -> None:
    controller = PredictiveInverse(-2.0, 2.0, 0.5)
    for setpoint in (1.0, math.nan, 1e300):
        u, path, _ = controller.decide(dyn, 0.3, setpoint)
        assert math.isfinite(u) and -2.0 <= u <= 2.0
        assert path in ("newton", "fallback", "hold")


def test_first_move_respects_amplitude_and_rate() -> None:
    controller = PredictiveInverse(-2.0, 2.0, 0.5)
    dyn = _dynamics([0.8], [[1.0, 0.0, 0.1]], 0.0)
    u, _, _ = controller.decide(dyn, 1.9, 100.0)  # far above: wants the upper limit
    assert u == pytest.approx(2.0)
    u, _, _ = controller.decide(dyn, 1.9, -100.0)  # far below: one rate step down
    assert u == pytest.approx(1.4)


def test_a_plan_held_at_a_limit_is_saturated_to_within_rounding() -> None:
    # An actuator that reached its limit by rate steps sits an ulp inside it: the plan's
    # first block at its bound map(−2) is met there, and the command counts as saturated,
    # or the supervisor's saturation test never sees a plan pinned at the limit.
    controller = PredictiveInverse(-2.0, 2.0, 0.5)
    dyn = _dynamics([0.8], [[1.0, 0.0, 0.1]], 0.0)
    inside = -2.0 + 4.0 * 2.0**-52
    assert inside > -2.0
    u, _, saturated = controller.decide(dyn, inside, -100.0)  # far below: the lower limit
    assert u == pytest.approx(-2.0, abs=1e-12)
    assert saturated
    u, _, saturated = controller.decide(dyn, 0.0, 0.0)  # well inside: not saturated
    assert not saturated


class _Hammerstein:
    """A plant unlike the emulator's: second order, a cubic pump with a dead zone, another
    gain and time scale. y(t) = 1.6 y(t−1) − 0.64 y(t−2) + 0.05·f(u(t−1)) + 0.03·f(u(t−2))."""

    def __init__(self) -> None:
        self.y = [0.0, 0.0]
        self.u = [0.0, 0.0]

    @staticmethod
    def pump(u: float) -> float:
        return math.copysign(max(abs(u) - 0.1, 0.0), u) + 0.2 * u**3

    def step(self, u: float) -> float:
        y = (
            1.6 * self.y[0]
            - 0.64 * self.y[1]
            + 0.05 * self.pump(self.u[0])
            + 0.03 * self.pump(self.u[1])
        )
        self.y = [y, self.y[0]]
        self.u = [u, self.u[0]]
        return y


def test_tracks_a_plant_it_was_not_tuned_on() -> None:
    plant = _Hammerstein()
    model = build_model("dynamic")
    controller = PredictiveInverse(-2.0, 2.0, 0.5)
    rng = np.random.default_rng(3)
    u_prev = u = 0.0
    errors = []
    for k in range(3000):
        y = plant.step(u)
        model.step(u_prev, y)
        u_prev = u
        if k < 1500:
            if k % 40 == 0:
                u = float(rng.uniform(-2.0, 2.0))
            continue
        controller.track(model.dynamics(), y)
        setpoint = 1.5 if (k // 300) % 2 else -1.0
        u, _, _ = controller.decide(model.dynamics(), u_prev, setpoint)
        errors.append(abs(y - setpoint))
    # Every 300-sample step ends within 2 % of the step size, and no command is non-finite.
    for start in range(0, len(errors), 300):
        assert max(errors[start + 250 : start + 300]) < 0.02 * 2.5


def _free_response(
    controller: PredictiveInverse, dyn: ModelDynamics, u_now: float, outputs: list[float]
) -> list[float]:
    """ŷ(k+j) at the controller's cost points with the input held at ``u_now``, from its
    closed form E·S_A(j) + Σ_l h_A(j − l)·d(l) (``PredictiveInverse._forcing``)."""
    constant, departures = controller._forcing(dyn, u_now, outputs)
    points = controller._points
    steps, impulses = free_response_terms(
        controller._free_ar, len(dyn.lag_polys), max(points) + 1, points
    )
    return [
        constant * step + sum(row[d] * departures[d] for d in range(len(departures)))
        for step, row in zip(steps, impulses, strict=True)
    ]


def _derived(
    na: int, nb: int, seed: int
) -> tuple[np.random.Generator, ModelDynamics, PredictiveInverse]:
    """A random stable model with ``na`` output and ``nb`` input lags, and a controller
    whose plan is derived for it."""
    rng = np.random.default_rng(seed)
    ar = (0.9 * rng.uniform(-1, 1, na) / na).tolist()
    polys = rng.normal(size=(nb, 3)).tolist()
    dyn = ModelDynamics(ar, 0.7, polys, 0.5, rng.normal(size=na).tolist(),
                        rng.uniform(-2, 2, nb).tolist())  # fmt: skip
    controller = PredictiveInverse(-2.0, 2.0, 0.5)
    controller._derive(dyn, [1.0] * nb)
    return rng, dyn, controller


@pytest.mark.parametrize(("na", "nb"), [(1, 1), (2, 4), (4, 4), (4, 2)])
def test_closed_form_free_response_equals_running_the_recursion(na: int, nb: int) -> None:
    rng, dyn, controller = _derived(na, nb, na * 10 + nb)
    sim = rng.normal(size=na).tolist()
    fast = _free_response(controller, dyn, 0.4, sim)
    slow = dyn.simulate_held(0.4, max(controller._points), 0.0, sim)  # the cost's span
    assert fast == pytest.approx([slow[j - 1] for j in controller._points], rel=1e-9, abs=1e-9)


@pytest.mark.parametrize(("na", "nb"), [(1, 1), (2, 4), (4, 4), (4, 2)])
def test_the_linear_term_is_the_columns_against_the_predicted_error(na: int, nb: int) -> None:
    # The QP's linear term from parts projected once per derivation equals the sum over
    # the cost points of each point's column times its predicted error (free response +
    # disturbance − the applied level's onset − setpoint), with the move penalty's pull.
    rng, dyn, controller = _derived(na, nb, na * 10 + nb + 1)
    controller._sim = rng.normal(size=na).tolist()
    controller._disturbance = 0.3
    plan = ModelDynamics(dyn.ar, dyn.bias, dyn.lag_polys, dyn.poly_scale, [], [])
    f = controller._linear_term(dyn, plan, 0.4, 0.25, 1.7)
    free = _free_response(controller, plan, 0.4, controller._sim)
    expected = [0.0] * len(f)
    blocks = len(f)
    for p in range(len(controller._onset)):
        error = free[p] + 0.3 - 0.25 * controller._onset[p] - 1.7
        for b in range(blocks):
            expected[b] += controller._columns[p * blocks + b] * error
    expected[0] -= controller._rho * 0.25
    assert f == pytest.approx(expected, rel=1e-9, abs=1e-9 * max(map(abs, expected)))


@pytest.mark.parametrize(("na", "nb"), [(1, 1), (2, 4), (4, 2)])
def test_the_forecasts_cached_projection_is_the_forecast_at_each_point(na: int, nb: int) -> None:
    # With the disturbance forecast trusted, each cost point's predicted error carries the
    # forecast x̂(k+j) = u(j)·x(k) + v(j)·x(k−1) on top of the level; the linear term gets it
    # from projections made once per derivation and trusted lead. Equal to projecting the
    # forecast at each point directly, on the sample the projections are made and on later
    # ones that reuse them with new departures.
    rng, dyn, controller = _derived(na, nb, na * 10 + nb + 2)
    forecast = ResidualForecast()
    controller._forecast = forecast
    points = controller._points
    period = 37.0
    for k in range(1000):
        if k % 50 == 0:
            forecast.hold(points)
        value = math.sin(2.0 * math.pi * k / period)
        forecast.observe(value, 0.0, 0.0)
    forecast.hold(points)
    assert forecast.confident(controller.settings.disturbance_forecast)
    trusted = forecast.trusted_lead()
    assert trusted > 1
    controller._sim = rng.normal(size=na).tolist()
    controller._disturbance = 0.3
    plan = ModelDynamics(dyn.ar, dyn.bias, dyn.lag_polys, dyn.poly_scale, [], [])
    for k in range(1000, 1003):
        f = controller._linear_term(dyn, plan, 0.4, 0.25, 1.7)
        free = _free_response(controller, plan, 0.4, controller._sim)
        x1, x2 = forecast.state()
        us, vs = forecast.weights(points, trusted)
        blocks = len(f)
        expected = [0.0] * blocks
        for p in range(len(points)):
            ahead = us[p] * x1 + vs[p] * x2
            assert (ahead != 0.0) == (points[p] <= trusted)
            error = free[p] + 0.3 + ahead - 0.25 * controller._onset[p] - 1.7
            for b in range(blocks):
                expected[b] += controller._columns[p * blocks + b] * error
        expected[0] -= controller._rho * 0.25
        assert f == pytest.approx(expected, rel=1e-9, abs=1e-9 * max(map(abs, expected)))
        forecast.observe(math.sin(2.0 * math.pi * k / period), 0.0, 0.0)
        assert forecast.trusted_lead() == trusted


def _estimate(residuals: list[float], horizon: int = 5) -> list[float]:
    """The disturbance estimate after each residual, at the pace a ``horizon`` gives."""
    controller = PredictiveInverse(-2.0, 2.0, 0.5)
    alpha = 1.0 / (1.0 + controller.settings.disturbance_share * horizon)
    out = []
    for r in residuals:
        controller._estimate_disturbance(r, alpha)
        out.append(controller.disturbance)
    return out


def test_the_disturbance_estimate_averages_a_white_residual_and_follows_a_wandering_one() -> None:
    rng = np.random.default_rng(3)
    white = rng.standard_normal(2000)
    # At the horizon's pace (α = 1/3.5) the estimate of white noise has a variance of
    # α/(2 − α) = 0.17: planning on it adds that to the output's. Averaged, far less.
    late = np.array(_estimate(list(white))[1000:])
    assert float(np.var(late)) < 0.02
    # A random walk seen through white noise of a tenth of its step: the estimate keeps up.
    walk = np.cumsum(rng.standard_normal(2000)) + 0.1 * rng.standard_normal(2000)
    followed = np.array(_estimate(list(walk)))
    assert float(np.sqrt(np.mean((followed[1:] - walk[:-1]) ** 2))) < 1.5
    # A step in a noise-free residual (a model error at a new level) is followed at the
    # horizon's pace, the fastest candidate.
    stepped = _estimate([0.0] * 50 + [1.0] * 50)
    assert stepped[-1] == pytest.approx(1.0 - (1.0 - 1.0 / 3.5) ** 50)


def test_a_non_minimum_phase_plant_settles_on_the_setpoints_side() -> None:
    # The random family's seed 29 depth plant (lockstep campaigns): poles 0.757 and 0.631,
    # a zero at 1.09, DC gain 0.71, a 2 s period. Its step response starts at −0.71 per
    # unit and ends at +0.71, and settles within the 20-sample horizon. A cost ending at
    # the horizon sees only the last blocks' wrong-way start: the plan moves the output
    # through them and holds a first block whose steady state lies on the far side of the
    # setpoint (0.83 m off a 0.8 m step, three trips, 14 × reference-only).
    from plant_emulator.random_plants import draw_family
    from tests.harm_rig import Loop, spec

    depth, _ = draw_family(29, 1)[0]
    assert depth.zero is not None and depth.zero > 1.0
    loop = Loop(depth, spec(period=depth.period))
    loop.run(1200, {"depth": None, "pitch": None})
    for setpoint in (15.8, 14.5, 15.4):
        start = len(loop.y)
        loop.run(600, {"depth": setpoint, "pitch": None})
        mean_error = sum(abs(y - setpoint) for y in loop.y[start:]) / 600
        assert mean_error < 0.1 and abs(loop.y[-1] - setpoint) < 0.01, (setpoint, mean_error)
    assert loop.pipeline.channels["depth"].supervisor.trips == 0


@pytest.mark.parametrize("phase", [0, 20, 70])
def test_the_phase_brings_the_second_derivation_forward(phase: int) -> None:
    """A service's vehicles that started together re-derive their plans on different
    samples: the first derivation counts as ``phase`` samples old (modulo the refresh)."""
    slow = _dynamics([0.9], [[1.0], [0.5]], 0.0)
    fast = _dynamics([0.5], [[1.0], [0.5]], 0.0)
    controller = PredictiveInverse(-2.0, 2.0, 0.5, phase=phase)
    refresh = controller.settings.refresh
    controller.track(slow, 0.0)  # starts the internal model
    controller.track(slow, 0.0)  # the first derivation, on the slow model
    first = controller.horizon
    samples = 0
    while controller.horizon == first and samples <= refresh:
        controller.track(fast, 0.0)
        samples += 1
    assert controller.horizon < first
    assert samples == refresh - phase % refresh


def _ringing_and_smooth() -> tuple[ModelDynamics, ModelDynamics]:
    """A response that arrives within a few samples and rings for hundreds (poles
    0.995·e^(±0.3i) beside a fast one), and a smooth one that settles in about 150."""
    r, w = 0.995, 0.3
    a1, a2 = 2 * r * math.cos(w), -r * r
    ringing = [a1 + 0.2, a2 - 0.2 * a1, -0.2 * a2]  # (1 − 0.2 q⁻¹)(1 − a1 q⁻¹ − a2 q⁻²)
    shape = [1.0, 0.0, 0.0]
    ring = ModelDynamics(ringing, 0.0, [shape], 0.5, [0.0] * 3, [0.0])
    smooth = ModelDynamics([0.98], 0.0, [shape], 0.5, [0.0], [0.0])
    return ring, smooth


def test_the_horizon_is_at_most_four_arrival_times_of_the_response() -> None:
    # The plan's horizon is the step response's settling time, at most four times its
    # arrival time (``PredictiveSettings.horizon_arrivals``): a response that arrives fast
    # and rings for long is planned over a few arrivals, a smooth one over its settling.
    from hil_service.umodel.predictive import PredictiveSettings

    ring, smooth = _ringing_and_smooth()
    capped = PredictiveInverse(-2.0, 2.0, 0.5)
    uncapped = PredictiveInverse(-2.0, 2.0, 0.5, PredictiveSettings(horizon_arrivals=0.0))
    response = step_response(ring.ar, [1.0], 1000)
    settled = settling_horizon(response, 0.05, 5, 1000)
    arrived = arrival_time(response, 0.05, 5, 1000)
    assert 4 * arrived < settled
    assert uncapped.horizon_for(ring) == settled
    assert capped.horizon_for(ring) == 4 * arrived
    slow = PredictiveInverse(-2.0, 2.0, 0.5)
    assert slow.horizon_for(smooth) == settling_horizon(
        step_response([0.98], [1.0], 1000), 0.05, 5, 1000
    )
    with pytest.raises(ValueError):
        PredictiveSettings(horizon_arrivals=0.5)
