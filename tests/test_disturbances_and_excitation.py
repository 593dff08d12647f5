"""Disturbance generators' statistics and determinism; excitation bounds; the actuator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plant_emulator.actuator import BallastActuator, PumpNonlinearity
from plant_emulator.disturbances import GaussMarkovCurrent, PiecewiseCurrentWave, WaveOrbital
from plant_emulator.excitation import EXCITATIONS, Prbs, build_excitation
from plant_emulator.scenarios import build_disturbance


def series(generator, n: int, dt: float = 1.0) -> np.ndarray:
    return np.array([generator.sample(k * dt) for k in range(n)])


def test_gauss_markov_statistics_for_a_seed():
    x = series(GaussMarkovCurrent(sigma=0.3, tau=20.0, seed=4), 200_000)
    assert x.std() == pytest.approx(0.3, rel=0.05)
    assert abs(x.mean()) < 0.03
    lag1 = np.corrcoef(x[:-1], x[1:])[0, 1]
    assert lag1 == pytest.approx(math.exp(-1 / 20.0), abs=0.01)


def test_gauss_markov_is_deterministic_per_seed():
    a = series(GaussMarkovCurrent(seed=1), 500)
    assert np.array_equal(a, series(GaussMarkovCurrent(seed=1), 500))
    assert not np.array_equal(a, series(GaussMarkovCurrent(seed=2), 500))


def test_wave_orbital_is_a_bounded_zero_mean_sum_of_sines():
    wave = WaveOrbital(amplitudes=(0.5, 0.2), periods=(10.0, 7.0), seed=3)
    x = series(wave, 7000, dt=0.1)  # 700 s, many periods of both
    assert abs(x.mean()) < 0.01
    assert np.max(np.abs(x)) <= 0.7 + 1e-12
    assert x.var() == pytest.approx((0.5**2 + 0.2**2) / 2, rel=0.05)
    phases_differ = not np.array_equal(
        x, series(WaveOrbital((0.5, 0.2), (10.0, 7.0), 4), 7000, 0.1)
    )
    assert phases_differ


def test_paper_current_wave_follows_its_breakpoints_and_repeats():
    wave = PiecewiseCurrentWave(amplitude=2.0)
    assert wave.sample(0.0) == 0.0
    assert wave.sample(60.0) == 2.0  # on the plateau 40..80 s
    assert wave.sample(30.0) == pytest.approx(1.0)  # halfway up the 20..40 s ramp
    assert wave.sample(60.0 + 200.0) == 2.0
    # Compared by its settings (its breakpoint arrays, built from them, are not compared).
    assert wave == PiecewiseCurrentWave(amplitude=2.0) != PiecewiseCurrentWave(amplitude=1.0)


def test_only_the_disturbed_scenario_disturbs():
    assert np.all(series(build_disturbance("paper", "depth"), 100) == 0.0)
    assert np.std(series(build_disturbance("disturbed", "depth"), 500)) > 0.05


@pytest.mark.parametrize("name", EXCITATIONS)
def test_excitations_stay_within_full_scale_and_repeat_for_a_seed(name):
    a = [build_excitation(name, seed=8).value(k) for k in range(2000)]
    b = [build_excitation(name, seed=8).value(k) for k in range(2000)]
    assert a == b
    assert max(abs(v) for v in a) <= 2.0


def test_random_steps_hold_levels_and_cover_the_range():
    exc = build_excitation("steps", seed=1)
    values = np.array([exc.value(k) for k in range(5000)])
    changes = np.count_nonzero(np.diff(values))
    assert 5000 / 40 <= changes <= 5000 / 10 + 1
    assert values.min() < -1.5 and values.max() > 1.5


def test_prbs_is_binary_and_balanced():
    prbs = Prbs(amplitude=1.0, hold=1, seed=0)
    values = np.array([prbs.value(k) for k in range(511 * 4)])
    assert set(np.unique(values)) == {-1.0, 1.0}
    assert abs(values.mean()) < 0.01  # a maximal-length sequence has one more 1 than 0


def test_actuator_limits_rate_and_nonfinite_commands():
    actuator = BallastActuator(limit=2.0, rate_limit=0.5)
    assert [actuator.apply(5.0) for _ in range(5)] == [0.5, 1.0, 1.5, 2.0, 2.0]
    assert actuator.apply(math.nan) == 2.0  # a NaN command holds position
    assert actuator.apply(-5.0) == 1.5


def test_pump_nonlinearity_has_a_dead_zone_and_is_odd():
    pump = PumpNonlinearity(dead_zone=0.2, cubic=0.1)
    assert pump(0.1) == pytest.approx(0.1 * 0.1**3)
    assert pump(1.0) == pytest.approx(0.8 + 0.1)
    assert pump(-1.3) == pytest.approx(-pump(1.3))
