"""``experiment --closed-loop --scenario family``: the controller on a seeded family of
vehicles it was not designed on (``plant_emulator.family``).

Per plant: IAE of the service's pipeline, of reference-only (the input whose steady state
is the setpoint, from the true plant) and of the oracle (a constrained receding-horizon
controller that knows the linear plant, its delay and its input map; none for Wiener
plants, whose output map it cannot represent), the supervisor's trips, whether the
horizon test ever passed and how many samples the channel commanded. Setpoints come from
actuator positions through the true plant, so each is reachable.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hil_service.experiment.closed_loop import (
    ClosedLoopSettings,
    InverseRun,
    RunTrace,
    _drive,
    inverse_run,
    oracle_run,
    score,
    setpoint_schedule,
)
from hil_service.experiment.oracle import KnownPlant, identity
from hil_service.experiment.random_loop import LEVEL_SHARES, oracle_settings_for
from hil_service.pipeline import PipelineSettings
from plant_emulator.family import (
    INPUT_LIMIT,
    RATE_LIMIT,
    FamilyPlantSpec,
    FamilyVehicle,
    draw_family,
)
from plant_emulator.models import CHANNELS
from protocols.samples import TelemetrySample

DEFAULT_PLANTS = 200
#: The target: no plant's IAE above this times reference-only's.
HARM_LIMIT = 1.1


def levels(spec: FamilyPlantSpec) -> tuple[float, ...]:
    return tuple(
        spec.offset + spec.scale * spec.wiener_map(spec.dc_gain * spec.input_map(s * INPUT_LIMIT))
        for s in LEVEL_SHARES
    )


def known(spec: FamilyPlantSpec) -> KnownPlant:
    model = spec.channel_model()
    return KnownPlant(
        a=np.array(model.a_cl, dtype=float),
        b=np.array(model.b_cl, dtype=float),
        c=np.array(model.c_cl, dtype=float) * spec.scale,
        d=0.0,
        trim=spec.offset,
        pump=identity if spec.input_map.identity else spec.input_map,
        u_limit=INPUT_LIMIT,
        rate_limit=RATE_LIMIT,
    )


@dataclass
class FamilyRow:
    spec: FamilyPlantSpec
    inverse_iae: float
    reference_iae: float
    oracle_iae: float | None
    trips: int
    horizon_passed: bool
    commanded: int
    #: The pipeline's IAE split by what the channel did (``phase_iae``).
    phases: dict[str, float] = field(default_factory=dict)
    #: The family's seed (with ``spec.vehicle`` and ``spec.channel``: which plant it is).
    seed: int | None = None

    def name(self) -> str:
        """Where to find the plant again: ``seed S vehicle V channel`` (``seed ?`` for a
        row without its seed)."""
        seed = "?" if self.seed is None else self.seed
        return f"seed {seed} vehicle {self.spec.vehicle} {self.spec.channel}"

    @property
    def reference_ratio(self) -> float | None:
        return self.inverse_iae / self.reference_iae if self.reference_iae > 0 else None

    @property
    def oracle_ratio(self) -> float | None:
        if self.oracle_iae is None or not self.oracle_iae > 0:
            return None
        return self.inverse_iae / self.oracle_iae

    def as_json(self) -> dict[str, Any]:
        return {
            "plant": self.spec.as_json(),
            "inverse_iae": _round(self.inverse_iae),
            "reference_only_iae": _round(self.reference_iae),
            "oracle_iae": _round(self.oracle_iae),
            "iae_ratio_reference_only": _round(self.reference_ratio),
            "iae_ratio_oracle": _round(self.oracle_ratio),
            "trips": self.trips,
            "horizon_passed": self.horizon_passed,
            "commanded": self.commanded,
            "iae_phases": {k: _round(v) for k, v in self.phases.items()},
        }


#: The phases of ``phase_iae``: before the channel first commands, while it commands,
#: after a trip (its safe input, or released), held by a gate after having commanded.
PHASES = ("before", "commanded", "tripped", "held")


def phase_iae(
    modes: list[str], index: int, y: np.ndarray, setpoint: np.ndarray, start: int, period: float
) -> dict[str, float]:
    """The IAE of samples ``start`` … split by the channel's mode (``index`` in the
    decision's ``mode``) on the sample before: the command that sample sent acts on it."""
    out = dict.fromkeys(PHASES, 0.0)
    started = False
    for i, mode in enumerate(modes):
        k = start + i + 1
        if k >= y.size:
            break
        path = mode.split("/")[index] if mode else "-"
        if path in ("safe", "released"):
            phase = "tripped"
        elif path == "-":
            phase = "held" if started else "before"
        else:
            started = True
            phase = "commanded"
        out[phase] += abs(float(y[k] - setpoint[k])) * period
    out["before"] += abs(float(y[start] - setpoint[start])) * period
    return out


def _round(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(f"{value:.6g}")


@dataclass
class FamilyResult:
    settings: ClosedLoopSettings
    plants: int
    rows: list[FamilyRow] = field(default_factory=list)
    oracle_failures: int = 0

    def summary(self) -> dict[str, Any]:
        ref = [r.reference_ratio for r in self.rows if r.reference_ratio is not None]
        passed = [r for r in self.rows if r.horizon_passed]
        oracle = [r.oracle_ratio for r in passed if r.oracle_ratio is not None]
        worst = max(self.rows, key=lambda r: r.reference_ratio or 0.0) if self.rows else None
        return {
            "plants": len(self.rows),
            "worst_ratio_reference_only": _round(max(ref)) if ref else None,
            "worst_plant": None if worst is None else worst.spec.describe(),
            "above_harm_limit": sum(r > HARM_LIMIT for r in ref),
            "median_ratio_oracle_where_passed": _round(float(np.median(oracle)))
            if oracle
            else None,
            "oracle_rows_where_passed": len(oracle),
            "horizon_passed": len(passed),
            "controlled": sum(r.commanded > 0 for r in self.rows),
            "share_controlled": _round(sum(r.commanded > 0 for r in self.rows) / len(self.rows))
            if self.rows
            else None,
            "trips": sum(r.trips for r in self.rows),
            "oracle_failures": self.oracle_failures,
        }

    def as_json(self) -> dict[str, Any]:
        return {
            "scenario": "family",
            "samples": self.settings.samples,
            "seed": self.settings.seed,
            "identify": self.settings.identify,
            "summary": self.summary(),
            "plants": [r.as_json() for r in self.rows],
        }


#: What a channel the service does not command gets in the simulation (``released``):
#: "hold" — the vehicle holds its input (neutral after the excitation), as the
#: emulator's does; "vehicle" — the vehicle's own controller takes the channel back:
#: reference-only, from the sample the service stops commanding it (and a tripped
#: channel's safe input is "release"). docs/control.md, "What a vehicle does when the
#: service does not command".
RELEASED = ("hold", "vehicle")


def run_family_closed_loop(
    settings: ClosedLoopSettings,
    plants: int = DEFAULT_PLANTS,
    pipeline_settings: PipelineSettings | None = None,
    released: str = "hold",
) -> FamilyResult:
    settings = replace(settings, scenario="family", neutral_after_identify=True)
    result = FamilyResult(settings=settings, plants=plants)
    for depth, pitch in draw_family(settings.seed, plants):
        rows, failures = run_vehicle(settings, depth, pitch, pipeline_settings, released)
        result.rows += rows
        result.oracle_failures += failures
    return result


def run_vehicle(
    settings: ClosedLoopSettings,
    depth: FamilyPlantSpec,
    pitch: FamilyPlantSpec,
    pipeline_settings: PipelineSettings | None = None,
    released: str = "hold",
) -> tuple[list[FamilyRow], int]:
    """One vehicle's three runs: its two rows and the oracle's failed LP solves."""
    if released not in RELEASED:
        raise ValueError(f"released must be one of {RELEASED}, got {released!r}")
    specs = {"depth": depth, "pitch": pitch}
    schedule = setpoint_schedule(settings, {ch: levels(specs[ch]) for ch in CHANNELS})
    reference_only = reference_only_controller(specs, schedule)
    if released == "vehicle":
        base = pipeline_settings or PipelineSettings(seed=settings.seed)
        pipeline_settings = base.replace(
            control=dataclasses.replace(base.control, safe_input="release")
        )
    inverse = inverse_run(
        settings,
        FamilyVehicle(depth, pitch, settings.seed),
        schedule,
        pipeline_settings,
        reference_only if released == "vehicle" else None,
    )
    reference = _drive(
        settings, FamilyVehicle(depth, pitch, settings.seed), schedule, reference_only
    )
    oracle, failures = _oracle(settings, specs) if settings.oracle else (None, 0)
    for run in (inverse.trace, reference, oracle):
        if run is not None:
            score(run, settings, depth.period)
    rows = [
        _row(settings, specs[ch], i, inverse, reference, oracle) for i, ch in enumerate(CHANNELS)
    ]
    return rows, failures


def reference_only_controller(
    specs: dict[str, FamilyPlantSpec], schedule: dict[str, np.ndarray]
) -> Callable[[int, TelemetrySample], tuple[float, float]]:
    """Reference-only: at each sample, the true plant's static inverse of the setpoint
    (through its Wiener and input maps), no feedback."""
    knowns = {ch: known(specs[ch]) for ch in CHANNELS}

    def reference_only(k: int, sample: TelemetrySample) -> tuple[float, float]:
        out = []
        for ch in CHANNELS:
            spec = specs[ch]
            linear = spec.wiener_inverse((float(schedule[ch][k]) - spec.offset) / spec.scale)
            out.append(knowns[ch].invert_pump(linear / spec.dc_gain, 0.0))
        return out[0], out[1]

    return reference_only


def _oracle(
    settings: ClosedLoopSettings, specs: dict[str, FamilyPlantSpec]
) -> tuple[RunTrace, int]:
    """The oracle's run in the plant's own units (scale 1, offset 0: its LP and settings
    are ``random_loop``'s, made for outputs of order one; the problem is the same in any
    unit, so its IAE scales with the output and ``_row`` multiplies it back), and its
    failed LP solves."""
    plain = {ch: dataclasses.replace(specs[ch], scale=1.0, offset=0.0) for ch in CHANNELS}
    plain_known = {ch: known(plain[ch]) for ch in CHANNELS}
    return oracle_run(
        settings,
        FamilyVehicle(plain["depth"], plain["pitch"], settings.seed),
        setpoint_schedule(settings, {ch: levels(plain[ch]) for ch in CHANNELS}),
        {ch: oracle_settings_for(plain_known[ch]) for ch in CHANNELS},
        {ch: 0.0 for ch in CHANNELS},
    )


def _row(
    settings: ClosedLoopSettings,
    spec: FamilyPlantSpec,
    index: int,
    inverse: InverseRun,
    reference: RunTrace,
    oracle: RunTrace | None,
) -> FamilyRow:
    """One channel's row (``index`` in the decisions' ``mode``)."""
    ch = spec.channel
    supervision = inverse.supervision[ch]
    trace = inverse.trace
    oracle_iae = None
    if oracle is not None and spec.wiener == 0.0:
        oracle_iae = oracle.metrics[ch].iae * spec.scale
    return FamilyRow(
        spec=spec,
        inverse_iae=trace.metrics[ch].iae,
        reference_iae=reference.metrics[ch].iae,
        oracle_iae=oracle_iae,
        trips=supervision["trips"],
        horizon_passed=supervision["horizon_passed"],
        commanded=supervision["commanded"],
        phases=phase_iae(
            inverse.modes,
            index,
            trace.y[ch],
            trace.setpoint[ch],
            settings.identify,
            spec.period,
        ),
        seed=settings.seed,
    )
