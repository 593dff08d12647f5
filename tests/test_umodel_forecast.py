"""H-step forecast of hil_service.umodel.forecast against a step-by-step simulation."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from hil_service.umodel import build_model
from hil_service.umodel.forecast import HorizonMap, forecast_model
from hil_service.umodel.reproducible import row_sum


def trained(name: str, seed: int = 3, n: int = 400) -> object:
    """A model with a non-trivial history and weights (random steps through a 2nd-order plant)."""
    model = build_model(name, seed=seed, init_scale=0.2)
    rng = np.random.default_rng(seed)
    y1 = y2 = u1 = 0.0
    for k in range(n):
        u = float(rng.uniform(-2.0, 2.0)) if k % 7 == 0 else u1
        y = 1.5 * y1 - 0.7 * y2 + 0.2 * u1 + 0.1 * u1**3
        model.step(u1, y)  # type: ignore[attr-defined]
        y2, y1, u1 = y1, y, u
    return model


def simulated(make: Callable[[], object], u_applied: float, u: float, horizon: int) -> float:
    """ŷ(k+H) by running a copy of the model (``make`` trains it again: the same seed gives
    the same model) forward on its own predictions."""
    sim = make()
    y_hat = math.nan
    for j in range(horizon):
        u_prev = u_applied if j == 0 else u
        y_hat = sim.predict(u_prev)  # type: ignore[attr-defined]
        assert sim.observe_only(u_prev, y_hat)  # type: ignore[attr-defined]
    return y_hat


@pytest.mark.parametrize("name", ["dynamic", "paper"])
@pytest.mark.parametrize("horizon", [2, 3, 5, 6, 20, 150])
def test_forecast_equals_step_by_step_simulation(name: str, horizon: int) -> None:
    model = trained(name)
    u_applied = 0.37
    forecast = forecast_model(model, u_applied, horizon)
    assert isinstance(forecast, HorizonMap)
    for u in (-2.0, -1.3, -0.2, 0.0, 0.37, 0.81, 1.6, 2.0):
        expected = simulated(lambda: trained(name), u_applied, u, horizon)
        got = forecast.value(u)
        assert got == pytest.approx(expected, rel=1e-12, abs=1e-12 * (1.0 + abs(expected)))


@pytest.mark.parametrize("name", ["dynamic", "paper"])
def test_forecast_derivative_and_grid_agree_with_the_scalar_value(name: str) -> None:
    model = trained(name, seed=5)
    forecast = forecast_model(model, -0.4, 20)
    h = 1e-6
    for u in (-1.7, -0.5, 0.3, 1.2):
        fd = (forecast.value(u + h) - forecast.value(u - h)) / (2 * h)
        assert forecast.derivative(u) == pytest.approx(fd, rel=1e-6, abs=1e-8)
    grid = np.linspace(-2.0, 2.0, 101)
    grid.flags.writeable = False
    vec = forecast.values(grid)
    scalar = [forecast.value(u) for u in grid.tolist()]
    assert np.allclose(vec, scalar, rtol=1e-12, atol=1e-12)
    assert np.array_equal(forecast.values(grid), vec)  # cached design gives the same bits


def test_forecast_rejects_short_horizon_and_unknown_models() -> None:
    with pytest.raises(ValueError):
        forecast_model(build_model("dynamic"), 0.0, 1)
    with pytest.raises(TypeError):
        forecast_model(build_model("persistence"), 0.0, 5)


def halving_sum(rows: list[list[float]]) -> list[float]:
    """Plain-Python statement of ``row_sum``'s order: the bits are fixed by the shape."""
    level = rows
    while len(level) > 1:
        half = len(level) // 2
        nxt = [[a + b for a, b in zip(level[i], level[half + i], strict=True)] for i in range(half)]
        if len(level) % 2:
            nxt[0] = [a + b for a, b in zip(nxt[0], level[-1], strict=True)]
        level = nxt
    return level[0]


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7, 20, 33])
def test_row_sum_is_the_documented_halving_order(n: int) -> None:
    rows = np.random.default_rng(n).normal(size=(n, 11))
    got = row_sum(rows)
    assert np.allclose(got, rows.sum(axis=0), rtol=1e-13, atol=1e-13)
    assert got.tolist() == halving_sum([r.tolist() for r in rows])
    assert not np.shares_memory(got, rows)  # a fresh array, never a view of the input


@pytest.mark.parametrize("name", ["dynamic", "paper"])
def test_forecast_grid_gives_the_same_bits_as_plain_python(name: str) -> None:
    """The fallback grid of the forecast uses element-wise IEEE operations only (no numpy
    exp/power, no BLAS): written out in plain Python it gives the same bits."""
    model = trained(name, seed=4)
    forecast = forecast_model(model, 0.6, 20)
    grid = np.linspace(-2.0, 2.0, 101)
    grid.flags.writeable = False
    got = forecast.values(grid).tolist()
    k = 1.0 / (model.rbf.beta * model.rbf.beta)  # type: ignore[attr-defined]
    coefficients = [forecast.rbf_gain * w for w in forecast._weights] + list(forecast.poly)
    products = []
    for u in grid.tolist():
        column = [math.exp(-(u - c) * (u - c) * k) for c in model.rbf.centres]  # type: ignore[attr-defined]
        x, p = u * model.poly_scale, 1.0  # type: ignore[attr-defined]
        for _ in forecast.poly:
            p *= x
            column.append(p)
        products.append([c * v for c, v in zip(coefficients, column, strict=True)])
    rows = [list(r) for r in zip(*products, strict=True)]
    expected = [t + forecast.offset for t in halving_sum(rows)]
    assert got == expected


@pytest.mark.parametrize("name", ["dynamic", "paper"])
def test_forecast_curvature_matches_finite_differences(name: str) -> None:
    model = trained(name, seed=7)
    forecast = forecast_model(model, 0.9, 20)
    h = 1e-5
    for u in (-1.9, -0.6, 0.05, 0.7, 1.8):
        fd = (forecast.derivative(u + h) - forecast.derivative(u - h)) / (2 * h)
        assert forecast.curvature(u) == pytest.approx(fd, rel=1e-5, abs=1e-6)


def test_curvature_pass_remembers_the_same_bits_as_evaluate() -> None:
    model = trained("dynamic", seed=11)
    first = forecast_model(model, 0.2, 20)
    second = forecast_model(model, 0.2, 20)
    for u in (-1.3, 0.1, 1.7):
        first.curvature(u)  # fills value and slope from the three-sum pass
        assert first.evaluate(u) == second.evaluate(u)


@pytest.mark.parametrize("horizon", [20, 150])
def test_newton_solves_a_reachable_forecast_target(horizon: int) -> None:
    """A target the forecast reaches (its value at some u in range) is met on the Newton path."""
    from hil_service.umodel import solve_inverse

    model = trained("dynamic", seed=2)
    forecast = forecast_model(model, 0.0, horizon)
    for u_true, u0 in [(0.35, 0.3), (-0.8, -0.6), (1.2, 1.0)]:
        target = forecast.value(u_true)
        res = solve_inverse(
            forecast.value,
            forecast.derivative,
            target,
            u0,
            -2.0,
            2.0,
            f_vec=forecast.values,
            d2f=forecast.curvature,
        )
        assert res.path == "newton"
        assert abs(res.residual) <= 1e-9 * max(1.0, abs(target))


def test_overflowing_forecast_never_gives_a_nan_command() -> None:
    """An explosive identified AR part overflows ŷ(k+150): the solver still returns a finite
    input on the fallback path with an infinite residual, never NaN."""
    from hil_service.umodel import solve_inverse

    model = trained("dynamic", seed=6)
    theta = model._theta  # type: ignore[attr-defined]
    theta[model._np + 1] = 1e5  # a_1 huge: the output recursion grows without bound  # type: ignore[attr-defined]
    forecast = forecast_model(model, 0.1, 150)
    res = solve_inverse(
        forecast.value,
        forecast.derivative,
        0.5,
        0.2,
        -2.0,
        2.0,
        f_vec=forecast.values,
        d2f=forecast.curvature,
    )
    assert math.isfinite(res.u) and -2.0 <= res.u <= 2.0
    assert not math.isnan(res.residual)
    assert res.path == "fallback"


def test_short_horizon_step_response_has_lfilter_bits() -> None:
    """Short horizons skip scipy; the Python loop must give lfilter's bits exactly, or a
    log recorded with one path would not replay with the other."""
    from scipy.signal import lfilter

    from hil_service.umodel.forecast import SHORT_HORIZON, _short_step_response

    rng = np.random.default_rng(11)
    for _ in range(3000):
        order = int(rng.integers(1, 8))
        horizon = int(rng.integers(1, SHORT_HORIZON + 1))
        ar = (rng.normal(0, 0.5, size=order) * rng.choice([1e-3, 0.3, 1.0])).tolist()
        reference = lfilter(np.ones(1), np.array([1.0, *[-c for c in ar]]), np.ones(horizon))
        assert _short_step_response(ar, horizon) == reference.tolist()
