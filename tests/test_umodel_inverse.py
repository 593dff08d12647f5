"""Inverse solver and command shaping of hil_service.umodel."""

from __future__ import annotations

import math

import pytest

from hil_service.umodel import (
    CommandShaper,
    InverseResult,
    solve_inverse,
)


def quad(u: float) -> float:  # (u − 0.5)(u + 1.5)
    return (u - 0.5) * (u + 1.5)


def dquad(u: float) -> float:
    return 2.0 * u + 1.0


@pytest.mark.parametrize(("u0", "root"), [(0.2, 0.5), (1.7, 0.5), (-1.0, -1.5), (-1.9, -1.5)])
def test_newton_finds_known_roots_from_nearby_start(u0: float, root: float) -> None:
    res = solve_inverse(quad, dquad, 0.0, u0, -2.0, 2.0)
    assert isinstance(res, InverseResult)
    assert res.path == "newton"
    assert res.u == pytest.approx(root, abs=1e-9)
    assert abs(res.residual) <= 1e-9
    assert not res.saturated
    assert 1 <= res.iterations <= 8


def test_newton_on_cubic_with_nonzero_target() -> None:
    f = lambda u: (u - 0.5) * (u + 1.5) * (u - 1.0)  # noqa: E731
    df = lambda u: 3 * u * u - 1.75  # noqa: E731  d/du of u³ − 1.75u + 0.75
    res = solve_inverse(f, df, 0.75, 0.1, -2.0, 2.0)  # u³ − 1.75u = 0 → u = 0 nearest
    assert res.path == "newton"
    assert res.u == pytest.approx(0.0, abs=1e-9)


def test_start_already_on_target_takes_no_iteration() -> None:
    res = solve_inverse(quad, dquad, 0.0, 0.5, -2.0, 2.0)
    assert (res.path, res.iterations, res.u) == ("newton", 0, 0.5)


def test_no_real_root_falls_back_to_minimiser() -> None:
    # u² + 1 = 0 has no real root: the best achievable is the minimum of u² + 1 at u = 0.
    res = solve_inverse(lambda u: u * u + 1.0, lambda u: 2.0 * u, 0.0, 0.7, -2.0, 2.0)
    assert res.path == "fallback"
    assert res.u == pytest.approx(0.0, abs=1e-6)
    assert res.residual == pytest.approx(1.0, abs=1e-9)
    assert not res.saturated


def test_zero_slope_at_start_falls_back_deterministically() -> None:
    # u² = 1 from u0 = 0 where f'(0) = 0: Newton cannot move; both roots are equally near,
    # the fallback picks the lower one, every time.
    results = {solve_inverse(lambda u: u * u, lambda u: 2.0 * u, 1.0, 0.0, -2.0, 2.0)}
    results.add(solve_inverse(lambda u: u * u, lambda u: 2.0 * u, 1.0, 0.0, -2.0, 2.0))
    assert len(results) == 1
    res = results.pop()
    assert res.path == "fallback"
    assert res.u == pytest.approx(-1.0, abs=1e-9)
    assert abs(res.residual) <= 1e-9


def test_newton_cycle_falls_back_to_the_real_root() -> None:
    # Classic 2-cycle of Newton on u³ − 2u + 2 from u0 = 0 (0 → 1 → 0 …); the root is −1.769…
    f = lambda u: u**3 - 2 * u + 2  # noqa: E731
    df = lambda u: 3 * u**2 - 2  # noqa: E731
    res = solve_inverse(f, df, 0.0, 0.0, -2.0, 2.0)
    assert res.path == "fallback"
    assert res.u == pytest.approx(-1.7692923542386314, abs=1e-9)
    assert abs(res.residual) <= 1e-9


def test_unreachable_target_saturates_at_bound() -> None:
    res = solve_inverse(lambda u: 2.0 * u, lambda u: 2.0, 10.0, 0.3, -2.0, 2.0)
    assert res.path == "fallback"
    assert res.u == 2.0
    assert res.residual == pytest.approx(-6.0)
    assert res.saturated
    low = solve_inverse(lambda u: 2.0 * u, lambda u: 2.0, -10.0, 0.3, -2.0, 2.0)
    assert (low.u, low.saturated) == (-2.0, True)


def test_flat_function_keeps_previous_input() -> None:
    res = solve_inverse(lambda u: 3.0, lambda u: 0.0, 1.0, 0.42, -2.0, 2.0)
    assert res.path == "fallback"
    assert res.u == 0.42
    assert res.residual == pytest.approx(2.0)


def test_non_finite_inputs_never_produce_nan() -> None:
    res = solve_inverse(quad, dquad, math.nan, 5.0, -2.0, 2.0)
    assert res.u == 2.0 and res.path == "fallback" and not math.isnan(res.residual)
    res = solve_inverse(quad, dquad, 0.0, math.nan, -2.0, 2.0)
    assert math.isfinite(res.u) and abs(res.residual) <= 1e-9
    with pytest.raises(ValueError):
        solve_inverse(quad, dquad, 0.0, 0.0, 1.0, -1.0)


def test_command_shaper_rate_limit_and_saturation() -> None:
    sh = CommandShaper(-1.0, 1.0, max_rate=0.3, u_init=0.0)
    out = sh.shape(0.2)
    assert (out.u, out.saturated, out.rate_limited) == (0.2, False, False)
    out = sh.shape(5.0)
    assert out.u == pytest.approx(0.5) and out.saturated and out.rate_limited
    out = sh.shape(5.0)
    assert out.u == pytest.approx(0.8) and out.saturated and out.rate_limited
    out = sh.shape(5.0)
    assert out.u == 1.0 and out.saturated and not out.rate_limited
    out = sh.shape(math.nan)
    assert out.u == 1.0 and not out.saturated
    sh.reset(3.0)
    assert sh.u == 1.0
    unlimited = CommandShaper(-1.0, 1.0)
    assert unlimited.shape(-0.9).u == -0.9
    with pytest.raises(ValueError):
        CommandShaper(1.0, 1.0)


def _wavy(u: float) -> float:  # interior extrema, e.g. a maximum near u = 0.52
    return math.sin(3.0 * u) + 0.2 * u


def _dwavy(u: float) -> float:
    return 3.0 * math.cos(3.0 * u) + 0.2


@pytest.mark.parametrize("u0", [-1.7, -0.3, 0.4, 0.52, 0.9, 1.95])
def test_unreachable_target_above_a_local_maximum_gives_that_maximum(u0: float) -> None:
    """Out-of-reach target above the interior maximum: the fallback's answer is the
    stationary point (Illinois regula falsi on f') wherever the search starts."""
    res = solve_inverse(_wavy, _dwavy, 5.0, u0, -2.0, 2.0)
    assert res.path == "fallback"
    assert not res.saturated
    assert _dwavy(res.u) == pytest.approx(0.0, abs=1e-6)
    assert res.u == pytest.approx(math.acos(-0.2 / 3.0) / 3.0, abs=1e-7)
    assert res.residual == pytest.approx(_wavy(res.u) - 5.0)
