"""``hil_service.umodel.structure``: the dynamic model's input lags chosen from the record by
validation, and the pipeline that rebuilds its identifier with them."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from hil_service.experiment import closed_loop
from hil_service.experiment.closed_loop import ClosedLoopSettings, setpoint_schedule
from hil_service.pipeline import (
    LAG_CHOICE_SPREAD,
    PipelineSettings,
    VehiclePipeline,
    choice_spread,
)
from hil_service.umodel.structure import _design, _validation_fits, choose_input_lags
from hil_service.umodel.supervisor import HorizonTest
from plant_emulator.family import FamilyVehicle, draw_vehicle


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


def _free_runs_one_sample_at_a_time(
    theta: np.ndarray, y: np.ndarray, u: np.ndarray, start: int, lags: int, segment: int,
    runs: np.ndarray, first: int,
) -> float:  # fmt: skip
    """The validation fit written the plain way: each segment's free run one sample at a
    time, its regressors from a list of measured then predicted outputs."""
    error = hold = 0.0
    s = start
    while s + segment <= y.size:
        if runs[s + segment - 1] < segment - 1 + first:
            s += 1
            continue
        run = [float(v) for v in y[: s + 1]]
        for t in range(s + 1, s + segment):
            row = [1.0] + [run[t - i] for i in range(1, 5)]
            for lag in range(1, lags + 1):
                x = float(u[t - lag + 1])
                row += [x, x * x, x * x * x]
            value = float(np.dot(theta, row))
            if not (math.isfinite(value) and abs(value) < 1e100):
                return -math.inf
            run.append(value)
            error += (float(y[t]) - value) ** 2
            hold += (float(y[t]) - float(y[s])) ** 2
        s += segment
    return 1.0 - math.sqrt(error / hold) if hold > 0.0 else -math.inf


@pytest.mark.parametrize("lags", [4, 6, 8])
def test_the_free_runs_advanced_together_score_as_one_at_a_time(lags: int) -> None:
    # The validation runs every segment's free run of every candidate at once, one sample
    # of each a step. It must score what each candidate's runs score one sample at a time:
    # the same segments (moved past restarts), the same regression, each run from its own
    # measured history on its own candidate's inputs, and a candidate that blows up fails
    # alone.
    rng = np.random.default_rng(lags)
    u = rng.uniform(-2.0, 2.0, 900)
    y = np.zeros(900)
    for t in range(2, 900):
        y[t] = 1.2 * y[t - 1] - 0.4 * y[t - 2] + 0.3 * u[t - 1] + 0.05 * rng.normal()
    rows = np.arange(8, 600)
    theta, *_ = np.linalg.lstsq(_design(y, u, rows, 4, lags, 3), y[rows], rcond=None)
    unstable = theta.copy()
    unstable[1] = 1e3  # y(t) ≈ 1,000·y(t−1): past 1e100 within a segment
    other_inputs = np.where(np.abs(u) > 0.3, u - 0.3 * np.sign(u), 0.0)  # beyond a dead zone
    candidates = [(theta, u), (unstable, u), (0.9 * theta, other_inputs)]
    runs = np.arange(900)
    runs[700:] -= 700  # a restart at 700: the segment across it moves on
    first = max(4, lags - 1)
    for record_runs in (np.arange(900), runs):
        together = _validation_fits(
            np.array([c[0] for c in candidates]), y, [c[1] for c in candidates], 600, 4,
            lags, 3, 50, record_runs, first,
        )  # fmt: skip
        plain = [
            _free_runs_one_sample_at_a_time(c[0], y, c[1], 600, lags, 50, record_runs, first)
            for c in candidates
        ]
        assert together == pytest.approx(plain, abs=1e-12)
        assert 0.5 < together[0] < 1.0
        assert together[1] == -math.inf
        assert math.isfinite(together[2]) and together[2] != together[0]
        # Alone, a candidate scores what it scores among others, to the bit.
        for i, (weights, inputs) in enumerate(candidates):
            alone = _validation_fits(
                weights[None], y, [inputs], 600, 4, lags, 3, 50, record_runs, first
            )
            assert alone == [together[i]]


def _sample_of_the_choice(phase: int, spread: int = LAG_CHOICE_SPREAD) -> dict[str, int]:
    """The sample on which each channel of a vehicle with ``phase`` chose its lags, on a
    family vehicle (seed 20, vehicle 0) identified open loop, control never asked."""
    depth, pitch = draw_vehicle(20, 0)
    settings = ClosedLoopSettings(
        scenario="family", samples=1300, seed=20, identify=1250, step_every=300,
        neutral_after_identify=True,
    )  # fmt: skip
    pipeline = VehiclePipeline(PipelineSettings(seed=20), phase=phase, spread=spread)
    chosen: dict[str, int] = {}

    def observe(k: int, sample: Any) -> None:
        pipeline.observe(sample)
        for ch, channel in pipeline.channels.items():
            if ch not in chosen and channel.lag_choice is not None:
                chosen[ch] = k

    schedule = setpoint_schedule(settings, {"depth": (0.0,), "pitch": (0.0,)})
    closed_loop._drive(settings, FamilyVehicle(depth, pitch, 20), schedule, observe)
    return chosen


def test_a_fleets_vehicles_make_their_choices_on_samples_their_phase_spreads():
    # A service gives its vehicles phases in the order they appear: a fleet that started
    # together must not make every channel's choice (12-25 ms of CPU each) on one sample.
    first = _sample_of_the_choice(0)
    assert set(first) == {"depth", "pitch"}
    for phase, spread, delay in ((37, 100, 37), (137, 100, 37), (437, 500, 437)):
        later = _sample_of_the_choice(phase, spread)
        assert later == {ch: k + delay for ch, k in first.items()}, (phase, first, later)


def test_a_larger_fleet_spreads_its_choices_over_more_samples():
    # At most two vehicles of a sample period choose: 1,000 gliders over 500 samples.
    assert choice_spread(32) == LAG_CHOICE_SPREAD
    assert choice_spread(1000) == 500
    assert [p % choice_spread(1000) for p in range(1000)].count(7) == 2
