"""Near pole–zero cancellations in the identified G, and when they set the plan's horizon
(docs/control.md, "Near pole–zero cancellations")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_service.umodel.cancellation import record_prefers, reduced_model
from hil_service.umodel.dynamics import ModelDynamics
from hil_service.umodel.horizon import arrival_time, step_response
from hil_service.umodel.predictive import PredictiveInverse, PredictiveSettings

BAND, LO, HI = 0.05, 5, 1000


def _with_pair(
    fast: float, delay: int, pole: float, zero: float
) -> tuple[list[float], list[float]]:
    """ar and gains of q^-(1+delay)·(1 − zero·q⁻¹) / ((1 − fast·q⁻¹)(1 − pole·q⁻¹))."""
    return [fast + pole, -fast * pole], [0.0] * delay + [1.0, -zero]


def _simulate(ar: list[float], gains: list[float], w: np.ndarray) -> np.ndarray:
    y = np.zeros(len(w))
    for t in range(len(w)):
        y[t] = sum(a * y[t - 1 - i] for i, a in enumerate(ar) if t - 1 - i >= 0)
        y[t] += sum(g * w[t - 1 - j] for j, g in enumerate(gains) if t - 1 - j >= 0)
    return y


def _steps(n: int, hold: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w, level, left = np.zeros(n), 0.0, 0
    for t in range(n):
        if left == 0:
            level, left = float(rng.uniform(-1.0, 1.0)), int(rng.integers(*hold))
        w[t], left = level, left - 1
    return w


def test_a_pair_hidden_until_the_response_arrives_is_taken_out() -> None:
    # A first-order plant (pole 0.342, delay 3) with the pair an identifier fitted to a
    # periodic disturbance (seed 0's vehicle 26 pitch of the family): a pole at 0.9995
    # beside a zero at 1.0018. The whole response arrives with the plant and then drifts
    # to a level of the other sign; without the pair it is the plant's.
    ar, gains = _with_pair(0.342, 3, 0.9995, 1.0018)
    reduced = reduced_model(ar, gains, BAND, LO, HI)
    assert reduced is not None
    assert reduced.ar == pytest.approx([0.342], abs=1e-9)
    assert reduced.gains == pytest.approx([0.0, 0.0, 0.0, 1.0], abs=1e-9)
    full = step_response(ar, gains, HI)
    plant = step_response(reduced.ar, reduced.gains, HI)
    assert list(reduced.response) == list(plant)
    assert full[HI - 1] * plant[HI - 1] < 0.0
    assert arrival_time(plant, BAND, LO, HI) < 10 < 500 < arrival_time(full, BAND, LO, HI)


def test_a_pair_the_response_shows_before_it_arrives_is_kept() -> None:
    # 0.02 apart: the pair moves the response by about 0.02 a sample, beyond the band
    # before the rest of the response (pole 0.3) has arrived.
    assert reduced_model(*_with_pair(0.3, 0, 0.95, 0.97), BAND, LO, HI) is None
    # No zero near a pole: nothing to take out.
    assert reduced_model([0.342, 0.5], [1.0, 0.2], BAND, LO, HI) is None


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_coefficients_or_records_change_nothing(bad: float) -> None:
    ar, gains = _with_pair(0.342, 3, 0.9995, 1.0018)
    assert reduced_model([bad, ar[1]], gains, BAND, LO, HI) is None
    assert reduced_model(ar, [*gains[:-1], bad], BAND, LO, HI) is None
    reduced = reduced_model(ar, gains, BAND, LO, HI)
    assert reduced is not None
    assert not record_prefers((ar, gains), reduced[:2], [0.0, bad, 1.0], [0.0, 1.0, 2.0])
    assert not record_prefers((ar, gains), reduced[:2], [0.0], [0.0])


def test_the_record_keeps_a_slow_mode_it_shows_and_drops_one_it_contradicts() -> None:
    # The glider's identified depth has that shape too: a pole at 0.9955 beside its
    # non-minimum-phase zero at 1.0045, a wrong-way start within five samples and the
    # rise over hundreds. Its record shows the rise, and the full path is kept.
    glider = _with_pair(0.38, 0, 0.9955, 1.0045)
    glider_reduced = reduced_model(*glider, BAND, LO, HI)
    assert glider_reduced is not None
    w = _steps(1000, (10, 40), seed=1)
    y = _simulate(*glider, w) + 0.01 * np.random.default_rng(2).standard_normal(1000)
    assert not record_prefers(glider, glider_reduced[:2], list(w), list(y))
    # The family plant: first order, no slow mode; the identified pair is the disturbance's.
    # Over inputs held for hundreds of samples (a controlled channel's setpoints) the
    # pair's drift is absent from the record, and the path without it is preferred.
    identified = _with_pair(0.342, 3, 0.9995, 1.0018)
    reduced = reduced_model(*identified, BAND, LO, HI)
    assert reduced is not None
    w = _steps(1000, (200, 300), seed=3)
    disturbance = 0.2 * np.sin(2.0 * np.pi * np.arange(1000) / 398.0)
    y = _simulate(reduced.ar, reduced.gains, w) + disturbance
    assert record_prefers(identified, (reduced.ar, reduced.gains), list(w), list(y))


def _model(ar: list[float], gains: list[float]) -> ModelDynamics:
    lags = [[g, 0.0, 0.0] for g in gains]
    return ModelDynamics(ar, 0.0, lags, 0.5, [0.0] * len(ar), [0.0] * len(gains))


def test_the_channels_verdict_decides_whether_a_hidden_pair_sets_the_horizon() -> None:
    ar, gains = _with_pair(0.38, 0, 0.9955, 1.0045)
    model = _model(ar, gains)
    reduced = reduced_model(ar, gains, BAND, LO, HI)
    assert reduced is not None
    without = reduced.response
    kept = PredictiveInverse(-2.0, 2.0, 0.5)
    dropped = PredictiveInverse(-2.0, 2.0, 0.5)
    dropped.reduced = without
    off = PredictiveInverse(-2.0, 2.0, 0.5, PredictiveSettings(cancel_near_pairs=False))
    off.reduced = without
    full = kept.horizon_for(model)
    assert full > 100
    assert off.horizon_for(model) == full
    assert dropped.horizon_for(model) == 4 * arrival_time(without, BAND, LO, HI) < 40
