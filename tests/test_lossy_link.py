"""A link that loses samples (docs/control.md, "Short gaps bridged"): a channel whose
horizon is longer than the runs between lost samples qualifies, commands and stays
supervised, because gaps of a few samples whose inputs are known are carried across
rather than restarting the record, the supervisor's windows and the internal model. In
process, on the plants of ``tests/harm_rig.py``."""

from __future__ import annotations

import math

import pytest

from hil_service.pipeline import ChannelPipeline, PipelineSettings, StepContinuity
from hil_service.umodel.dynamics import ModelDynamics
from hil_service.umodel.supervisor import HorizonTest
from tests.harm_rig import Loop, spec

SETPOINT = 15.8  # trim 15, 0.8 above


def _mean_error(values: list[float]) -> float:
    read = [abs(y - SETPOINT) for y in values if math.isfinite(y)]
    return sum(read) / len(read)


@pytest.mark.parametrize("bridge_gap", [5, 0], ids=["bridged", "resynchronised"])
def test_a_slow_channel_commands_on_a_link_that_loses_two_percent(bridge_gap):
    # A slow plant (a horizon of about 175 samples) on a link losing 2 % of the samples:
    # the runs between losses average 50 samples, shorter than the horizon, so a record
    # restarted at every gap seldom holds a whole horizon, and every gap stops commanding
    # while the history refills.
    loop = Loop(
        spec(poles=(0.98, 0.95)),
        spec(),
        settings=PipelineSettings(bridge_gap=bridge_gap),
        loss_share=0.02,
    )
    identify = 2500
    loop.run(identify, {"depth": None, "pitch": None})
    loop.run(3000, {"depth": SETPOINT, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    lost = loop.modes.count("lost")
    assert lost > 80
    read = [m for m in loop.modes[identify + 300 :] if m != "lost"]
    commanded = sum(m.startswith(("newton", "fallback")) for m in read) / len(read)
    if bridge_gap == 0:
        assert commanded < 0.8 and depth.bridged == 0
        return
    assert depth.bridged > 0 and depth.health()["bridged"] == depth.bridged
    # Every sample read while control is on commands, and the output reaches the setpoint.
    assert commanded == 1.0
    assert _mean_error(loop.y[-300:]) < 0.02 * abs(loop.y[identify] - SETPOINT)


CHANGE = 2900  # 400 samples into control


@pytest.mark.parametrize(
    "change",
    [lambda k, u: -u if k >= CHANGE else u, lambda k, u: 5.0 * u if k >= CHANGE else u],
    ids=["sign-flip", "gain-x5"],
)
def test_the_supervisor_trips_on_a_link_that_loses_five_percent(change):
    # Gaps fall inside every supervised window (70-110 samples here): the windows run on
    # across them, so a plant change trips within two of them, as on a clean link.
    identify = 2500
    loop = Loop(spec(poles=(0.97, 0.9)), spec(), change=change, loss_share=0.05)
    loop.run(identify, {"depth": None, "pitch": None})
    loop.run(3000, {"depth": SETPOINT, "pitch": None})
    depth = loop.pipeline.channels["depth"]
    assert depth.bridged > 50
    before = [m for m in loop.modes[identify + 300 : CHANGE] if m != "lost"]
    assert before and all(m.startswith(("newton", "fallback")) for m in before)
    trip = next(k for k, m in enumerate(loop.modes) if m.startswith("safe"))
    assert CHANGE < trip <= CHANGE + 2 * depth.supervisor.window, trip
    assert loop.reasons[trip].startswith("supervisor: ")
    enabled_error = abs(loop.y[identify] - SETPOINT)
    assert _mean_error(loop.y[-100:]) <= 1.2 * enabled_error


def test_the_supervisor_arms_with_bounds_across_a_gap_it_cannot_bridge():
    # A gap whose inputs are unknown restarts the record; the verdict stands, and so do
    # the figures the supervisor's bound is derived from.
    test = HorizonTest(window=50, minimum=2)
    dyn = ModelDynamics([0.5], 0.0, [[1.0]], 1.0, [0.0], [0.0])
    y = 0.0
    for k in range(120):
        u = 1.0 if (k // 10) % 2 else -1.0
        y = 0.5 * y + u
        test.record(y, u)
    assert test.evaluate(dyn, 10)
    figures = (test.model_rms, test.hold_rms)
    test.break_record()
    test.record(y, 1.0)
    assert not test.evaluate(dyn, 10) and test.steps == 0
    assert (test.model_rms, test.hold_rms) == figures and test.hold_rms > 0.0


def _first_order(u: float, y: float) -> float:
    return 0.9 * y + 0.1 * u


def test_the_horizon_test_scores_no_lost_sample_and_starts_no_segment_on_one():
    dyn = ModelDynamics([0.9], 0.0, [[0.1]], 1.0, [0.0], [0.0])
    clean, lossy = HorizonTest(window=200), HorizonTest(window=200)
    y = 0.0
    for k in range(400):
        u = 1.0 if (k // 25) % 2 else -1.0
        y = _first_order(u, y)
        clean.record(y, u)
        if k % 17 == 5:
            lossy.record_missing(y + 100.0, u)  # a wild stand-in: never scored
        else:
            lossy.record(y, u)
    assert clean.evaluate(dyn, 30) and lossy.evaluate(dyn, 30)
    assert clean.fit == pytest.approx(100.0) and lossy.fit == pytest.approx(100.0)
    assert lossy.full
    # A stand-in sits at run 0 and the next sample starts a run: no regression across it.
    runs = lossy.runs()
    stand_in = 5
    assert runs[stand_in] == 0 and runs[stand_in + 1] == 0 and runs[stand_in + 2] == 1


@pytest.mark.parametrize(
    ("times", "missing"),
    [
        ([0, 100, 200, 400], 1),
        ([0, 100, 200, 300, 700], 3),
        ([0, 100, 200, 300, 688], 3),  # a jittered clock rounds to whole samples
        ([0, 100, 200, 300, 50], 0),  # a step back is a restart: nothing to count
    ],
)
def test_the_step_continuity_counts_the_samples_a_gap_lost(times, missing):
    gaps = StepContinuity()
    for t in times:
        follows = gaps.follows(t)
    assert not follows and gaps.missing == missing


def _channel(bridge_gap: int = 5) -> ChannelPipeline:
    channel = ChannelPipeline("depth", PipelineSettings(bridge_gap=bridge_gap), 0)
    y, u = 0.0, 0.0
    for k in range(400):
        u = 0.5 if (k // 20) % 2 else -0.5
        y = _first_order(u, y)
        channel.observe(float(k), y, u)
    return channel


@pytest.mark.parametrize(
    ("u_after", "missing", "bridged"),
    [
        (None, 2, True),  # the input read before the gap: nothing changed it
        (0.7, 2, False),  # changed at an unknown step within the gap
        (None, 6, False),  # longer than bridge_gap
    ],
)
def test_a_gap_is_bridged_only_when_its_inputs_are_known(u_after, missing, bridged):
    channel = _channel()
    assert channel.u_prev is not None
    u = channel.u_prev if u_after is None else u_after
    channel.observe(400.0 + missing, 0.0, u, follows_previous=False, missing=missing)
    assert channel.bridged == (missing if bridged else 0)
    assert (channel.resync == 0) is bridged


def test_a_gap_after_the_channels_own_command_is_bridged():
    channel = _channel()
    channel.last_command = 0.9  # what the last decision sent on this channel
    channel.observe(403.0, 0.0, 0.9, follows_previous=False, missing=2)
    assert channel.bridged == 2 and channel.resync == 0
