"""The steady-glide baseline recovers a glider's flight parameters; the dive evaluation
scores held-out dives and says when an input is not excited."""

from __future__ import annotations

import numpy as np
import pytest

from hil_service.offline.field.evaluate import Arrays, Segment, excitation, identify_dives
from hil_service.umodel.steady_glide import SteadyGlide, fit_static_pitch, fit_steady_glide

TRUTH = SteadyGlide(k=0.5, v0=0.2, c_p=0.0004, rms=0.0, samples=0)
PERIOD = 10.0


def _dives(count: int, rng: np.random.Generator) -> Arrays:
    """Saw-tooth dives of the true steady-glide model: buoyancy and pitch switch at the
    bottom (600 m); the pitch input sets the pitch through a static balance."""
    depth, pitch, u_depth, u_pitch, segments = [], [], [], [], []
    for dive in range(count):
        start = len(depth)
        z, going_down = 0.5, True
        b_down, b_up = -1.0 + 0.1 * rng.standard_normal(), 1.0 + 0.1 * rng.standard_normal()
        for _ in range(4000):
            b = b_down if going_down else b_up
            m = -0.8 if going_down else 0.8
            theta = 0.05 + 0.45 * m + 0.05 * b
            depth.append(z)
            pitch.append(theta + 0.002 * rng.standard_normal())
            u_depth.append(b)
            u_pitch.append(m)
            z = TRUTH.step(z, b, theta, PERIOD)
            if going_down and z > 600.0:
                going_down = False
            if not going_down and z < 0.5:
                break
        segments.append(Segment(dive, start, len(depth)))
    return Arrays(
        PERIOD,
        np.array(depth),
        np.array(pitch),
        np.array(u_depth),
        np.array(u_pitch),
        segments,
    )


def test_steady_glide_least_squares_recovers_the_flight_parameters() -> None:
    arrays = _dives(2, np.random.default_rng(0))
    z, b, th = arrays.depth, arrays.u_depth, arrays.pitch
    rate = np.concatenate([np.diff(z[s.start : s.stop]) / PERIOD for s in arrays.segments])
    cols = [np.concatenate([a[s.start : s.stop - 1] for s in arrays.segments]) for a in (b, th, z)]
    fitted = fit_steady_glide(rate, *cols, v0_range=(-2.0, 2.0))
    assert fitted.k == pytest.approx(TRUTH.k, rel=0.05)
    assert fitted.v0 == pytest.approx(TRUTH.v0, abs=0.03)
    assert fitted.c_p == pytest.approx(TRUTH.c_p, abs=1e-4)


def test_static_pitch_balance_is_linear_least_squares() -> None:
    rng = np.random.default_rng(1)
    m, v = rng.uniform(-1, 1, 500), rng.uniform(-1, 1, 500)
    theta = 0.1 + 0.4 * m - 0.2 * v
    fitted = fit_static_pitch(theta, m, v)
    assert (fitted.a, fitted.b, fitted.c) == pytest.approx((0.1, 0.4, -0.2), abs=1e-9)


def test_held_out_dives_scored_and_the_true_model_fits_best() -> None:
    arrays = _dives(4, np.random.default_rng(2))
    depth, pitch = identify_dives(arrays)
    assert depth.train_dives == [0, 1] and depth.held_out == [2, 3]
    fits = {m.model: m.fit for m in depth.models}
    assert fits["steady-glide"] > 99.0
    assert fits["persistence"] < 0.0
    for model in depth.models:
        assert [d.dive for d in model.dives] == [2, 3]
        assert all(d.k_step_nmse is not None for d in model.dives)
    assert {m.model for m in pitch.models} == {
        "persistence",
        "rls-arx",
        "dynamic",
        "static-balance",
    }


def test_a_constant_input_is_not_excited_and_says_why() -> None:
    arrays = _dives(2, np.random.default_rng(3))
    arrays.u_pitch = np.full_like(arrays.u_pitch, 0.3)
    result = excitation(arrays, "pitch", arrays.segments)
    assert not result.excited
    assert "input std" in result.why and "moves per dive" in result.why
    assert excitation(arrays, "depth", arrays.segments).excited


def test_one_dive_cannot_be_held_out() -> None:
    arrays = _dives(1, np.random.default_rng(4))
    with pytest.raises(ValueError, match="at least two dives"):
        identify_dives(arrays)
