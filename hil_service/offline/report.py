"""A report from a service log: scores per vehicle and channel, figures, ``report.md``.

A vehicle that rebooted during the log restarted its clock: the report covers every run of
it (a segment). Scores are over all segments; the figures put the segments one after
another on a clock that runs on (a segment starts one step after the previous one ended),
with each restart marked, so a log without a restart is drawn on its own clock unchanged.

The scores use the settings the log stores (burn-in, the model to re-identify): a stored
configuration that cannot be read is refused (``StoredConfigError``), never replaced by the
defaults; a log that stores none is scored with the default burn-in, which ``report.md``
states as it states any.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.config import ServiceConfig, stored_pipeline
from hil_service.offline.field.report import field_section
from hil_service.offline.identify import has_estimates, identify_offline
from hil_service.offline.plots import UNITS, prediction_figure, tracking_figure
from hil_service.offline.series import LogSeries, VehicleSeries, load_series
from hil_service.pipeline import PipelineSettings, VehiclePipeline
from hil_service.umodel import from_config
from hil_service.umodel.multistep import (
    CONVERGENCE_BAND,
    MultiStepScores,
    control_horizon,
    converged_at,
    longest_contiguous,
    multistep_scores,
)
from hil_service.umodel.scoring import ErrorStats
from protocols.keys import CHANNELS

DEFAULT_BURN_IN = 300


@dataclass(frozen=True)
class ChannelSummary:
    system_id: int
    channel: str
    model: str
    samples: int
    nmse: float | None
    skill: float | None
    converged_at: int | None  # sample index, None when the error never settled in the band
    commands: int
    tracking_mae: float | None  # mean |y − setpoint| over commanded samples
    tracking_rms: float | None
    # Free-run fit (%) and k-step NMSE of the logged model re-identified on the first half
    # of the longest gap-free stretch and frozen (hil_service/umodel/multistep.py).
    fit: float | None = None
    k_step_nmse: float | None = None
    horizon: int | None = None
    segments: int = 1  # runs of the vehicle's clock (restarts + 1)


@dataclass(frozen=True)
class Report:
    markdown: Path
    figures: list[Path]
    summaries: list[ChannelSummary]
    #: True when the log held no estimates (an imported tlog) and its telemetry was run
    #: through the identifier here (``hil_service.offline.identify``).
    offline: bool = False
    #: A field import's dive-by-dive identification (``hil_service.offline.field.report``).
    field: list[Any] = dataclasses.field(default_factory=list)


OFFLINE_NOTE = (
    "- identified offline: the log holds no estimate records (an imported telemetry log), so "
    "its raw frames were run through the service's path as `glider-hil replay` runs them, "
    "with the profile and configuration the log stores; no commands were sent"
)


def _burn_in(config: ServiceConfig | None) -> int:
    """The burn-in the service ran with (the default for a log that stores no configuration)."""
    return DEFAULT_BURN_IN if config is None else config.pipeline.burn_in


@dataclass(frozen=True)
class Segment:
    """One run of a vehicle's clock: telemetry_t[start:stop]."""

    start: int
    stop: int
    t_first: float
    t_last: float


def segments(vehicle: VehicleSeries) -> list[Segment]:
    starts = vehicle.segment_starts or ([0] if vehicle.telemetry_t else [])
    stops = [*starts[1:], len(vehicle.telemetry_t)]
    t = vehicle.telemetry_t
    return [Segment(a, b, t[a], t[b - 1]) for a, b in zip(starts, stops, strict=True) if b > a]


def running_clock(vehicle: VehicleSeries) -> tuple[np.ndarray, list[float]]:
    """Each telemetry record's time on a clock that runs on across restarts, and where on
    it each restart is. A segment starts one typical step after the previous one ended."""
    t = np.asarray(vehicle.telemetry_t, dtype=float)
    clock = t.copy()
    parts = segments(vehicle)
    steps = np.concatenate([np.diff(t[p.start : p.stop]) for p in parts] or [np.zeros(0)])
    step = float(np.median(steps)) if steps.size else 0.0
    restarts: list[float] = []
    for previous, part in itertools.pairwise(parts):
        offset = clock[previous.stop - 1] + step - t[part.start]
        clock[part.start : part.stop] += offset
        restarts.append(float(clock[part.start]) - step / 2)
    return clock, restarts


def _on_samples(indexes: list[int], values: list[float], size: int) -> np.ndarray:
    """Values tied to telemetry positions, as an array over all telemetry (NaN elsewhere)."""
    aligned = np.full(size, np.nan)
    for k, value in zip(indexes, values, strict=True):
        if 0 <= k < size:
            aligned[k] = value
    return aligned


#: Fewer gap-free samples than this and the multi-step figures are not computed.
MIN_FIT_SAMPLES = 40


def multistep_from_log(
    vehicle: VehicleSeries, channel: str, config: dict[str, Any]
) -> MultiStepScores | None:
    """The multi-step figures of the model the log's configuration describes, or None.

    The model is rebuilt from the stored pipeline settings (same seed and options as the
    service's), on the applied inputs (telemetry) and the outputs the identifier saw.
    """
    stored = stored_pipeline(config)
    if stored is None:
        return None
    try:
        settings = PipelineSettings.from_json(stored)
        model_config = VehiclePipeline(settings).configs()[channel]
        # The horizon the service's controller derived at run time (its last health), else
        # the default of the experiment.
        horizon = recorded_horizon(vehicle, channel) or control_horizon(channel)
    except (TypeError, ValueError, KeyError, AttributeError):
        return None
    outputs = dict(zip(vehicle.channels[channel].t, vehicle.channels[channel].y, strict=True))
    rows = [
        (t, outputs[t], u)
        for t, u in zip(vehicle.telemetry_t, vehicle.applied[channel], strict=True)
        if t in outputs and math.isfinite(outputs[t]) and math.isfinite(u)
    ]
    start, stop = longest_contiguous([r[0] for r in rows])
    n = stop - start
    if n < MIN_FIT_SAMPLES:
        return None
    y = np.array([r[1] for r in rows[start:stop]])
    u = np.array([r[2] for r in rows[start:stop]])
    k = max(1, min(int(horizon), n // 8))
    return multistep_scores(lambda: from_config(model_config), u, y, n // 2, k)


def _health_identifier(vehicle: VehicleSeries, channel: str) -> dict[str, Any]:
    """The channel's ``identifier`` entry of the last recorded health, or {}."""
    identifier = (vehicle.last_health or {}).get("identifier")
    entry = identifier.get(channel) if isinstance(identifier, dict) else None
    return entry if isinstance(entry, dict) else {}


def recorded_horizon(vehicle: VehicleSeries, channel: str) -> int | None:
    """The multi-step horizon the service last reported for ``channel`` (health's
    ``multistep_horizon``), or None in a log without it."""
    horizon = _health_identifier(vehicle, channel).get("multistep_horizon")
    if isinstance(horizon, int) and not isinstance(horizon, bool) and horizon >= 1:
        return horizon
    return None


def _multistep_health_lines(vehicle: VehicleSeries) -> list[str]:
    """The service's own rolling multi-step accuracy (last health), per channel."""
    lines = []
    for channel in CHANNELS:
        entry = _health_identifier(vehicle, channel)
        if "multistep_fit" not in entry and "multistep_nmse" not in entry:
            continue
        fit, nmse = _number(entry.get("multistep_fit")), _number(entry.get("multistep_nmse"))
        horizon = recorded_horizon(vehicle, channel)
        lines.append(
            f"- {channel}: free-run fit {_fmt(fit, '.1f')} %, NMSE {_fmt(nmse, '.4g')}, free runs "
            f"restarted every {_fmt(horizon, 'd')} samples (one-step skill "
            f"{_fmt(_number(entry.get('skill')), '.3f')})"
        )
    if not lines:
        return []
    return [
        "",
        "### Multi-step accuracy, as the service measured it",
        "",
        "Last health: a frozen copy of the model run free on the applied inputs, restarted "
        "from the measured outputs every control horizon, over the last window "
        "(`scoring.MultiStepStats`, the same formulas as the table's).",
        "",
        *lines,
    ]


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def summarise(
    vehicle: VehicleSeries, channel: str, burn_in: int, config: dict[str, Any] | None = None
) -> ChannelSummary:
    series = vehicle.channels[channel]
    data = series.arrays()
    stats = ErrorStats(burn_in=burn_in)
    for y, y_hat, base, status in zip(
        data["y"], data["y_hat"], data["baseline_y_hat"], series.status, strict=True
    ):
        if status in ("rejected", "diverged") or not math.isfinite(base):
            continue
        stats.add(float(y), float(y - y_hat), float(y - base))
    error = data["y"] - data["y_hat"]
    # The output of the sample each command answered, matched by position in the log (a
    # time alone is ambiguous once the vehicle's clock restarted).
    outputs = {k: y for k, y in zip(series.index, series.y, strict=True) if k >= 0}
    gaps = []
    commands = vehicle.commands
    for k, setpoint in zip(commands.index, commands.setpoint[channel], strict=True):
        y = outputs.get(k)
        if y is not None and math.isfinite(setpoint):
            gaps.append(y - setpoint)
    gap = np.asarray(gaps)
    return ChannelSummary(
        system_id=vehicle.system_id,
        channel=channel,
        model=series.model or "-",
        samples=len(series.t),
        nmse=stats.nmse(),
        skill=stats.skill(),
        converged_at=converged_at(error, data["y"]) if error.size else None,
        commands=sum(math.isfinite(u) for u in commands.u[channel]),
        tracking_mae=float(np.mean(np.abs(gap))) if gap.size else None,
        tracking_rms=float(np.sqrt(np.mean(gap**2))) if gap.size else None,
        **_multistep_fields(vehicle, channel, config),
        segments=max(len(segments(vehicle)), 1),
    )


def _multistep_fields(
    vehicle: VehicleSeries, channel: str, config: dict[str, Any] | None
) -> dict[str, Any]:
    scores = None if config is None else multistep_from_log(vehicle, channel, config)
    if scores is None:
        return {}
    return {"fit": scores.fit, "k_step_nmse": scores.k_step_nmse, "horizon": scores.horizon}


def _figure_note(summary: ChannelSummary | None) -> str:
    """The persistence baseline and the multi-step fit, for the identification figure."""
    if summary is None:
        return ""
    fit = (
        f"free-run fit {summary.fit:.1f} %, k-step NMSE {_fmt(summary.k_step_nmse, '.3g')} "
        f"(k = {summary.horizon})"
        if summary.fit is not None
        else f"free-run fit – (fewer than {MIN_FIT_SAMPLES} gap-free samples, no "
        "configuration to rebuild the model from, or a field import: per held-out dive in "
        "report.md)"
    )
    return f"one-step skill vs persistence {_fmt(summary.skill, '.3f')}; {fit}"


def _figures(
    vehicle: VehicleSeries, channel: str, out: Path, summary: ChannelSummary | None = None
) -> list[Path]:
    series = vehicle.channels[channel]
    if not series.t:
        return []
    data = series.arrays()
    clock, restarts = running_clock(vehicle)
    if vehicle.telemetry_t:
        # Estimates whose sample has no telemetry record in the log cannot be placed.
        placed = np.asarray([0 <= k < clock.size for k in series.index], dtype=bool)
        t = clock[np.asarray(series.index, dtype=int)[placed]]
    else:  # no telemetry recorded at all: the estimates' own times
        placed = np.ones(len(series.t), dtype=bool)
        t = data["t"]
    alpha = data["alpha"][placed] if data["alpha"].size else data["alpha"]
    name = f"glider{vehicle.system_id}_{channel}"
    paths = [
        prediction_figure(
            out / f"{name}_identification.png",
            f"glider {vehicle.system_id} {channel}: {series.model} model, a-priori prediction",
            channel,
            t,
            data["y"][placed],
            data["y_hat"][placed],
            alpha,
            restarts=restarts,
            baseline=data["baseline_y_hat"][placed],
            note=_figure_note(summary),
        )
    ]
    if any(math.isfinite(u) for u in vehicle.commands.u[channel]):
        paths.append(_control_figure(out / f"{name}_control.png", vehicle, channel))
    return paths


def _control_figure(path: Path, vehicle: VehicleSeries, channel: str) -> Path:
    """Setpoint and output per telemetry sample; commanded and applied ballast below."""
    clock, restarts = running_clock(vehicle)
    size = clock.size
    series, commands = vehicle.channels[channel], vehicle.commands
    return tracking_figure(
        path,
        f"glider {vehicle.system_id} {channel}: setpoint, output and ballast",
        channel,
        clock,
        [(f"measured {channel}", _on_samples(series.index, series.y, size))],
        _on_samples(commands.index, commands.setpoint[channel], size),
        [
            ("applied (telemetry)", np.asarray(vehicle.applied[channel])),
            ("commanded", _on_samples(commands.index, commands.u[channel], size)),
        ],
        restarts=restarts,
    )


def _fmt(value: float | int | None, spec: str) -> str:
    return "–" if value is None else format(value, spec)


def _link_lines(vehicle: VehicleSeries) -> list[str]:
    health = vehicle.last_health
    if not health:
        return ["No health publication was recorded for this vehicle."]
    link = health.get("link") or {}
    counters = health.get("counters") or {}
    # Logs written before health was per vehicle keep the link's counters in "counters".
    link_wide = health.get("link_wide") or counters
    loss = link.get("loss_fraction", health.get("packet_loss"))
    lines = []
    counted, logged = counters.get("samples"), len(vehicle.telemetry_t)
    if isinstance(counted, int) and counted < logged:
        # Health comes every --health-period s of the service's clock: a log that ends
        # between two (a lockstep mission runs far faster) has samples after the last.
        lines.append(
            f"- as of the last health, after {counted} of the log's {logged} samples "
            "(health is periodic: the counts below stop there)"
        )
    return [
        *lines,
        f"- packet loss: {_fmt(loss * 100 if isinstance(loss, (int, float)) else None, '.2f')} % "
        f"({link.get('frames_lost', '–')} frames lost of "
        f"{link.get('frames_received', '–')} received; "
        f"{link.get('frames_duplicated', '–')} duplicated, "
        f"{link.get('frames_reordered', '–')} reordered)",
        f"- samples: {counters.get('samples', '–')} complete, "
        f"{counters.get('incomplete', '–')} incomplete steps, "
        f"{counters.get('out_of_order', '–')} out of order, "
        f"{counters.get('invalid', '–')} invalid, "
        f"{counters.get('restarts', '–')} clock restarts",
        f"- commands sent {counters.get('commands_sent', '–')}, "
        f"acknowledged {counters.get('acks_accepted', '–')}, "
        f"refused {counters.get('acks_refused', '–')}",
        f"- the whole link (every vehicle on it): {link_wide.get('bad_frames', '–')} bad "
        f"frames, {link_wide.get('unknown_frames', '–')} unknown, "
        f"{link_wide.get('unknown_system', '–')} messages of systems not served",
    ]


def _segment_lines(vehicle: VehicleSeries) -> list[str]:
    """The runs of the vehicle's clock, when it restarted (a reboot) during the log."""
    parts = segments(vehicle)
    if len(parts) < 2:
        return []
    lines = [
        "",
        "### Vehicle clock",
        "",
        f"The vehicle's clock restarted {len(parts) - 1} "
        f"time{'s' if len(parts) > 2 else ''} (a reboot): the log holds {len(parts)} "
        "segments, all scored; the figures show them one after another, each restart marked "
        "by a dotted line.",
        "",
        "| segment | vehicle time | samples | commands |",
        "|---:|---|---:|---:|",
    ]
    commands = vehicle.commands.index
    for number, part in enumerate(parts, start=1):
        sent = sum(part.start <= k < part.stop for k in commands)
        lines.append(
            f"| {number} | {part.t_first:g} – {part.t_last:g} s | {part.stop - part.start} "
            f"| {sent} |"
        )
    return lines


def markdown(
    series: LogSeries, summaries: list[ChannelSummary], figures: list[Path], burn_in: int
) -> str:
    read = series.read
    lines = [
        f"# Glider HIL report: `{series.path.name}`",
        "",
        f"- log: `{series.path}` ({read.messages} messages, "
        f"{'complete' if read.intact else read.describe()})",
        f"- scores after a burn-in of {burn_in} samples; skill = 1 − MSE(model) / "
        "MSE(persistence); convergence = first sample after which the a-priori error stays "
        f"within {CONVERGENCE_BAND:.0%} of the output's range",
        "- fit = free-run (simulation) fit, 100·(1 − ‖y − ŷ_sim‖ / ‖y − mean y‖) %, and k-step "
        "NMSE at the control horizon k (the service's last reported horizon, at most an "
        "eighth of the stretch): the model re-identified from the log on the first half "
        "of its longest gap-free stretch, frozen, scored on the second half",
    ]
    if series.skipped:
        lines.append(f"- {series.skipped} publications could not be read and were skipped")
    if stored_pipeline(series.config) is None and not has_estimates(series):
        lines.append(
            "- fit % and k-step NMSE `–`: the log stores no service configuration to rebuild "
            "the model from"
        )
    lines += [
        "",
        "| glider | channel | model | samples | NMSE | skill | fit % | k | k-step NMSE "
        "| converged at | commands | tracking MAE | tracking RMS |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summaries:
        unit = UNITS[s.channel]
        lines.append(
            f"| {s.system_id} | {s.channel} | {s.model} | {s.samples} | {_fmt(s.nmse, '.5f')} "
            f"| {_fmt(s.skill, '.3f')} | {_fmt(s.fit, '.1f')} | {_fmt(s.horizon, 'd')} "
            f"| {_fmt(s.k_step_nmse, '.4g')} "
            f"| {_fmt(s.converged_at, 'd') if s.samples else '–'} "
            f"| {s.commands} | {_fmt(s.tracking_mae, '.3f')} {unit if s.tracking_mae else ''} "
            f"| {_fmt(s.tracking_rms, '.3f')} {unit if s.tracking_rms else ''} |"
        )
    for system_id, vehicle in sorted(series.vehicles.items()):
        lines += ["", f"## Glider {system_id}", "", "### Link", "", *_link_lines(vehicle)]
        lines += _multistep_health_lines(vehicle)
        lines += _segment_lines(vehicle)
        for channel in CHANNELS:
            own = [f for f in figures if f.name.startswith(f"glider{system_id}_{channel}_")]
            if not own:
                continue
            lines += ["", f"### {channel.capitalize()}", ""]
            lines += [f"![{f.stem.replace('_', ' ')}]({f.name})" for f in own]
    return "\n".join(lines) + "\n"


def write_report(log: str | Path, out: str | Path) -> Report:
    """The report of ``log`` in ``out``; nothing is written when the log holds nothing to
    report (no estimates, none identified offline, not a field import). StoredConfigError
    when the log's stored configuration cannot be read."""
    series = load_series(log)
    config = ServiceConfig.from_stored(series.config, log)
    offline = False
    if not has_estimates(series):
        identified = identify_offline(log, series)
        if identified is not None and has_estimates(identified):
            series, offline = identified, True
    directory = Path(out)
    field_import = isinstance(series.config.get("field"), dict)
    if not has_estimates(series) and not field_import:
        return Report(directory / "report.md", [], [], offline)
    directory.mkdir(parents=True, exist_ok=True)
    burn_in = _burn_in(config)
    fit_config = series.config
    defaults = offline and stored_pipeline(series.config) is None
    if defaults and not field_import:  # the default settings the offline replay ran with
        fit_config = {**series.config, "service": ServiceConfig().stored()["service"]}
    summaries: list[ChannelSummary] = []
    figures: list[Path] = []
    for _, vehicle in sorted(series.vehicles.items()):
        for channel in CHANNELS:
            if not vehicle.channels[channel].t:
                continue
            summaries.append(summarise(vehicle, channel, burn_in, fit_config))
            figures += _figures(vehicle, channel, directory, summaries[-1])
    path = directory / "report.md"
    text = markdown(series, summaries, figures, burn_in)
    if offline:
        lines = text.split("\n")
        at = next((i for i, line in enumerate(lines) if line.startswith("- log:")), 1)
        notes = [OFFLINE_NOTE]
        if field_import:
            notes.append(
                "- fit % and k-step NMSE `–` in this table: a field import's longest gap-free "
                "stretch is one dive, whose halves are its descent and its climb; they are "
                "given per held-out dive in the field identification below"
            )
        elif defaults:
            notes.append(
                "- the log stores no service configuration: the offline identification and "
                "the fit % / k-step NMSE columns ran with the default pipeline settings"
            )
        text = "\n".join([*lines[: at + 1], *notes, *lines[at + 1 :]])
    lines, field_figures, field_results = field_section(log, series.config, directory)
    if lines:
        text += "\n".join(lines) + "\n"
        figures += field_figures
    path.write_text(text, encoding="utf-8")
    return Report(path, figures, summaries, offline, field_results)
