"""``hil_service.umodel.structure``: the dynamic model's input lags chosen from the record by
validation, and the pipeline that rebuilds its identifier with them."""

from __future__ import annotations

import numpy as np
import pytest

from hil_service.umodel.structure import _design, _regressors, choose_input_lags
from hil_service.umodel.supervisor import HorizonTest


def _record(delay: int, noise: float = 0.0, n: int = 900, seed: int = 0):
    """y = 0.6 y(t−1) + 0.5 u(t−1−delay) (+ white noise), the input a random step every 25
    samples; returned as the horizon test records them (y[t], the input one step before)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1.5, 1.5, n // 25 + 1), 25)[:n]
    x = np.zeros(n)
    for t in range(1, n):
        x[t] = 0.6 * x[t - 1] + 0.5 * (u[t - 1 - delay] if t - 1 - delay >= 0 else 0.0)
    y = x + noise * rng.standard_normal(n)
    return y[1:], u[:-1]  # y[t] with the input applied at t − 1


@pytest.mark.parametrize(("delay", "lags"), [(0, 4), (1, 4), (4, 6), (5, 6), (6, 8)])
def test_a_delay_the_default_lags_cannot_hold_gets_enough_lags(delay, lags):
    y, u = _record(delay)
    choice = choose_input_lags(y, u, u_scale=2.0)
    assert choice is not None and choice.lags == lags, choice and choice.fits


def test_the_choice_is_the_same_in_any_output_unit_and_offset():
    y, u = _record(5, noise=0.02)
    base = choose_input_lags(y, u, u_scale=2.0)
    scaled = choose_input_lags(1000.0 + 1e-3 * y, u, u_scale=2.0)
    assert base is not None and scaled is not None and base.lags == scaled.lags == 6
    for lags, fit in base.fits.items():
        assert scaled.fits[lags] == pytest.approx(fit, abs=1e-6)


def test_a_short_or_broken_record_makes_no_choice():
    y, u = _record(2)
    assert choose_input_lags(y[:200], u[:200], u_scale=2.0) is None
    y[500] = np.nan
    assert choose_input_lags(y, u, u_scale=2.0) is None
    assert choose_input_lags(np.ones(900), u, u_scale=2.0) is None  # nothing moved


def test_no_candidate_that_predicts_keeps_the_default():
    # Noise as large as the response: no number of lags predicts over the segments, and
    # the choice keeps the model's own four rather than pick among models that all fail.
    y, u = _record(5, noise=3.0)
    choice = choose_input_lags(y, u, u_scale=2.0)
    assert choice is not None and max(choice.fits.values()) < 0.5 and choice.lags == 4


def _shift_at(y: np.ndarray, u: np.ndarray, restarts: list[int]):
    """The record an asynchronous sampler leaves, as ``HorizonTest`` keeps it: at each
    restart the reading is a tick early (the next output in its place) and the repeat
    that follows is dropped."""
    record = HorizonTest()
    keep = np.ones(y.size, dtype=bool)
    for t in restarts:
        keep[t] = False
    for t in range(y.size):
        if not keep[t]:
            continue
        early = t > 0 and not keep[t - 1]
        # Paired with the input before the early reading.
        record.record(float(y[t]), float(u[t - 1] if early else u[t]))
        if early:
            record.restart_run()
    ys, us = record.samples()
    return np.array(ys), np.array(us), record.runs()


def test_the_record_restarts_its_runs_and_a_gap_clears_them():
    record = HorizonTest()
    for k in range(5):
        record.record(float(k), 0.0)
    record.restart_run()  # the newest is out of step; the next starts a run
    record.record(5.0, 0.0)
    record.record(6.0, 0.0)
    assert record.runs() == [0, 1, 2, 3, 0, 0, 1]
    record.break_record()
    record.record(7.0, 0.0)
    assert record.runs() == [0] and record.samples() == ([7.0], [0.0])


def test_no_regression_reaches_across_a_reading_served_early():
    y, u = _record(1)
    # Sparse restarts: the choice is the one of the clean record.
    ys, us, runs = _shift_at(y, u, [130, 640, 700, 820])
    clean = choose_input_lags(y, u, u_scale=2.0)
    across = choose_input_lags(ys, us, u_scale=2.0, runs=runs)
    assert clean is not None and across is not None and across.lags == clean.lags == 4
    assert min(across.fits.values()) > 0.99  # the shifted samples left out, not fitted
    # A restart every 15 samples leaves no 50-sample segment to validate on: no choice
    # (the pipeline keeps its four lags) rather than one fitted to misaligned samples.
    dense = list(range(15, y.size, 15))
    ys, us, runs = _shift_at(y, u, dense)
    assert choose_input_lags(ys, us, u_scale=2.0, runs=runs) is None


@pytest.mark.parametrize("lags", [4, 6, 8])
def test_the_free_runs_regressors_are_the_fits_rows_to_the_bit(lags: int) -> None:
    # A candidate is fitted on rows built a column at a time and validated by free runs
    # whose regressors are built a sample at a time: the two must be one regression, or
    # the validation fit scores a model that was never fitted.
    rng = np.random.default_rng(lags)
    y = rng.normal(size=600).cumsum()
    u = rng.uniform(-2.0, 2.0, 600)
    rows = np.arange(8, 400)
    by_sample = np.array([_regressors(y, u, int(t), 4, lags, 3) for t in rows])
    by_column = _design(y, u, rows, 4, lags, 3)
    assert by_column.shape == by_sample.shape
    assert by_column.tobytes() == by_sample.tobytes()
