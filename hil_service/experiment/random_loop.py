"""``experiment --closed-loop --scenario random``: the controller on plants it was not tuned on.

A seeded family of random plants (``plant_emulator.random_plants``), two per vehicle; each
vehicle runs the same three closed loops as the glider scenarios (the service's pipeline,
reference only, the oracle) through the same ``VehiclePipeline``. Setpoints are chosen per
plant from actuator positions, r = trim + DC·pump(u_level), so each is reachable and a
reference-only input exists; each plant gets its own oracle row.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hil_service.experiment.closed_loop import (
    ClosedLoopSettings,
    RunTrace,
    _drive,
    inverse_run,
    known_plant,
    oracle_run,
    score,
    setpoint_schedule,
)
from hil_service.experiment.oracle import KnownPlant, OracleSettings
from hil_service.pipeline import PipelineSettings
from plant_emulator.models import CHANNELS
from plant_emulator.random_plants import (
    RandomPlantSpec,
    RandomVehicle,
    RandomVehicleConfig,
    draw_family,
)
from protocols.samples import TelemetrySample

#: Actuator positions the setpoints are drawn from, as shares of the input limit; all beyond
#: the widest dead zone, so every step moves the output.
LEVEL_SHARES = (0.5, -0.35, 0.25, -0.175)
TRIMS = {"depth": 15.0, "pitch": 0.0}
DEFAULT_PLANTS = 20


def channel_levels(spec: RandomPlantSpec, limit: float, trim: float) -> tuple[float, ...]:
    pump = spec.pump()
    levels = []
    for share in LEVEL_SHARES:
        u = share * limit
        levels.append(trim + spec.dc_gain * (pump(u) if pump else u))
    return tuple(levels)


def oracle_settings_for(plant: KnownPlant) -> OracleSettings:
    """Horizon from the slowest pole (about five time constants, 20–600 samples), move
    blocks doubling to cover about half of it, a disturbance filter of a few samples (the
    random plants have no disturbance: it only absorbs round-off)."""
    radius = float(np.max(np.abs(np.linalg.eigvals(plant.a))))
    horizon = int(min(600, max(20, math.ceil(5.0 / max(1.0 - radius, 1e-3)))))
    blocks: list[int] = []
    size = 1
    while sum(blocks) + size <= horizon // 2 and len(blocks) < 12:
        blocks.append(size)
        if len(blocks) >= 2:
            size *= 2
    stride = max(1, horizon // 150)
    return OracleSettings(
        horizon=horizon, blocks=tuple(blocks), disturbance_tau=5.0, cost_stride=stride
    )


@dataclass
class PlantRow:
    """One plant's closed-loop figures."""

    vehicle: int
    channel: str
    spec: RandomPlantSpec
    inverse_iae: float
    reference_iae: float
    oracle_iae: float | None
    divergences: int
    non_finite_commands: int
    bound: float | None  # non-minimum-phase IAE bound on these steps

    @property
    def ratio(self) -> float | None:
        if self.oracle_iae is None or self.oracle_iae <= 0:
            return None
        return self.inverse_iae / self.oracle_iae

    @property
    def reference_ratio(self) -> float | None:
        if self.oracle_iae is None or self.oracle_iae <= 0:
            return None
        return self.reference_iae / self.oracle_iae

    def as_json(self) -> dict[str, Any]:
        return {
            "vehicle": self.vehicle,
            "channel": self.channel,
            "plant": self.spec.as_json(),
            "inverse_iae": round(self.inverse_iae, 4),
            "reference_only_iae": round(self.reference_iae, 4),
            "oracle_iae": None if self.oracle_iae is None else round(self.oracle_iae, 4),
            "iae_ratio_oracle": _round(self.ratio),
            "reference_only_ratio_oracle": _round(self.reference_ratio),
            "divergences": self.divergences,
            "non_finite_commands": self.non_finite_commands,
            "iae_lower_bound": _round(self.bound),
        }


def _round(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else round(value, 4)


@dataclass
class RandomResult:
    settings: ClosedLoopSettings
    plants: int
    rows: list[PlantRow] = field(default_factory=list)
    traces: list[dict[str, RunTrace | None]] = field(default_factory=list)
    blocked: int = 0
    oracle_failures: int = 0

    def ratios(self) -> list[float]:
        return [r.ratio for r in self.rows if r.ratio is not None]

    def summary(self) -> dict[str, Any]:
        ratios = self.ratios()
        finite = [r for r in ratios if math.isfinite(r)]
        return {
            "plants": len(self.rows),
            "median_ratio": _round(float(np.median(finite))) if finite else None,
            "max_ratio": _round(max(finite)) if finite else None,
            "above_2x": sum(r > 2.0 for r in finite),
            "divergences": sum(r.divergences for r in self.rows),
            "non_finite_commands": sum(r.non_finite_commands for r in self.rows),
            "blocked_steps": self.blocked,
            "oracle_failures": self.oracle_failures,
        }

    def as_json(self) -> dict[str, Any]:
        return {
            "scenario": "random",
            "samples": self.settings.samples,
            "seed": self.settings.seed,
            "identify": self.settings.identify,
            "summary": self.summary(),
            "plants": [r.as_json() for r in self.rows],
        }


def _reference_only_controller(
    schedule: dict[str, np.ndarray],
    specs: dict[str, RandomPlantSpec],
    knowns: dict[str, KnownPlant],
) -> Callable[[int, TelemetrySample], tuple[float, float]]:
    """The position whose steady state is the setpoint: pump⁻¹((r − trim) / DC gain)."""

    def control(k: int, sample: TelemetrySample) -> tuple[float, float]:
        out = []
        for ch in CHANNELS:
            target = (float(schedule[ch][k]) - TRIMS[ch]) / specs[ch].dc_gain
            out.append(knowns[ch].invert_pump(target, 0.0))
        return out[0], out[1]

    return control


def _bound(spec: RandomPlantSpec, step_total: float) -> float | None:
    if spec.zero is None:
        return None
    return spec.zero / (spec.zero - 1.0) * spec.period * step_total


def run_random_closed_loop(
    settings: ClosedLoopSettings,
    plants: int = DEFAULT_PLANTS,
    pipeline_settings: PipelineSettings | None = None,
) -> RandomResult:
    """Every vehicle of the family of ``settings.seed``: inverse, reference only, oracle."""
    settings = replace(settings, scenario="random")
    result = RandomResult(settings=settings, plants=plants)
    for v, (depth, pitch) in enumerate(draw_family(settings.seed, plants)):
        config = RandomVehicleConfig(depth=depth, pitch=pitch)
        specs = {"depth": depth, "pitch": pitch}
        levels = {ch: channel_levels(specs[ch], config.input_limit, TRIMS[ch]) for ch in CHANNELS}
        schedule = setpoint_schedule(settings, levels)
        reference_vehicle = RandomVehicle(config)
        knowns = {ch: known_plant(reference_vehicle, ch, TRIMS[ch]) for ch in CHANNELS}

        reference_only = _reference_only_controller(schedule, specs, knowns)

        inverse = inverse_run(settings, RandomVehicle(config), schedule, pipeline_settings)
        reference = _drive(settings, reference_vehicle, schedule, reference_only)
        oracle: RunTrace | None = None
        if settings.oracle:
            oracle, failures = oracle_run(
                settings,
                RandomVehicle(config),
                schedule,
                {ch: oracle_settings_for(knowns[ch]) for ch in CHANNELS},
                TRIMS,
            )
            result.oracle_failures += failures
        for run in (inverse.trace, reference, oracle):
            if run is not None:
                score(run, settings, config.period)
        result.blocked += inverse.blocked
        result.traces.append(
            {"inverse": inverse.trace, "reference_only": reference, "oracle": oracle}
        )
        for ch in CHANNELS:
            inv = inverse.trace.metrics[ch]
            result.rows.append(
                PlantRow(
                    vehicle=v,
                    channel=ch,
                    spec=specs[ch],
                    inverse_iae=inv.iae,
                    reference_iae=reference.metrics[ch].iae,
                    oracle_iae=None if oracle is None else oracle.metrics[ch].iae,
                    divergences=inverse.divergences[ch],
                    non_finite_commands=inverse.trace.non_finite_commands[ch],
                    bound=_bound(specs[ch], inv.step_total),
                )
            )
    return result
