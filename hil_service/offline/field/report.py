"""The identification section of ``report`` for a log imported from field data.

Reads the grid samples (``glider/{id}/telemetry``) and the segments the import stored
(``field`` in the configuration, docs/mcap.md), runs ``evaluate.identify_dives`` and writes
a table per channel (one-step skill, free-run fit per held-out dive, k-step NMSE, for
persistence, RLS-ARX, the U-model, the two-input U-model of depth and the
first-principles baseline), whether the input was excited enough, and a figure per model of
predicted vs actual over one held-out dive. The import's counts and its notes (a file cut
short, times before 1980, rows dropped: ``field.issues.notes``) head the section. A
stored ``field`` part that cannot be read (an ``issues`` or ``grid`` that is not an object,
a grid period that is not a number) is named in the section, and the identification is not
computed.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from hil_service.config import stored_pipeline
from hil_service.mcap.reader import LogReader
from hil_service.offline.field.evaluate import (
    GLIDE_U,
    PHYSICAL,
    Arrays,
    ChannelResult,
    ModelResult,
    Segment,
    identify_dives,
)
from hil_service.offline.series import telemetry_columns
from hil_service.pipeline import PipelineSettings
from protocols import keys
from protocols.payload_json import is_finite_number

UNITS = {"depth": "m", "pitch": "rad"}
#: The most import notes the report lists: an import notes every row it drops, and the
#: rest stay in the log's stored ``field.issues.notes``.
MAX_NOTES = 20


def field_arrays(log: str | Path, field: dict[str, Any], system_id: int = 1) -> Arrays:
    topic = keys.telemetry(system_id)
    rows = [m.json() for m in LogReader(log).messages({topic})]
    grid = field.get("grid") or {}
    segments = [
        Segment(int(s["dive"]), int(s["start"]), int(s["stop"])) for s in grid.get("segments", [])
    ]

    column = telemetry_columns(rows, ("depth", "pitch", "u_depth", "u_pitch"), log)
    return Arrays(
        float(grid.get("period_s", 1.0)),
        column["depth"],
        column["pitch"],
        column["u_depth"],
        column["u_pitch"],
        [s for s in segments if s.stop <= len(rows)],
        float(field.get("full_scale", 2.0)),
    )


def field_results(
    log: str | Path, config: dict[str, Any], system_id: int = 1, split: str = "first"
) -> tuple[Arrays, list[ChannelResult]]:
    """The grid samples of a field import and ``identify_dives`` on them with the log's
    pipeline settings (the model, its options, the seed)."""
    arrays = field_arrays(log, config["field"], system_id)
    stored = stored_pipeline(config)
    settings = PipelineSettings() if stored is None else PipelineSettings.from_json(stored)
    options = {ch: settings.options_for(ch) for ch in keys.CHANNELS}
    return arrays, identify_dives(arrays, settings.model, options, seed=settings.seed, split=split)


def _fmt(value: float | None, spec: str, why: str = "") -> str:
    if value is None or not math.isfinite(value):
        return f"– ({why})" if why else "–"
    return format(value, spec)


def _figure(path: Path, result: ChannelResult, model: ModelResult, period: float) -> Path | None:
    if model.trace is None:
        return None
    actual, one, sim = model.trace
    persistence = np.concatenate(([actual[0]], actual[:-1]))
    t = np.arange(actual.size) * period / 60.0
    fig = Figure(figsize=(10.0, 6.5), dpi=100, layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    unit = UNITS[result.channel]
    top.plot(t, actual, color="black", linewidth=1.2, label="actual")
    top.plot(t, sim, color="tab:red", linewidth=1.0, label=f"{model.model} free run")
    top.plot(
        t,
        np.full(actual.size, actual[0]),
        color="grey",
        linestyle=":",
        label="persistence free run",
    )
    top.set_ylabel(f"{result.channel} [{unit}]")
    if result.channel == "depth":
        top.invert_yaxis()
    top.legend(loc="best")
    top.set_title(
        f"free run (multi-step): fit {_fmt(_dive_fit(model, result.figure_dive), '.1f')} %"
    )
    bottom.plot(
        t, actual - one, color="tab:blue", linewidth=0.9, label=f"{model.model} one-step error"
    )
    bottom.plot(
        t,
        actual - persistence,
        color="grey",
        linewidth=0.9,
        linestyle="--",
        label="persistence one-step error",
    )
    bottom.axhline(0.0, color="black", linewidth=0.5)
    bottom.set_ylabel(f"y − ŷ [{unit}]")
    bottom.set_xlabel("time in the held-out dive [min]")
    bottom.legend(loc="best")
    for ax in (top, bottom):
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"{result.channel}, held-out dive {result.figure_dive}: {model.model} vs actual")
    fig.savefig(path)
    return path


def _dive_fit(model: ModelResult, dive: int | None) -> float | None:
    return next((d.fit for d in model.dives if d.dive == dive), None)


def field_section(
    log: str | Path, config: dict[str, Any], out: Path, system_id: int = 1
) -> tuple[list[str], list[Path], list[ChannelResult]]:
    """Markdown lines, figures and results of the field identification (nothing when the
    log is not a field import)."""
    field = config.get("field")
    if not isinstance(field, dict):
        return [], [], []
    what = " ".join(str(part) for part in (field.get("format"), field.get("vehicle")) if part)
    heading = ["", f"## Field identification ({what or 'format not stored'})"]
    unreadable = _unreadable(field)
    if unreadable:
        return (
            [*heading, "", f"Not computed: the log's stored {unreadable} ({log})."],
            [],
            [],
        )
    grid = field.get("grid") or {}
    issues = field.get("issues") or {}
    period = float(grid.get("period_s") or 0)
    spacing = f"grid {period:g} s" if period > 0 else "as recorded (no grid)"
    lines = [
        *heading,
        "",
        f"- {_count(field.get('files', []))} file(s){_skipped(issues)}; "
        f"{issues.get('rows', '–')} rows; "
        f"{issues.get('out_of_order', 0)} out of order, {issues.get('repeated_time', 0)} "
        f"repeated timestamps, {issues.get('nan_rows', 0)} NaN rows, "
        f"{issues.get('unparsable_rows', 0)} unparsable, {issues.get('out_of_range', 0)} out "
        f"of range, {issues.get('filled_inputs', 0)} "
        f"inputs held, {issues.get('surface_rows', 0)} at the surface; missing columns: "
        f"{issues.get('missing_columns') or 'none'}",
        f"- {spacing}, segments split at gaps > {grid.get('gap_s')} s: "
        f"{grid.get('grid_samples')} samples in {_count(grid.get('segments', []))} segments; "
        f"{grid.get('raw_used')} of {grid.get('raw_in_dive')} in-dive samples used "
        f"({_percent(grid.get('used_fraction', 0))} %); {grid.get('interpolated')} grid "
        f"samples interpolated (linear, at most {grid.get('max_distance_s')} s from a raw "
        f"sample); not used: {grid.get('lost') or 'none'}",
        *_note_lines(issues.get("notes"), log),
    ]
    if not period > 0:
        return (
            [
                *lines,
                "",
                "Identification per dive not computed: the log holds the samples as recorded "
                "(`--as-recorded`), at varying steps; the models need a uniform grid (import "
                "without `--as-recorded`).",
            ],
            [],
            [],
        )
    try:
        arrays, results = field_results(log, config, system_id)
    except (ValueError, KeyError, TypeError) as error:
        return [*lines, "", f"Identification not computed: {error}"], [], []
    figures: list[Path] = []
    for result in results:
        lines += _channel_lines(result, arrays.period)
        for model in result.models:
            name = f"field_{result.channel}_{model.model}.png"
            path = _figure(out / name, result, model, arrays.period)
            if path is not None:
                figures.append(path)
                lines.append(f"![{result.channel} {model.model}]({name})")
    return lines, figures, results


def _skipped(issues: dict[str, Any]) -> str:
    """What follows the count of files read when the import skipped some ("13 file(s) read,
    1 that could not be read skipped"); "" when it skipped none."""
    skipped = issues.get("unreadable_files")
    if not skipped or not isinstance(skipped, dict):
        return ""
    return f" read, {len(skipped)} that could not be read skipped"


def _unreadable(field: dict[str, Any]) -> str:
    """What of a field import's stored ``field`` the section cannot read ("" when it can)."""
    for name in ("grid", "issues"):
        value = field.get(name)
        if value is not None and not isinstance(value, dict):
            return f"field.{name} is not an object"
    period = (field.get("grid") or {}).get("period_s")
    if period is not None and not is_finite_number(period):
        return "field.grid.period_s is not a number"
    return ""


def _note_lines(notes: Any, log: str | Path) -> list[str]:
    """The import's notes (a file cut short, times before 1980, a row dropped, ...) as an
    "Import notes" list, the first ``MAX_NOTES`` of them; nothing when there are none."""
    if not isinstance(notes, list) or not notes:
        return []
    lines = ["", "Import notes:", ""]
    lines += [f"- {note}" for note in notes[:MAX_NOTES]]
    if len(notes) > MAX_NOTES:
        lines.append(
            f"- ... and {len(notes) - MAX_NOTES} more (all in `glider-hil info {log}`, "
            "field.issues.notes)"
        )
    return lines


def _count(items: Any) -> str:
    return str(len(items)) if isinstance(items, list) else "–"


def _percent(fraction: Any) -> str:
    return f"{100 * fraction:.1f}" if is_finite_number(fraction) else "–"


def _channel_lines(result: ChannelResult, period: float) -> list[str]:
    ex = result.excitation
    held = result.held_out
    lines = [
        "",
        f"### {result.channel.capitalize()}",
        "",
        f"Trained on dives {result.train_dives[0]}–{result.train_dives[-1]}, scored on "
        f"{held[0]}–{held[-1]}; k = {result.horizon} samples ({result.horizon * period:g} s).",
        f"Input excitation over the training dives: std {100 * ex.std:.1f} % of full scale, "
        f"{ex.moves:.1f} moves per dive, regressor rcond {ex.rcond:.2g}: "
        f"**{'excited enough' if ex.excited else 'not excited enough: ' + ex.why}**.",
        "",
        "| model | one-step skill | mean free-run fit % | k-step NMSE | "
        + " | ".join(f"fit % dive {d}" for d in held)
        + " |",
        "|---|---:|---:|---:|" + "---:|" * len(held),
    ]
    for model in result.models:
        cells = []
        for dive in held:
            score = next((d for d in model.dives if d.dive == dive), None)
            cells.append("–" if score is None else _fmt(score.fit, ".1f", score.why))
        lines.append(
            f"| {model.model} | {_fmt(model.skill, '.4f', model.why)} | "
            f"{_fmt(model.fit, '.1f', model.why)} | {_fmt(model.k_step_nmse, '.3g', model.why)} | "
            + " | ".join(cells)
            + " |"
        )
    physical = next((m for m in result.models if m.model == PHYSICAL[result.channel]), None)
    if physical is not None and physical.parameters:
        text = ", ".join(f"{k} {v:.4g}" for k, v in physical.parameters.items())
        lines += ["", f"{physical.model} parameters (least squares on the training dives): {text}"]
    glide = next((m for m in result.models if m.model == GLIDE_U), None)
    if glide is not None and glide.parameters:
        numbers = {k: v for k, v in glide.parameters.items() if isinstance(v, float)}
        text = ", ".join(f"{k} {v:.4g}" for k, v in numbers.items())
        lines += [
            "",
            f"{GLIDE_U} (buoyancy input and measured pitch), structure "
            f"{glide.parameters.get('structure', '–')}, parameters after the training "
            f"dives: {text}",
        ]
        choice = glide.parameters.get("structure_choice")
        if isinstance(choice, dict):
            lines.append(_structure_line(choice))
    return lines


def _structure_line(choice: dict[str, Any]) -> str:
    """How the glide-u structure was chosen and each candidate's median fit; when no
    training dive validated any candidate (too few dives long enough, or no fit), that and
    why, in place of a list of empty fits."""
    fits = choice.get("median_fit")
    fits = fits if isinstance(fits, dict) else {}
    folds = choice.get("folds") or []
    held = f"; held out in turn: {folds}" if folds else ""
    if not any(is_finite_number(v) for v in fits.values()):
        return (
            f"Structure not validated: no training dive validated a candidate "
            f"({choice.get('why')}{held}); median free-run fit %: none."
        )
    scores = ", ".join(f"{k} {_fmt(v, '.1f')}" for k, v in fits.items())
    return (
        f"Structure chosen on the training dives only ({choice.get('why')}{held}); "
        f"median free-run fit %: {scores}."
    )
