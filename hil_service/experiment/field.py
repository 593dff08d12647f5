"""``glider-hil experiment --log``: the identification experiment on a log's recorded samples.

The emulator experiment (``experiment/identification.py``) runs every model on a plant it
drives; this one runs them on what a vehicle recorded: a field import (``glider-hil import``
of a Seaglider, SeaExplorer, Slocum or mapped CSV/Parquet data set) or any log of the
project's layout (a ``serve`` or ``emulate`` recording, an imported tlog).

The samples are split into training and scored parts as the field report splits them
(``offline/field/evaluate.identify_dives``): a field import by its dives (``--split first``,
the first half trains; ``alternate``, every other dive trains; ``both``); any other log by
its contiguous runs of samples (a step longer than 1.5 of the median step, or back in
time, ends a run), a log of one run cut into two halves, the first training. Every model
of the emulator experiment (``paper``, ``dynamic``, ``rls-arx``, ``persistence``) and the
field models (the two-input ``glide-u``, the steady-glide flight model and its
buoyancy-only form for depth, the static moment balance for pitch) is trained on the
training part, frozen, and scored on each scored part: one-step skill against persistence,
free-run fit % and k-step NMSE (k = ``horizon_s`` of samples, 300 s by default).

A log that was cut short or damaged is used as far as it can be read; what the reader
found (``ReadReport.describe``) is kept as the experiment's ``recovery``.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.config import ServiceConfig, shown_json
from hil_service.mcap.reader import LogError, LogReader
from hil_service.offline.field.evaluate import (
    SPLITS,
    Arrays,
    ChannelResult,
    Segment,
    identify_dives,
)
from hil_service.offline.field.report import field_arrays
from hil_service.offline.series import telemetry_columns
from hil_service.pipeline import PipelineSettings
from hil_service.umodel import paper_preset
from protocols import keys
from protocols.payload_json import is_finite_number

#: The emulator experiment's models beside the log's own (``dynamic`` by default).
EXTRA_MODELS = {"paper": paper_preset}
RUN_BREAK = 1.5  # a step longer than this many median steps ends a run


@dataclass
class FieldExperiment:
    log: str
    source: str  # "field import (<format>)" or "recorded samples"
    split: str
    samples: int
    period: float
    runs: int
    results: list[ChannelResult]
    #: What reading the log found when it was not finished or lost chunks ("": intact).
    recovery: str = ""

    def as_json(self) -> dict[str, Any]:
        recovery = {"recovery": self.recovery} if self.recovery else {}
        return {
            "log": self.log,
            "source": self.source,
            "split": self.split,
            "samples": self.samples,
            "period_s": self.period,
            "runs": self.runs,
            "channels": {
                r.channel: {
                    "train": r.train_dives,
                    "scored": r.held_out,
                    "horizon": r.horizon,
                    "excited": r.excitation.excited,
                    "excitation": r.excitation.why,
                    "models": {
                        m.model: {
                            "skill": _finite(m.skill),
                            "fit": _finite(m.fit),
                            "k_step_nmse": _finite(m.k_step_nmse),
                            "fits": [_finite(d.fit) for d in m.dives],
                            "why": m.why,
                        }
                        for m in r.models
                    },
                }
                for r in self.results
            },
            **recovery,
        }


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def recorded_arrays(log: str | Path, system_id: int = 1) -> Arrays:
    """The telemetry of a log that is not a field import, cut into its contiguous runs."""
    rows = [m.json() for m in LogReader(log).messages({keys.telemetry(system_id)})]
    if len(rows) < 8:
        raise ValueError(f"{log}: {len(rows)} telemetry samples of vehicle {system_id}, 8 needed")

    column = telemetry_columns(rows, ("t", "depth", "pitch", "u_depth", "u_pitch"), log)
    t = column["t"]
    steps = np.diff(t)
    forward = steps[np.isfinite(steps) & (steps > 0)]
    if forward.size == 0:
        raise ValueError(f"{log}: the telemetry's time never advances")
    period = float(np.median(forward))
    breaks = [0, *(np.flatnonzero(~((steps > 0) & (steps <= RUN_BREAK * period))) + 1), len(t)]
    runs = [(a, b) for a, b in itertools.pairwise(breaks) if b - a >= 2]
    if len(runs) == 1:  # one run: its first half trains, the second is scored
        a, b = runs[0]
        runs = [(a, (a + b) // 2), ((a + b) // 2, b)]
    segments = [Segment(i, a, b) for i, (a, b) in enumerate(runs)]
    return Arrays(
        period, column["depth"], column["pitch"], column["u_depth"], column["u_pitch"], segments
    )


def run_field_experiment(
    log: str | Path, split: str = "first", horizon_s: float = 300.0, system_id: int = 1
) -> FieldExperiment:
    path = Path(log)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
    try:
        reader = LogReader(path)
        for _ in reader.messages({keys.telemetry(system_id)}):
            pass  # the configuration is read with the messages
        config = reader.config()
    except LogError as error:
        raise ValueError(str(error)) from error
    report = reader.report
    recovery = "" if report.intact else report.describe()
    service = ServiceConfig.from_stored(config, path)  # StoredConfigError is a ValueError
    settings = PipelineSettings() if service is None else service.pipeline
    field = config.get("field")
    if isinstance(field, dict):
        grid = field.get("grid")
        period = grid.get("period_s") if isinstance(grid, dict) else None
        if period is not None and not is_finite_number(period):
            raise ValueError(
                f"{log}: stored config field.grid.period_s: expected a number, "
                f"got {shown_json(period)}"
            )
        if not (period or 0) > 0:
            raise ValueError(
                f"{log}: imported --as-recorded (no uniform grid); the models need the grid "
                "(import without --as-recorded)"
            )
        arrays = field_arrays(path, field, system_id)
        source = f"field import ({field.get('format')})"
    else:
        arrays = recorded_arrays(path, system_id)
        source = "recorded samples"
    options = {ch: settings.options_for(ch) for ch in keys.CHANNELS}
    results = identify_dives(
        arrays,
        settings.model,
        options,
        horizon_s=horizon_s,
        seed=settings.seed,
        split=split,
        extra_models={name: make for name, make in EXTRA_MODELS.items() if name != settings.model},
    )
    return FieldExperiment(
        str(path),
        source,
        split,
        sum(s.stop - s.start for s in arrays.segments),
        arrays.period,
        len(arrays.segments),
        results,
        recovery,
    )


def field_table(experiments: list[FieldExperiment]) -> str:
    lines: list[str] = []
    for e in experiments:
        lines += [
            f"{e.log}: {e.source}, {e.samples} samples every {e.period:g} s in {e.runs} "
            f"dives/runs, split {e.split}; models trained on the training part and frozen; "
            f"one-step skill vs persistence, free-run fit % and k-step NMSE on the scored part",
            f"{'channel':7s} {'model':28s} {'skill':>10s} {'fit %':>8s} {'k':>4s} "
            f"{'k-step NMSE':>12s}  fit % per scored dive/run",
        ]
        for r in e.results:
            lines.append(
                f"{r.channel:7s} trained on {r.train_dives}, scored on {r.held_out}; input "
                f"{'excited enough' if r.excitation.excited else 'not excited enough: '}"
                f"{'' if r.excitation.excited else r.excitation.why}"
            )
            for m in r.models:
                fits = " ".join(_fmt(d.fit, ".1f") for d in m.dives)
                lines.append(
                    f"{r.channel:7s} {m.model:28s} {_fmt(m.skill, '.4f'):>10s} "
                    f"{_fmt(m.fit, '.1f'):>8s} {r.horizon:>4d} {_fmt(m.k_step_nmse, '.4g'):>12s}"
                    f"  {fits}{'  (' + m.why + ')' if m.why else ''}"
                )
        lines.append("")
    return "\n".join(lines).rstrip()


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None or not math.isfinite(value) else format(value, spec)
