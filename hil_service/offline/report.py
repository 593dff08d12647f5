"""A report from a service log: scores per vehicle and channel, figures, ``report.md``."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.experiment.identification import (
    CONVERGENCE_BAND,
    control_horizon,
    converged_at,
)
from hil_service.experiment.multistep import MultiStepScores, longest_contiguous, multistep_scores
from hil_service.offline.plots import UNITS, prediction_figure, tracking_figure
from hil_service.offline.series import CHANNELS, LogSeries, VehicleSeries, load_series
from hil_service.pipeline import PipelineSettings, VehiclePipeline
from hil_service.umodel import from_config
from hil_service.umodel.scoring import ErrorStats

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
    # of the longest gap-free stretch and frozen (hil_service/experiment/multistep.py).
    fit: float | None = None
    k_step_nmse: float | None = None
    horizon: int | None = None


@dataclass(frozen=True)
class Report:
    markdown: Path
    figures: list[Path]
    summaries: list[ChannelSummary]


def _burn_in(config: dict[str, Any]) -> int:
    pipeline = (config.get("service") or {}).get("pipeline") or {}
    value = pipeline.get("burn_in", DEFAULT_BURN_IN)
    return int(value) if isinstance(value, int) and value >= 0 else DEFAULT_BURN_IN


#: Fewer gap-free samples than this and the multi-step figures are not computed.
MIN_FIT_SAMPLES = 40


def multistep_from_log(
    vehicle: VehicleSeries, channel: str, config: dict[str, Any]
) -> MultiStepScores | None:
    """The multi-step figures of the model the log's configuration describes, or None.

    The model is rebuilt from the stored pipeline settings (same seed and options as the
    service's), on the applied inputs (telemetry) and the outputs the identifier saw.
    """
    stored = (config.get("service") or {}).get("pipeline")
    if not isinstance(stored, dict):
        return None
    try:
        settings = PipelineSettings.from_json(stored)
        model_config = VehiclePipeline(settings).configs()[channel]
        horizon = settings.control.horizon.get(channel, control_horizon(channel))
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
    outputs = dict(zip(series.t, series.y, strict=True))
    gaps = []
    commands = vehicle.commands
    for t, setpoint in zip(commands.t, commands.setpoint[channel], strict=True):
        y = outputs.get(t)
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
    )


def _multistep_fields(
    vehicle: VehicleSeries, channel: str, config: dict[str, Any] | None
) -> dict[str, Any]:
    scores = None if config is None else multistep_from_log(vehicle, channel, config)
    if scores is None:
        return {}
    return {"fit": scores.fit, "k_step_nmse": scores.k_step_nmse, "horizon": scores.horizon}


def _figures(vehicle: VehicleSeries, channel: str, out: Path) -> list[Path]:
    series = vehicle.channels[channel]
    if not series.t:
        return []
    data = series.arrays()
    name = f"glider{vehicle.system_id}_{channel}"
    paths = [
        prediction_figure(
            out / f"{name}_identification.png",
            f"glider {vehicle.system_id} {channel}: {series.model} model, a-priori prediction",
            channel,
            data["t"],
            data["y"],
            data["y_hat"],
            data["alpha"],
        )
    ]
    if any(math.isfinite(u) for u in vehicle.commands.u[channel]):
        paths.append(_control_figure(out / f"{name}_control.png", vehicle, channel))
    return paths


def _control_figure(path: Path, vehicle: VehicleSeries, channel: str) -> Path:
    """Setpoint and output on the telemetry clock; commanded and applied ballast below."""
    index = {t: k for k, t in enumerate(vehicle.telemetry_t)}

    def on_telemetry_clock(times: list[float], values: list[float]) -> np.ndarray:
        aligned = np.full(len(index), np.nan)
        for t, value in zip(times, values, strict=True):
            k = index.get(t)
            if k is not None:
                aligned[k] = value
        return aligned

    series, commands = vehicle.channels[channel], vehicle.commands
    return tracking_figure(
        path,
        f"glider {vehicle.system_id} {channel}: setpoint, output and ballast",
        channel,
        np.asarray(vehicle.telemetry_t),
        [(f"measured {channel}", on_telemetry_clock(series.t, series.y))],
        on_telemetry_clock(commands.t, commands.setpoint[channel]),
        [
            ("applied (telemetry)", np.asarray(vehicle.applied[channel])),
            ("commanded", on_telemetry_clock(commands.t, commands.u[channel])),
        ],
    )


def _fmt(value: float | int | None, spec: str) -> str:
    return "–" if value is None else format(value, spec)


def _link_lines(vehicle: VehicleSeries) -> list[str]:
    health = vehicle.last_health
    if not health:
        return ["No health publication was recorded for this vehicle."]
    link = health.get("link") or {}
    counters = health.get("counters") or {}
    loss = link.get("loss_fraction", health.get("packet_loss"))
    return [
        f"- packet loss: {_fmt(loss * 100 if isinstance(loss, (int, float)) else None, '.2f')} % "
        f"({link.get('frames_lost', '–')} frames lost of "
        f"{link.get('frames_received', '–')} received; "
        f"{link.get('frames_duplicated', '–')} duplicated, "
        f"{link.get('frames_reordered', '–')} reordered)",
        f"- samples: {counters.get('samples', '–')} complete, "
        f"{counters.get('incomplete', '–')} incomplete steps, "
        f"{counters.get('out_of_order', '–')} out of order, "
        f"{counters.get('invalid', '–')} invalid",
        f"- frames: {counters.get('bad_frames', '–')} bad, "
        f"{counters.get('unknown_frames', '–')} unknown; "
        f"commands sent {counters.get('commands_sent', '–')}, "
        f"acknowledged {counters.get('acks_accepted', '–')}, "
        f"refused {counters.get('acks_refused', '–')}",
    ]


def markdown(series: LogSeries, summaries: list[ChannelSummary], figures: list[Path]) -> str:
    burn_in = _burn_in(series.config)
    read = series.read
    lines = [
        f"# Glider HIL report: `{series.path.name}`",
        "",
        f"- log: `{series.path}` ({read.messages} messages, "
        f"{'complete' if read.complete else 'not finished: ' + read.describe()})",
        f"- scores after a burn-in of {burn_in} samples; skill = 1 − MSE(model) / "
        "MSE(persistence); convergence = first sample after which the a-priori error stays "
        f"within {CONVERGENCE_BAND:.0%} of the output's range",
        "- fit = free-run (simulation) fit, 100·(1 − ‖y − ŷ_sim‖ / ‖y − mean y‖) %, and k-step "
        "NMSE at the control horizon k: the model re-identified from the log on the first half "
        "of its longest gap-free stretch, frozen, scored on the second half",
    ]
    if series.skipped:
        lines.append(f"- {series.skipped} publications could not be read and were skipped")
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
        for channel in CHANNELS:
            own = [f for f in figures if f.name.startswith(f"glider{system_id}_{channel}_")]
            if not own:
                continue
            lines += ["", f"### {channel.capitalize()}", ""]
            lines += [f"![{f.stem.replace('_', ' ')}]({f.name})" for f in own]
    return "\n".join(lines) + "\n"


def write_report(log: str | Path, out: str | Path) -> Report:
    series = load_series(log)
    directory = Path(out)
    directory.mkdir(parents=True, exist_ok=True)
    burn_in = _burn_in(series.config)
    summaries: list[ChannelSummary] = []
    figures: list[Path] = []
    for _, vehicle in sorted(series.vehicles.items()):
        for channel in CHANNELS:
            if not vehicle.channels[channel].t:
                continue
            summaries.append(summarise(vehicle, channel, burn_in, series.config))
            figures += _figures(vehicle, channel, directory)
    path = directory / "report.md"
    path.write_text(markdown(series, summaries, figures), encoding="utf-8")
    return Report(path, figures, summaries)
