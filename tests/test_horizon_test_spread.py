"""A fleet whose identifiers converge together does not run every channel's horizon test on
the same sample: a vehicle of phase p runs it ``p mod refresh`` samples after one of phase 0
(a test runs the model over up to 1,000 samples: 2,000 channels at once stalled a
1,000-glider service for most of a second, every ``refresh`` samples)."""

from __future__ import annotations

from typing import Any

import pytest

from hil_service.experiment import closed_loop
from hil_service.experiment.closed_loop import ClosedLoopSettings, setpoint_schedule
from hil_service.pipeline import PipelineSettings, VehiclePipeline
from plant_emulator.family import FamilyVehicle, draw_vehicle


def _evaluations(phase: int, asked: bool) -> dict[str, list[int]]:
    """The samples on which each channel of a family vehicle (seed 20, vehicle 0) of
    ``phase`` ran its horizon test; ``asked``: control on with setpoints (the test every
    ``refresh`` samples until it passes), else health's slow cadence."""
    depth, pitch = draw_vehicle(20, 0)
    settings = ClosedLoopSettings(
        scenario="family", samples=1300, seed=20, identify=1250, step_every=300,
        neutral_after_identify=True,
    )  # fmt: skip
    # spread 1: the input lags are chosen on the same sample whatever the phase, so the
    # models are the same sample for sample.
    pipeline = VehiclePipeline(PipelineSettings(seed=20), phase=phase, spread=1)
    runs: dict[str, list[int]] = {ch: [] for ch in pipeline.channels}

    def observe(k: int, received: Any) -> None:
        pipeline.observe(received)
        if asked:
            # Asked to command (the commands themselves are not applied: open loop).
            pipeline.decide(received, {"depth": 0.0, "pitch": 0.0}, enabled=True)
        for ch, channel in pipeline.channels.items():
            if channel.horizon_test.evaluations > len(runs[ch]):
                runs[ch].append(k)

    schedule = setpoint_schedule(settings, {"depth": (0.0,), "pitch": (0.0,)})
    closed_loop._drive(settings, FamilyVehicle(depth, pitch, 20), schedule, observe)
    return runs


@pytest.mark.parametrize("asked", [False, True])
def test_a_fleets_vehicles_run_their_first_horizon_tests_on_samples_their_phase_spreads(
    asked: bool,
) -> None:
    # Later runs follow the model (asked: every refresh samples until it passes) and the
    # events that ask for a verdict at once (the input lags' choice, a restart), which a
    # fleet's phases spread themselves.
    first = _evaluations(0, asked)
    assert all(first.values()), first
    for phase in (37, 137):  # 37 samples late, for a refresh of 50
        later = _evaluations(phase, asked)
        assert {ch: ks[0] for ch, ks in later.items()} == {
            ch: ks[0] + 37 for ch, ks in first.items()
        }, (phase, first, later)
