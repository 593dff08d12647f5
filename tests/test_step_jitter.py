"""The lockstep path with a vehicle whose sample period jitters: the glider profile's
MAVLink messages, encoded and parsed as on the wire, through ``SampleAssembler`` into the
identifier (``VehiclePipeline``), whose continuity check must tell jitter from a lost
sample."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from hil_service.pipeline import PipelineSettings, StepContinuity, VehiclePipeline
from hil_service.sources.lockstep_assembler import (
    AssemblyCounters,
    SampleAssembler,
    VehicleCounters,
)
from plant_emulator.plant import GliderPlant, PlantConfig
from protocols.mapping import TelemetryMapping
from protocols.mavlink_io import MavlinkCodec
from protocols.samples import TelemetrySample

PERIOD_MS = 1000


def _times(n: int, jitter: float, seed: int = 3) -> list[int]:
    """Each stamp within ±jitter·period of a regular grid: steps of P ± 2j."""
    rng = np.random.default_rng(seed)
    grid = PERIOD_MS * (10 + np.arange(n))
    return [int(t) for t in grid + rng.uniform(-jitter, jitter, n) * PERIOD_MS]


def _samples(times: list[int]) -> list[TelemetrySample]:
    plant = GliderPlant(PlantConfig(scenario="disturbed", seed=1))
    return [
        plant.step(1.5 * math.sin(k / 7), -math.cos(k / 5))._replace(time_boot_ms=t)
        for k, t in enumerate(times)
    ]


def _through_the_link(samples: list[TelemetrySample]) -> tuple[list[TelemetrySample], dict]:
    """Encoded, packed, parsed and assembled: what a lockstep service receives."""
    mapping = TelemetryMapping()
    vehicle, service = MavlinkCodec(1, 1), MavlinkCodec(255, 0)
    assembler = SampleAssembler()
    out = []
    for sample in samples:
        for message in mapping.encode_telemetry(sample):
            for parsed in service.parse(vehicle.pack(message), datagram=True):
                assembled = assembler.add(parsed)
                if assembled is not None:
                    out.append(assembled)
    return out, assembler.counters.as_dict()


def _identify(samples: list[TelemetrySample]) -> tuple[VehiclePipeline, int]:
    pipeline = VehiclePipeline(PipelineSettings())
    estimated = sum("depth" in pipeline.observe(s) for s in samples)
    return pipeline, estimated


def test_a_jittering_period_is_not_a_gap_a_lost_sample_still_is() -> None:
    times = _times(600, jitter=0.2)  # steps from 0.6 to 1.4 periods
    assembled, counters = _through_the_link(_samples(times))
    assert len(assembled) == 600 and counters["incomplete"] == 0
    steps = np.diff([s.time_boot_ms for s in assembled])
    assert steps.min() < 0.7 * PERIOD_MS and steps.max() > 1.3 * PERIOD_MS
    pipeline, estimated = _identify(assembled)
    assert pipeline.gaps.gaps == 0
    assert abs(pipeline.gaps.period_ms - PERIOD_MS) < 0.1 * PERIOD_MS  # type: ignore[operator]
    history = pipeline.channels["depth"].model.history_length
    assert estimated >= 600 - history - 1

    # The same stream with three samples lost on the way: each is a gap, whatever the
    # jitter around it, and the identifier re-synchronises after it.
    lost = {150, 300, 450}
    kept = [s for k, s in enumerate(assembled) if k not in lost]
    pipeline, estimated = _identify(kept)
    assert pipeline.gaps.gaps == 3
    assert pipeline.channels["depth"].skipped >= 3 * history


def test_the_shortest_step_as_the_period_took_jitter_for_lost_samples() -> None:
    """The reference: the continuity rule a jittering vehicle defeats (the shortest step
    seen as the period), on the same stamps."""
    times = _times(600, jitter=0.2)
    shortest: int | None = None
    flagged = 0
    for a, b in itertools.pairwise(times):
        step = b - a
        shortest = step if shortest is None else min(shortest, step)
        flagged += step > 1.5 * shortest
    assert flagged > 50
    steps = StepContinuity()
    assert sum(not steps.follows(t) for t in times) == 1  # the first sample only


def test_a_persistent_change_of_period_is_learnt() -> None:
    steps = StepContinuity()
    times = [1000 * k for k in range(20)] + [19_000 + 2000 * k for k in range(1, 20)]
    verdicts = [steps.follows(t) for t in times]
    # The first step of 2 s and the next are gaps; the third agrees with them: learnt.
    assert verdicts[20:23] == [False, False, True] and all(verdicts[23:])
    assert (steps.period_ms, steps.period_changes, steps.gaps) == (2000, 1, 2)
    # A single lost sample at the new period is still a gap.
    assert steps.follows(times[-1] + 4000) is False
    assert steps.follows(times[-1] + 6000) is True
    # And a shorter period follows on at once and is learnt as its steps come in.
    now = times[-1] + 6000
    assert all(steps.follows(now + 1000 * k) for k in range(1, 12))
    assert steps.period_ms == 1000


def test_assembly_counters_as_dict_name_every_field():
    vehicle = VehicleCounters(1, 2, 3, 4, 5)
    assert vehicle.as_dict() == dataclasses.asdict(vehicle)
    total = AssemblyCounters(1, 2, 3, 4, 5, 6)
    assert total.as_dict() == dataclasses.asdict(total)
