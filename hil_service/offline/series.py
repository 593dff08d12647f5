"""Time series per vehicle from a service log: what ``report`` draws and scores.

Reads the decoded Zenoh publications the service recorded (``glider/{id}/telemetry``,
``umodel/{channel}``, ``command/ballast``, ``health``), not the raw MAVLink: a report shows
what the service computed at the time, under the configuration stored in the log.

A vehicle that reboots starts its clock again, so telemetry times repeat across a restart:
a restart is a telemetry time at or before the previous one, and each estimate and command
is tied to the telemetry record of its own sample by position in the log (``index``), never
by its time alone.

A publication that cannot be used is counted (``LogSeries.skipped``) and skipped, none of it
kept: not JSON, not an object, a field missing or of the wrong JSON type (a time that is not
a finite number, a value that is neither a number nor null, the null a NaN is recorded as).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.mcap.reader import LogReader, ReadReport
from protocols import keys
from protocols.keys import CHANNELS
from protocols.payload_json import is_finite_number

_SERIES_KINDS = frozenset({keys.TELEMETRY, keys.UMODEL, keys.COMMAND_BALLAST, keys.HEALTH})


@dataclass
class ChannelSeries:
    t: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    y_hat: list[float] = field(default_factory=list)
    baseline_y_hat: list[float] = field(default_factory=list)
    alpha: list[list[float]] = field(default_factory=list)
    status: list[str] = field(default_factory=list)
    model: str = ""
    index: list[int] = field(default_factory=list)  # of the sample in telemetry_t, -1: none

    def arrays(self) -> dict[str, np.ndarray]:
        width = max((len(a) for a in self.alpha), default=0)
        alpha = np.full((len(self.alpha), width), np.nan)
        for k, a in enumerate(self.alpha):
            alpha[k, : len(a)] = a
        return {
            "t": np.asarray(self.t, dtype=float),
            "y": np.asarray(self.y, dtype=float),
            "y_hat": np.asarray(self.y_hat, dtype=float),
            "baseline_y_hat": np.asarray(self.baseline_y_hat, dtype=float),
            "alpha": alpha,
        }


@dataclass
class CommandSeries:
    t: list[float] = field(default_factory=list)
    u: dict[str, list[float]] = field(default_factory=lambda: {ch: [] for ch in CHANNELS})
    setpoint: dict[str, list[float]] = field(default_factory=lambda: {ch: [] for ch in CHANNELS})
    saturated: int = 0
    index: list[int] = field(default_factory=list)  # of the sample in telemetry_t, -1: none


@dataclass
class VehicleSeries:
    system_id: int
    telemetry_t: list[float] = field(default_factory=list)
    applied: dict[str, list[float]] = field(default_factory=lambda: {ch: [] for ch in CHANNELS})
    channels: dict[str, ChannelSeries] = field(
        default_factory=lambda: {ch: ChannelSeries() for ch in CHANNELS}
    )
    commands: CommandSeries = field(default_factory=CommandSeries)
    last_health: dict[str, Any] | None = None
    #: Where in telemetry_t each run of the vehicle's clock starts (a restart: a reboot).
    segment_starts: list[int] = field(default_factory=list)
    #: Time → position in telemetry_t, for the current segment only.
    _in_segment: dict[float, int] = field(default_factory=dict, repr=False)

    def sample_index(self, t: float) -> int:
        """Position in telemetry_t of the latest sample stamped ``t`` (-1: not recorded)."""
        return self._in_segment.get(t, -1)


@dataclass
class LogSeries:
    path: Path
    read: ReadReport
    config: dict[str, Any]
    vehicles: dict[int, VehicleSeries]
    skipped: int  # publications that could not be used (bad JSON, missing fields)


def _number(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) else math.nan


def telemetry_columns(
    rows: list[Any], names: tuple[str, ...], where: str | Path
) -> dict[str, np.ndarray]:
    """Each of ``names`` over the telemetry payloads ``rows``, as floats.

    ValueError, naming ``where``, each field and how many samples lack it, when any sample
    has no finite number there (the recorder writes a NaN as null): no model can train on
    such a sample, nor be scored against it.
    """
    columns = {
        name: np.asarray(
            [_number(row.get(name)) if isinstance(row, dict) else math.nan for row in rows],
            dtype=float,
        )
        for name in names
    }
    lacking = {name: int(np.count_nonzero(~np.isfinite(v))) for name, v in columns.items()}
    counts = ", ".join(f"{name} in {n}" for name, n in lacking.items() if n)
    if counts:
        raise ValueError(
            f"{where}: telemetry samples without a finite number (null, as a NaN is recorded, "
            f"or missing): {counts} of {len(rows)}; the identification needs every value"
        )
    return columns


def load_series(path: str | Path) -> LogSeries:
    """All vehicles' series; a log cut short is read up to its last complete chunk."""
    reader = LogReader(path)
    vehicles: dict[int, VehicleSeries] = {}
    skipped = 0
    for message in reader.messages():
        parsed = keys.parse(message.topic)
        if parsed is None or parsed.kind not in _SERIES_KINDS:
            continue
        vehicle = vehicles.setdefault(parsed.system_id, VehicleSeries(parsed.system_id))
        try:
            payload = message.json()
            _add(vehicle, parsed.kind, parsed.channel, payload)
        except (ValueError, TypeError, KeyError, AttributeError):
            skipped += 1
    return LogSeries(Path(path), reader.report, reader.config(), vehicles, skipped)


def _time(payload: dict[str, Any]) -> float:
    """A publication's ``t``: a finite number (ValueError otherwise)."""
    value = payload["t"]
    if not is_finite_number(value):
        raise ValueError(f"t: expected a finite number, got {value!r}")
    return float(value)


def _reading(value: Any, name: str) -> float:
    """A value of a publication: a number, or null (a NaN, recorded as null) as NaN;
    ValueError for anything else."""
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name}: expected a number or null, got {value!r}")
    return float(value)


def _object(value: Any, name: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ValueError(f"{name}: expected an object, got {value!r}")
    return value


def _add(vehicle: VehicleSeries, kind: str, channel: str | None, payload: Any) -> None:
    """One publication into ``vehicle``'s series, read whole before any of it is kept (a
    ValueError, TypeError or KeyError leaves the series as they were)."""
    payload = _object(payload, kind)
    if kind == keys.TELEMETRY:
        t = _time(payload)
        applied = {ch: _reading(payload[f"u_{ch}"], f"u_{ch}") for ch in CHANNELS}
        if not vehicle.telemetry_t or not t > vehicle.telemetry_t[-1]:
            vehicle.segment_starts.append(len(vehicle.telemetry_t))
            vehicle._in_segment.clear()
        vehicle._in_segment[t] = len(vehicle.telemetry_t)
        vehicle.telemetry_t.append(t)
        for ch in CHANNELS:
            vehicle.applied[ch].append(applied[ch])
    elif kind == keys.HEALTH:
        vehicle.last_health = dict(payload)
    elif kind == keys.COMMAND_BALLAST:
        commands = vehicle.commands
        t = _time(payload)
        stored = payload.get("setpoints")
        setpoints = {} if stored is None else _object(stored, "setpoints")
        values = {ch: _reading(payload.get(f"u_{ch}"), f"u_{ch}") for ch in CHANNELS}
        wanted = {ch: _reading(setpoints.get(ch), f"setpoints.{ch}") for ch in CHANNELS}
        commands.t.append(t)
        commands.index.append(vehicle.sample_index(t))
        for ch in CHANNELS:
            commands.u[ch].append(values[ch])
            commands.setpoint[ch].append(wanted[ch])
        commands.saturated += bool(payload.get("saturated"))
    elif channel is not None:
        series = vehicle.channels[channel]
        stored_alpha = payload.get("alpha", [])
        if not isinstance(stored_alpha, list):
            raise ValueError(f"alpha: expected a list, got {stored_alpha!r}")
        alpha = [_reading(a, "alpha") for a in stored_alpha]
        t = _time(payload)
        y, y_hat = _reading(payload["y"], "y"), _reading(payload["y_hat"], "y_hat")
        baseline = _reading(payload.get("baseline_y_hat"), "baseline_y_hat")
        series.t.append(t)
        series.index.append(vehicle.sample_index(t))
        series.y.append(y)
        series.y_hat.append(y_hat)
        series.baseline_y_hat.append(baseline)
        series.alpha.append(alpha)
        series.status.append(str(payload.get("status", "ok")))
        series.model = str(payload.get("model", series.model))
