"""The paper's plants, the inner loop that stabilises them, and the simulated glider."""

from __future__ import annotations

import numpy as np
import pytest

from plant_emulator.models import (
    CHANNELS,
    DEFAULT_DESIGNS,
    DEPTH_DEN,
    DEPTH_NUM,
    PITCH_DEN,
    cancel_common_roots,
    design_closed_loop,
    open_loop_plant,
)
from plant_emulator.plant import GliderPlant, PlantConfig


def test_depth_cancellation_removes_the_pole_at_one_once():
    num, den = cancel_common_roots(DEPTH_NUM, DEPTH_DEN)
    assert len(np.roots(den)) == 3
    assert len(np.roots(num)) == 2
    # One pole at z = 1 stays (the integrator); the NMP zero at 1.00453 stays too.
    assert np.sum(np.abs(np.roots(den) - 1.0) < 1e-4) == 1
    assert np.min(np.abs(np.roots(num) - 1.00453)) < 1e-4


def test_open_loop_plants_are_not_stable():
    assert np.max(np.abs(np.roots(PITCH_DEN))) == pytest.approx(1.021, abs=1e-3)
    for channel in CHANNELS:
        poles = open_loop_plant(channel).poles()
        assert np.max(np.abs(poles)) >= 1.0 - 1e-6


@pytest.mark.parametrize("channel", CHANNELS)
@pytest.mark.parametrize("period", [0.5, 1.0, 5.0])
def test_inner_loop_is_stable_and_has_the_designed_dc_gain(channel, period):
    loop = design_closed_loop(channel, period)
    poles = loop.as_state_space().poles()
    assert np.max(np.abs(poles)) < 1.0
    assert loop.dc_gain() == pytest.approx(DEFAULT_DESIGNS[channel].dc_gain, rel=1e-6)
    # And the simulated step response settles to that gain.
    ys = [loop.step(1.0) for _ in range(4000)]
    assert ys[-1] == pytest.approx(DEFAULT_DESIGNS[channel].dc_gain, rel=1e-3)


def test_paper_printed_compensated_depth_model_is_unstable():
    # Paper eq. 16 as printed: kept here as the reason the emulator designs its own loop.
    den = [1, -2.62, 2.344, -0.8347, 0.1166, -0.005582, 0.0001357]
    assert np.max(np.abs(np.roots(den))) > 1.0


def run_plant(scenario: str, seed: int, steps: int = 300) -> np.ndarray:
    plant = GliderPlant(PlantConfig(scenario=scenario, seed=seed))
    rng = np.random.default_rng(99)
    commands = rng.uniform(-2, 2, size=(steps, 2))
    samples = [plant.step(*c) for c in commands]
    return np.array([[s.depth, s.pitch, s.u_depth, s.u_pitch] for s in samples])


@pytest.mark.parametrize("scenario", ["paper", "disturbed", "nonlinear"])
def test_plant_is_deterministic_for_a_seed(scenario):
    assert np.array_equal(run_plant(scenario, 5), run_plant(scenario, 5))


def test_disturbed_scenario_depends_on_seed_and_paper_does_not():
    assert not np.array_equal(run_plant("disturbed", 1), run_plant("disturbed", 2))
    assert np.array_equal(run_plant("paper", 1), run_plant("paper", 2))


def test_depth_is_trim_plus_model_output_and_inputs_are_rate_limited():
    plant = GliderPlant(PlantConfig(trim_depth=20.0))
    first = plant.step(2.0, -2.0)
    assert first.depth == 20.0 and first.pitch == 0.0
    assert (first.u_depth, first.u_pitch) == (0.5, -0.5)  # default rate limit 0.5/step
    assert [plant.step(2.0, -2.0).u_depth for _ in range(5)] == [1.0, 1.5, 2.0, 2.0, 2.0]


def test_outputs_depend_on_the_previous_input_only():
    a, b = GliderPlant(), GliderPlant()
    a.step(1.0, 1.0)
    b.step(1.0, 1.0)
    assert a.step(2.0, 2.0).depth == b.step(-2.0, -2.0).depth
