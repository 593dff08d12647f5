"""Readings served twice by an asynchronous sampler (hil_service/pipeline.py, ``observe``).

A stream at the sample rate with jitter sometimes delivers a reading one tick early, and
the sampler then serves it again on the next tick: the output sequence is y(k−1), y(k+1),
y(k+1), y(k+2). On the ArduSub profile (10 Hz) about 7 % of the depth samples were such
repeats. The pipeline undoes the update learnt from the early reading, drops the repeat and
refills the history without training, while control goes on.
"""

from __future__ import annotations

import random

from hil_service.pipeline import ChannelPipeline, PipelineSettings, VehiclePipeline
from plant_emulator.excitation import build_channel_excitations
from plant_emulator.plant import GliderPlant, PlantConfig

PERIOD = 0.1
IDENTIFY, CONTROL = 600, 1500  # samples: the ArduSub test's 60 s and 150 s at 10 Hz


def _loop(seed: int, repeat_share: float) -> tuple[float, VehiclePipeline]:
    """The ArduSub test in process: prbs identification, then a 1 m depth step; every
    output reading is served a tick early (and then again) with ``repeat_share``.
    Returns the mean |depth error| over the second half of the step."""
    plant = GliderPlant(PlantConfig(period=PERIOD, seed=seed))
    pipeline = VehiclePipeline(PipelineSettings(burn_in=IDENTIFY // 2))
    excitation = build_channel_excitations("prbs", seed)
    rng = random.Random(seed)
    command, sample, served_early = (0.0, 0.0), None, False
    errors = []
    for k in range(IDENTIFY + CONTROL):
        if served_early:
            served_early = False  # the plant has not moved since the early reading
        elif k > 0 and rng.random() < repeat_share:
            plant.step(*command)
            sample, served_early = plant.step(*command), True
        else:
            sample = plant.step(*command)
        assert sample is not None
        sample = sample._replace(time_boot_ms=round(k * PERIOD * 1000))  # the tick's time
        pipeline.observe(sample, sampled=True)
        if k < IDENTIFY:
            command = (excitation["depth"].value(k), excitation["pitch"].value(k))
            continue
        decision = pipeline.decide(sample, {"depth": 16.0, "pitch": 0.1}, True)
        assert decision.command is not None, decision.reason  # repeats never block control
        command = (decision.command.u_depth, decision.command.u_pitch)
        errors.append(abs(sample.depth - 16.0))
    tail = errors[len(errors) // 2 :]
    return sum(tail) / len(tail), pipeline


def test_repeated_readings_are_dropped_and_the_depth_step_is_tracked() -> None:
    # Measured (seeds 1, 2, 4): 0.120, 0.067, 0.004 m with the repeats handled; 0.249,
    # 0.747, 0.396 m when the identifier learnt from them (no control leaves 1 m).
    for seed in (1, 2, 4):
        error, pipeline = _loop(seed, 0.065)
        depth = pipeline.channels["depth"]
        assert depth.repeats > 50
        assert error < 0.3, (seed, error)


def test_without_repeats_nothing_is_dropped() -> None:
    error, pipeline = _loop(1, 0.0)
    assert error < 0.05  # measured 0.003 m
    # A noise-free output settles exactly, so pitch may repeat at its setpoint; the depth
    # step has not settled to the last bit within 150 s.
    assert pipeline.channels["depth"].repeats == 0


def test_a_repeat_undoes_the_update_learnt_from_the_early_reading() -> None:
    plant = GliderPlant(PlantConfig(period=PERIOD, seed=3))
    excitation = build_channel_excitations("prbs", 3)
    pipeline = VehiclePipeline(PipelineSettings(burn_in=50))
    depth = pipeline.channels["depth"]
    samples = []
    for k in range(200):
        samples.append(plant.step(excitation["depth"].value(k), excitation["pitch"].value(k)))
    for sample in samples[:150]:
        pipeline.observe(sample, sampled=True)
    before = depth.model.snapshot()["theta"]
    early = samples[151]._replace(time_boot_ms=samples[150].time_boot_ms)  # k+1 served at k
    pipeline.observe(early, sampled=True)
    assert depth.model.snapshot()["theta"] != before  # learnt from it, not knowing yet
    again = early._replace(time_boot_ms=samples[151].time_boot_ms)
    assert pipeline.observe(again, sampled=True) == {}  # dropped
    assert depth.repeats == 1
    assert depth.model.snapshot()["theta"] == before  # and the update undone
    skipped = depth.skipped
    for sample in samples[152 : 152 + depth.model.history_length]:
        assert "depth" not in pipeline.observe(sample, sampled=True)  # refills, no training
    assert depth.skipped == skipped + depth.model.history_length
    assert "depth" in pipeline.observe(samples[152 + depth.model.history_length], sampled=True)


def _prbs_samples(n: int, seed: int = 3) -> list:
    plant = GliderPlant(PlantConfig(period=PERIOD, seed=seed))
    excitation = build_channel_excitations("prbs", seed)
    return [
        plant.step(excitation["depth"].value(k), excitation["pitch"].value(k)) for k in range(n)
    ]


def test_repeats_and_reused_inputs_are_counted_exactly_and_each_refills_the_history() -> None:
    """Two repeated outputs and two reused input readings after the first lags are filled,
    one reused reading while they are: each one outside the start refills the history
    (no estimate for ``history_length`` samples), each is counted once, and the samples
    learnt from carry their own time."""
    samples = _prbs_samples(120)
    pipeline = VehiclePipeline(PipelineSettings(burn_in=50))
    depth = pipeline.channels["depth"]
    history = depth.model.history_length
    repeated = {40, 70}  # the output of the sample before, served again
    reused = {2, 55, 90}  # 2: still filling the lags after the first sample
    published = []
    for k, sample in enumerate(samples):
        if k in repeated:
            sample = sample._replace(depth=samples[k - 1].depth, pitch=samples[k - 1].pitch)
        estimates = pipeline.observe(sample, inputs_reused=k in reused, sampled=True)
        if "depth" in estimates:
            assert estimates["depth"]["t"] == sample.t
            published.append(k)
    assert (depth.repeats, depth.input_reuses) == (2, 2)
    # A repeat is not learnt from and refills after it; a reused input is learnt from (its
    # output is fresh) and the samples after it refill.
    quiet = set(range(history))
    quiet |= {k + i for k in repeated for i in range(history + 1)}
    quiet |= {k + i for k in reused - {2} for i in range(1, history + 1)}
    assert published == [k for k in range(120) if k not in quiet]
    assert depth.skipped == history * 5


def test_a_repeat_while_the_history_refills_undoes_nothing() -> None:
    """The update undone by a repeat is the one learnt from the sample just before; after a
    sample that only refilled the history there is none, and an older update stays."""
    samples = _prbs_samples(80)
    pipeline = VehiclePipeline(PipelineSettings(burn_in=50))
    depth = pipeline.channels["depth"]
    for k, sample in enumerate(samples[:60]):
        pipeline.observe(sample, inputs_reused=k == 59, sampled=True)  # 59 is learnt from
    assert depth.refill == depth.model.history_length
    pipeline.observe(samples[60], sampled=True)  # refills
    learnt = depth.model.snapshot()["theta"]
    again = samples[61]._replace(depth=samples[60].depth)
    assert "depth" not in pipeline.observe(again, sampled=True)
    assert depth.repeats == 1
    assert depth.model.snapshot()["theta"] == learnt


def test_a_lockstep_source_learns_from_every_repeated_output() -> None:
    """Outside an asynchronous sampler (the default, as the lockstep assembler and the
    experiments call it) an output equal to the one before is real: it is learnt from."""
    pipeline = ChannelPipeline("depth", PipelineSettings(burn_in=50), 0)
    y = u = 0.0
    learnt = 0
    for k in range(60):
        u = 0.5 if k < 20 else 0.0
        y = 0.5 * y + 0.2 * u if k < 30 else 1.0  # held exactly from k = 30
        learnt += pipeline.observe(float(k), y, u) is not None
    assert pipeline.repeats == 0
    assert learnt == 60 - pipeline.model.history_length
