"""Inverse solver, command shaping and reference filter of hil_service.umodel."""

from __future__ import annotations

import math

import pytest

from hil_service.umodel import (
    CommandShaper,
    InverseResult,
    ReferenceFilter,
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


def test_vectorised_grid_gives_same_answer() -> None:
    f = lambda u: u * u + 1.0  # noqa: E731
    a = solve_inverse(f, lambda u: 2.0 * u, 0.0, 0.7, -2.0, 2.0)
    b = solve_inverse(f, lambda u: 2.0 * u, 0.0, 0.7, -2.0, 2.0, f_vec=lambda us: us * us + 1.0)
    assert a == b


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


def test_reference_filter() -> None:
    ref = ReferenceFilter(a=0.5)
    # First call starts the filter at the measured output (bumpless), then moves halfway.
    assert ref.filter(4.0, start=2.0) == 3.0
    assert ref.filter(4.0, start=9.0) == 3.5
    assert ref.filter(math.nan) == 3.5  # an ignored setpoint keeps the filter
    assert ref.value == 3.5
    ref.reset(0.0)
    assert ref.filter(1.0) == 0.5
    assert ReferenceFilter(a=0.0).filter(7.0) == 7.0
    with pytest.raises(ValueError):
        ReferenceFilter(a=1.0)


def _wavy(u: float) -> float:  # interior extrema, e.g. a maximum near u = 0.52
    return math.sin(3.0 * u) + 0.2 * u


def _dwavy(u: float) -> float:
    return 3.0 * math.cos(3.0 * u) + 0.2


def _d2wavy(u: float) -> float:
    return -9.0 * math.sin(3.0 * u)


@pytest.mark.parametrize("u0", [-1.7, -0.3, 0.4, 0.52, 0.9, 1.95])
def test_curvature_refinement_finds_the_same_minimiser_as_regula_falsi(u0: float) -> None:
    """Out-of-reach target above a local maximum: the fallback's answer is that maximum,
    whether the stationary point is found by Illinois on f' or by Newton on f'."""
    v = 5.0
    plain = solve_inverse(_wavy, _dwavy, v, u0, -2.0, 2.0)
    fast = solve_inverse(_wavy, _dwavy, v, u0, -2.0, 2.0, d2f=_d2wavy)
    assert plain.path == fast.path == "fallback"
    assert fast.u == pytest.approx(plain.u, abs=1e-7)
    assert abs(fast.residual) <= abs(plain.residual) + 1e-12
    assert fast.saturated == plain.saturated
    assert _dwavy(fast.u) == pytest.approx(0.0, abs=1e-6)


def test_curvature_refinement_never_leaves_the_bracket() -> None:
    """A misleading f'' (wrong sign, zero, NaN) only slows the search down: the bracket holds."""
    v = 5.0
    reference = solve_inverse(_wavy, _dwavy, v, 0.3, -2.0, 2.0)
    for bad in (lambda u: 1.0, lambda u: 0.0, lambda u: math.nan, lambda u: -1e-9):
        res = solve_inverse(_wavy, _dwavy, v, 0.3, -2.0, 2.0, d2f=bad)
        assert res.u == pytest.approx(reference.u, abs=1e-6)


def test_curvature_is_ignored_when_a_root_exists() -> None:
    res = solve_inverse(quad, dquad, 0.0, 0.2, -2.0, 2.0, d2f=lambda u: 2.0)
    assert res.path == "newton" and res.u == pytest.approx(0.5, abs=1e-9)


def test_warm_start_refinement_matches_the_bracketed_search() -> None:
    """The stationary-point search started at u0 gives what the bracketed search gives, and
    a warm start that lands on a maximum of |f − v| is not accepted."""
    from hil_service.umodel.inverse import _extremum

    xtol = 4e-7
    # Minimum of |f − v| at u = 0 (f − v = u² + 1 > 0): warm start accepted.
    f, df, d2f = (lambda u: u * u), (lambda u: 2.0 * u), (lambda u: 2.0)
    plain = _extremum(f, df, -1.0, -0.04, 0.04, xtol, 60)
    warm = _extremum(f, df, -1.0, -0.04, 0.04, xtol, 60, d2f, 0.013)
    assert warm[0] == pytest.approx(plain[0], abs=xtol) and warm[1] <= plain[1] + 1e-15
    # u = 0 is a maximum of |f − v| for f = −u², v = −5: the warm point is refused and the
    # bracketed search runs as without a start.
    g, dg, d2g = (lambda u: -u * u), (lambda u: -2.0 * u), (lambda u: -2.0)
    plain = _extremum(g, dg, -5.0, -0.04, 0.04, xtol, 60)
    warm = _extremum(g, dg, -5.0, -0.04, 0.04, xtol, 60, d2g, 0.013)
    assert warm[0] == pytest.approx(plain[0], abs=xtol)
    assert warm[1] == pytest.approx(plain[1])
