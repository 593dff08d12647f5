"""The one definition of the multi-step figures (``scoring.normalised_square_error``), used
by ``experiment``/``report`` (``umodel/multistep.py``) and ``health``
(``scoring.MultiStepStats``), and the free-run fit's ceiling (``identification.fit_bound``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_service.experiment.identification import (
    IdentificationSettings,
    derived_horizon,
    fit_bound,
    plant_outputs,
    run_identification,
)
from hil_service.umodel import build_model
from hil_service.umodel.multistep import MultiStepScores, fit_percent, nmse
from hil_service.umodel.scoring import (
    MultiStepStats,
    fit_from_nmse,
    normalised_square_error,
)


def test_normalised_square_error_on_known_values():
    y = [0.0, 2.0, 4.0]  # mean 2, Σ(y − ȳ)² = 8
    assert normalised_square_error(y, [1.0, -1.0, 0.0]) == pytest.approx(2.0 / 8.0)
    assert normalised_square_error(y, [0.0, 0.0, 0.0]) == 0.0
    assert fit_from_nmse(0.25) == pytest.approx(50.0)
    assert fit_from_nmse(None) is None


def test_normalised_square_error_refuses_what_it_cannot_score():
    assert normalised_square_error([1.0], [0.0]) is None
    assert normalised_square_error([3.0, 3.0, 3.0], [0.0, 1.0, 0.0]) is None  # flat
    assert normalised_square_error([1.0, math.nan], [0.0, 0.0]) is None
    assert normalised_square_error([1.0, 2.0], [0.0, math.inf]) is None
    with pytest.raises(ValueError, match="differ in length"):
        normalised_square_error([1.0, 2.0], [0.0])


def test_health_and_experiment_compute_the_same_figures():
    rng = np.random.default_rng(5)
    y = np.cumsum(rng.standard_normal(300))
    y_sim = y + 0.3 * rng.standard_normal(300)
    stats = MultiStepStats(window=300)
    for a, b in zip(y, y_sim, strict=True):
        stats.add(float(a), float(b))
    assert stats.nmse() == nmse(y, y_sim)
    assert stats.fit() == fit_percent(y, y_sim)
    # The norm form of the fit, computed independently.
    direct = 100.0 * (1.0 - np.linalg.norm(y - y_sim) / np.linalg.norm(y - y.mean()))
    assert stats.fit() == pytest.approx(direct, rel=1e-12)


def test_health_window_keeps_only_the_last_samples_and_caps_a_blow_up():
    stats = MultiStepStats(window=4)
    for value in (100.0, -100.0, 0.0, 1.0, 2.0, 3.0):
        stats.add(value, value)
    assert stats.nmse() == 0.0 and stats.fit() == 100.0
    stats.add(4.0, math.inf)  # a free run that blew up: very negative, still finite
    assert stats.fit() is not None and stats.fit() < -1e90
    for value in (5.0, 6.0, 7.0, 8.0):
        stats.add(value, value)
    assert stats.fit() == 100.0  # gone with the window


def test_fit_bound_is_at_least_the_noise_free_plant_and_100_without_disturbance():
    settings = IdentificationSettings("disturbed", "depth", samples=1200, seed=2)
    bound = fit_bound(settings, clock_seeds=2)
    # The disturbance's mean is the best constant to add: never below the plant alone.
    assert bound.noise_free is not None and bound.bound is not None
    assert bound.bound >= bound.noise_free
    assert bound.bound < 100.0
    # The deterministic current wave makes the time-aware mean a better predictor.
    assert bound.clock is not None and bound.clock > bound.bound
    clean = fit_bound(IdentificationSettings("nonlinear", "depth", samples=600), clock_seeds=1)
    assert clean.noise_free == clean.bound == clean.clock == 100.0
    with pytest.raises(ValueError, match="clock_seeds"):
        fit_bound(settings, clock_seeds=0)


def test_the_disturbance_is_additive_and_independent_of_the_input():
    settings = IdentificationSettings("disturbed", "pitch", samples=800, seed=1)
    y = plant_outputs(settings)
    x = plant_outputs(settings, disturbed=False)
    other_input = plant_outputs(
        IdentificationSettings("disturbed", "pitch", samples=800, seed=3), seed=1
    )
    other_x = plant_outputs(
        IdentificationSettings("disturbed", "pitch", samples=800, seed=3), disturbed=False
    )
    # Same disturbance seed, another input: the same disturbance sequence.
    np.testing.assert_allclose(y - x, other_input - other_x, rtol=0, atol=1e-12)
    assert np.std(y - x) > 0.0


def test_the_k_step_horizon_is_the_one_the_controller_derives():
    settings = IdentificationSettings("paper", "pitch", samples=800, seed=0)
    result = run_identification(settings)
    assert result.horizon_source == "derived"
    # The stabilised pitch loop settles in 5–15 samples; the cap here is (800 − 400) // 4.
    assert 3 <= result.horizon <= 30
    assert result.as_json()["horizon"] == result.horizon
    assert all(t.multistep.horizon == result.horizon for t in result.models.values())
    given = run_identification(IdentificationSettings("paper", "pitch", samples=800, horizon=7))
    assert (given.horizon, given.horizon_source) == (7, "given")


def test_a_model_without_an_input_map_has_no_derived_horizon():
    assert derived_horizon(build_model("persistence")) == 0
    assert derived_horizon(build_model("rls-arx")) == 0
    assert derived_horizon(build_model("dynamic", seed=0)) == 0  # nothing identified yet


def test_a_tiny_k_step_nmse_keeps_its_significant_digits():
    scores = MultiStepScores(fit=99.9, k_step_nmse=3.21e-9, horizon=5, split=10, windows=4)
    assert scores.as_json()["k_step_nmse"] == 3.21e-9
    assert MultiStepScores(None, math.nan, 5, 10, 0).as_json()["k_step_nmse"] is None
