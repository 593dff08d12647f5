"""The health report's multi-step accuracy (``multistep_nmse``, ``multistep_fit``): a frozen
copy of the model, restarted from the measured outputs every prediction horizon, runs
free on the applied inputs; each of its outputs is a 1…horizon-step-ahead prediction
(``ChannelPipeline._observe``, ``MultiStepStats``)."""

from __future__ import annotations

from hil_service.pipeline import ControlSettings, PipelineSettings, VehiclePipeline
from hil_service.umodel.scoring import MultiStepStats
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.plant import GliderPlant, PlantConfig


def test_the_pitch_free_run_restarts_from_the_measured_outputs_every_horizon() -> None:
    """The figure the pipeline reports equals the one made here from its definition: a copy
    of the model's dynamics taken at each restart, advanced on the inputs applied, and a
    restart after as many learning samples as the horizon at the previous one, or sooner
    once the horizon has become shorter than what is left of the run."""
    plant = GliderPlant(PlantConfig(period=0.1, seed=5))
    excitation = build_channel_excitations("prbs", 5)
    # A horizon derived before the model is learnt is the longest allowed: kept short here.
    settings = PipelineSettings(burn_in=50, control=ControlSettings(max_horizon=40))
    pipeline = VehiclePipeline(settings)
    pitch = pipeline.channels["pitch"]
    expected = MultiStepStats(window=pitch.multistep.window)
    free_run, left, restarts = None, 0, 0
    previous = None
    for k in range(300):
        sample = plant.step(excitation["depth"].value(k), excitation["pitch"].value(k))
        learns = pitch.resync == 0 and previous is not None
        if learns and free_run is not None:
            expected.add(sample.pitch, free_run.advance(previous.u_pitch))
        estimates = pipeline.observe(sample)
        assert ("pitch" in estimates) == learns
        previous = sample
        if not learns:
            continue
        left -= 1
        if left <= 0 or (free_run is not None and left > pitch.controller.horizon):
            horizon = pitch.controller.horizon  # the one the pipeline has just derived
            restarts += 1
            if horizon < 2:
                free_run, left = None, pitch.settings.control.min_horizon
            else:
                free_run, left = pitch.model.dynamics(), horizon
    assert restarts > 10 and expected.nmse() is not None  # the test saw free runs
    assert pitch.multistep.nmse() == expected.nmse()
    assert pitch.health()["multistep_horizon"] == pitch.controller.horizon


def test_a_run_started_on_the_longest_horizon_ends_when_the_model_gets_a_short_one() -> None:
    """Before the model has an input map its horizon is the longest allowed (1,000 samples):
    the free run started then, on an early model whose AR part may be unstable, is not kept
    for 1,000 samples once the learnt model's horizon is a few samples, so the figure is
    that of the horizon health names, not of a run that blew up."""
    plant = GliderPlant(PlantConfig(period=0.1, seed=5))
    excitation = build_channel_excitations("prbs", 5)
    pipeline = VehiclePipeline(PipelineSettings(burn_in=50))
    pitch = pipeline.channels["pitch"]
    longest = []
    for k in range(600):
        sample = plant.step(excitation["depth"].value(k), excitation["pitch"].value(k))
        pipeline.observe(sample)
        if pitch._free_run is not None:
            longest.append(pitch._free_run_left)
            assert pitch._free_run_left <= max(pitch.controller.horizon, 1)
    assert max(longest) > 100, "a run was started on the longest horizon"
    assert pitch.controller.horizon < 50
    health = pitch.health()
    assert health["multistep_horizon"] == pitch.controller.horizon
    assert health["multistep_nmse"] is not None and health["multistep_nmse"] < 10.0
