"""The random-plant target on fixed plants: the predictive inverse against the known-model
oracle and the reference input alone, on plants the controller was not tuned on.

The two plants are seed 0's worst of ``--scenario random`` for a plan mixing two models
(docs/control.md, "Random plants, plant by plant"): a third-order plant with a dead zone and
a cubic pump term (plant 6: 3.76x the oracle with such a plan) and a third-order plant with
a non-minimum-phase zero, a dead zone and a cubic term (plant 16: 1.996x). Written out here so
that a change to the random family's draws does not change the test. Short runs (two
setpoint steps after identification): seconds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil_service.experiment.closed_loop import (
    ClosedLoopSettings,
    _drive,
    inverse_run,
    known_plant,
    oracle_run,
    score,
    setpoint_schedule,
)
from hil_service.experiment.random_loop import (
    TRIMS,
    _reference_only_controller,
    channel_levels,
    oracle_settings_for,
)
from hil_service.pipeline import PipelineSettings
from hil_service.umodel.dynamics import ModelDynamics
from hil_service.umodel.predictive import PredictiveInverse
from plant_emulator.models import CHANNELS
from plant_emulator.random_plants import RandomPlantSpec, RandomVehicle, RandomVehicleConfig

DEAD_ZONE_PLANT = RandomPlantSpec(
    index=6,
    order=3,
    poles=((0.8942, 0.0), (0.6142, 0.0), (0.5258, 0.0)),
    zero=None,
    dc_gain=0.3789,
    dead_zone=0.1951,
    cubic=0.1410,
    period=0.2,
)
NMP_DEAD_ZONE_PLANT = RandomPlantSpec(
    index=16,
    order=3,
    poles=((0.6782, 0.0580), (0.8230, 0.0)),
    zero=2.4202,
    dc_gain=4.1726,
    dead_zone=0.2662,
    cubic=0.0885,
    period=0.2,
)


@pytest.fixture(scope="module")
def runs():
    """Inverse, reference only and oracle on the same vehicle, steps and identification."""
    settings = ClosedLoopSettings("random", samples=3100, identify=1500, step_every=800, seed=0)
    config = RandomVehicleConfig(depth=DEAD_ZONE_PLANT, pitch=NMP_DEAD_ZONE_PLANT)
    specs = {"depth": config.depth, "pitch": config.pitch}
    levels = {ch: channel_levels(specs[ch], config.input_limit, TRIMS[ch]) for ch in CHANNELS}
    schedule = setpoint_schedule(settings, levels)
    reference_vehicle = RandomVehicle(config)
    knowns = {ch: known_plant(reference_vehicle, ch, TRIMS[ch]) for ch in CHANNELS}
    inverse = inverse_run(settings, RandomVehicle(config), schedule, PipelineSettings(seed=0))
    reference = _drive(
        settings, reference_vehicle, schedule, _reference_only_controller(schedule, specs, knowns)
    )
    oracle, failures = oracle_run(
        settings,
        RandomVehicle(config),
        schedule,
        {ch: oracle_settings_for(knowns[ch]) for ch in CHANNELS},
        TRIMS,
    )
    assert failures == 0
    for trace in (inverse.trace, reference, oracle):
        score(trace, settings, config.period)
    return settings, inverse, reference, oracle


@pytest.mark.parametrize("channel", CHANNELS)
def test_the_inverse_is_near_the_oracle_and_beats_the_reference_alone(runs, channel):
    _, inverse, reference, oracle = runs
    inv = inverse.trace.metrics[channel].iae
    ref = reference.metrics[channel].iae
    orc = oracle.metrics[channel].iae
    # Measured on these two steps (IAE, output units·s): dead-zone plant (depth) inverse
    # 1.889, oracle 1.779, reference 2.816; NMP plant (pitch) inverse 15.11, oracle 13.62,
    # reference 17.87. A plan whose free response and block effects come from two
    # different models gives depth inverse 3.043 (1.71x the oracle, above the reference
    # alone) and pitch 15.68, and its input moves 0.70 in total over the last half of the
    # first step (0.023 with one model). The target is 2x; 1.4x here keeps a margin over
    # the measured 1.06 and 1.11 and fails such a plan.
    assert orc < ref
    assert inv < 1.4 * orc, (inv, orc)
    assert inv < ref, (inv, ref)
    assert inverse.divergences[channel] == 0
    assert inverse.trace.non_finite_commands[channel] == 0
    assert inverse.blocked == 0


def test_the_plan_holds_still_at_a_setpoint_it_has_reached(runs):
    """The saw tooth that made the dead-zone plant 3.8x the oracle: at a held setpoint the
    input crept for ``refresh`` samples and snapped back at each derivation. Over the last
    half of each step the input now moves less than a rate step in total."""
    settings, inverse, _, _ = runs
    u = inverse.trace.u["depth"]
    for start in range(settings.identify, settings.samples, settings.step_every):
        tail = u[start + settings.step_every // 2 : start + settings.step_every]
        assert float(np.sum(np.abs(np.diff(tail)))) < 0.5, start


def _dynamics(bias: float, ar: list[float]) -> ModelDynamics:
    return ModelDynamics(
        ar=ar,
        bias=bias,
        lag_polys=[[0.2, 0.0, 0.01], [0.1, 0.0, 0.005]],
        poly_scale=0.5,
        outputs=[1.0, 0.9, 0.8],
        inputs=[0.5, 0.4],
    )


def test_the_free_response_is_the_model_the_plan_was_derived_from():
    """Between two derivations the identifier moves on; the plan's prediction stays one
    model's (the derivation's), so a model that moved along the steady-state direction
    (bias against AR coefficients) does not change the command until the next derivation,
    and then changes it as that model asks."""
    first = _dynamics(0.05, [0.9, -0.1, 0.05])
    moved = _dynamics(0.06, [0.9, -0.1, 0.04])
    commands = []
    for later in (first, moved):
        controller = PredictiveInverse(-2.0, 2.0, 0.5)
        controller.decide(first, 0.5, 0.8)
        commands.append(controller.decide(later, 0.5, 0.8)[0])
    assert commands[0] == commands[1]
    assert all(math.isfinite(c) for c in commands)
    fresh = PredictiveInverse(-2.0, 2.0, 0.5)
    assert abs(fresh.decide(moved, 0.5, 0.8)[0] - commands[0]) > 0.01
