"""A mission's scores: tracking of the HIL run against the offline yardsticks, the
identifier's fit and skill, and what went wrong. Pure: numbers in, a flat row out."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil_service.campaign.mission import Mission, Trace
from hil_service.experiment.closed_loop import step_metrics
from plant_emulator.models import CHANNELS

#: A run diverged when its output strays this many times the largest setpoint step from
#: the setpoint (after the first step has had ``step_every`` samples to settle), or is not
#: finite.
DIVERGENCE_FACTOR = 10.0

#: The columns of runs.csv, in order (per-channel ones are expanded for depth and pitch).
RUN_COLUMNS = (
    "scenario", "seed", "status", "reason", "steps", "wall_s", "cpu_s", "steps_per_s",
)  # fmt: skip
CHANNEL_COLUMNS = (
    "iae",
    "iae_reference",
    "iae_oracle",
    "ratio_reference",
    "ratio_oracle",
    "overshoot_pct",
    "settling_s",
    "fit_nmse",
    "skill",
    "divergences",
)
TAIL_COLUMNS = (
    "commands_sent",
    "commands_refused",
    "lockstep_timeouts",
    "oracle_failures",
    "log",
)


def columns() -> list[str]:
    per_channel = [f"{ch}_{name}" for ch in CHANNELS for name in CHANNEL_COLUMNS]
    return [*RUN_COLUMNS, *per_channel, *TAIL_COLUMNS]


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not b > 0 or not math.isfinite(a):
        return None
    return round(a / b, 4)


def _iae(trace: Trace, setpoint: np.ndarray, channel: str, mission: Mission) -> float | None:
    y = trace.y[channel]
    if not np.all(np.isfinite(y[mission.identify :])):
        return None
    metrics = step_metrics(y, setpoint, mission.identify, mission.settle_band, mission.period)
    return metrics.iae


def divergence(mission: Mission, trace: Trace, schedule: dict[str, np.ndarray]) -> str | None:
    """Why the HIL run counts as diverged, or None."""
    start = mission.identify + mission.step_every
    for ch in CHANNELS:
        y = trace.y[ch][mission.identify :]
        if not np.all(np.isfinite(y)):
            bad = mission.identify + int(np.flatnonzero(~np.isfinite(y))[0])
            return f"{ch} not finite at step {bad}"
        r = schedule[ch]
        levels = r[np.isfinite(r)]
        largest = float(np.max(np.abs(np.diff(levels)))) if levels.size > 1 else 1.0
        error = np.abs(trace.y[ch][start:] - r[start:])
        if error.size and float(np.max(error)) > DIVERGENCE_FACTOR * max(largest, 1e-9):
            k = start + int(np.argmax(error))
            return f"{ch} error {float(np.max(error)):.3g} at step {k}"
    return None


def score(
    mission: Mission,
    hil: Trace,
    reference: Trace | None,
    oracle: Trace | None,
    identifier: dict[str, Any],
) -> dict[str, Any]:
    """The per-channel columns of a finished run (values may be None)."""
    schedule = mission.schedule()
    row: dict[str, Any] = {}
    for ch in CHANNELS:
        setpoint = schedule[ch]
        y = hil.y[ch]
        finite = bool(np.all(np.isfinite(y[mission.identify :])))
        metrics = (
            step_metrics(y, setpoint, mission.identify, mission.settle_band, mission.period)
            if finite
            else None
        )
        iae = None if metrics is None else metrics.iae
        iae_ref = None if reference is None else _iae(reference, setpoint, ch, mission)
        iae_oracle = None if oracle is None else _iae(oracle, setpoint, ch, mission)
        health = identifier.get(ch, {})
        row.update(
            {
                f"{ch}_iae": None if iae is None else round(iae, 4),
                f"{ch}_iae_reference": None if iae_ref is None else round(iae_ref, 4),
                f"{ch}_iae_oracle": None if iae_oracle is None else round(iae_oracle, 4),
                f"{ch}_ratio_reference": _ratio(iae, iae_ref),
                f"{ch}_ratio_oracle": _ratio(iae, iae_oracle),
                f"{ch}_overshoot_pct": None
                if metrics is None or metrics.overshoot is None
                else round(metrics.overshoot, 2),
                f"{ch}_settling_s": None
                if metrics is None or metrics.settling_median is None
                else round(metrics.settling_median, 2),
                f"{ch}_fit_nmse": health.get("nmse"),
                f"{ch}_skill": health.get("skill"),
                f"{ch}_divergences": health.get("divergences"),
            }
        )
    return row
