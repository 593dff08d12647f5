"""A fleet whose identifiers converge together does not run every channel's horizon test on
the same samples every ``refresh``: a vehicle of phase p runs the tests that come off the
cadence (the first, at convergence; the first ask's) when one of phase 0 does, and the
ones on the cadence ``p mod refresh`` samples after it (each runs the model over up to
1,000 samples: 2,000 channels at once stalled a 1,000-glider service for most of a second,
every 50 samples)."""

from __future__ import annotations

from typing import Any

import pytest

from hil_service.experiment import closed_loop
from hil_service.experiment.closed_loop import ClosedLoopSettings, setpoint_schedule
from hil_service.pipeline import PipelineSettings, VehiclePipeline
from plant_emulator.family import FamilyVehicle, draw_vehicle


def _evaluations(phase: int, asked: bool) -> dict[str, list[int]]:
    """The samples on which each channel of a family vehicle (seed 20, vehicle 0) of
    ``phase`` ran its horizon test; ``asked``: control on with a depth setpoint (its test every
    ``refresh`` samples until it passes), else health's slow cadence (every ``window``)."""
    depth, pitch = draw_vehicle(20, 0)
    settings = ClosedLoopSettings(
        scenario="family", samples=1300, seed=20, identify=1250, step_every=300,
        neutral_after_identify=True,
    )  # fmt: skip
    # Lags given, not chosen: the choice asks for a verdict at once, on its own sample.
    pipeline = VehiclePipeline(PipelineSettings(seed=20, choose_input_lags=False), phase=phase)
    runs: dict[str, list[int]] = {ch: [] for ch in pipeline.channels}

    def observe(k: int, received: Any) -> None:
        pipeline.observe(received)
        if asked:
            # Depth asked to command (the commands are not applied: open loop). Pitch is
            # not asked: its trips would follow depth's commands, which the shift changes.
            pipeline.decide(received, {"depth": 0.0, "pitch": None}, enabled=True)
        for ch, channel in pipeline.channels.items():
            if channel.horizon_test.evaluations > len(runs[ch]):
                runs[ch].append(k)

    schedule = setpoint_schedule(settings, {"depth": (0.0,), "pitch": (0.0,)})
    closed_loop._drive(settings, FamilyVehicle(depth, pitch, 20), schedule, observe)
    return runs


@pytest.mark.parametrize("asked", [False, True])
def test_a_fleets_vehicles_run_their_later_horizon_tests_on_samples_their_phase_spreads(
    asked: bool,
) -> None:
    # The tests off the cadence come on the same samples whatever the phase: the first, at
    # convergence, and asked, the first ask's right after it and a trip's (open loop, the
    # commands are not applied: the supervisor may stop them). The first on the cadence,
    # the first that differs, comes 37 samples later; when the ones after it come depends
    # on the model there, which the shift changes.
    first = _evaluations(0, asked)
    for phase in (37, 137):  # 37 samples late, for a refresh of 50
        later = _evaluations(phase, asked)
        shifted = 0
        for ch in ["depth"] if asked else list(first):
            ks = first[ch]
            pairs = enumerate(zip(ks, later[ch], strict=False))
            differ = next((i for i, (a, b) in pairs if a != b), None)
            if differ is None:  # no test on the cadence within the run
                assert later[ch] == ks, (phase, ch, ks, later[ch])
                continue
            # The first test, at convergence, is not put off: nor is a first verdict.
            assert differ > 0, (phase, ch, ks, later[ch])
            assert later[ch][differ] == ks[differ] + 37, (phase, ch, ks, later[ch])
            shifted += 1
        assert shifted, (phase, first, later)
