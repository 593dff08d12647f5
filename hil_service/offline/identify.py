"""Estimates for a log that has none: its telemetry through the identifier, offline.

An imported tlog (``glider-hil import``) holds the vehicle's frames but none of the service's
publications, so a report of it would be empty. ``identify_offline`` runs the log's raw
frames through the same path ``glider-hil replay`` does (``hil_service.offline.replay``:
the service wired as ``serve`` wires it, with the profile and configuration the log stores,
no commands sent) and gathers what the service publishes (telemetry, estimates, health) as
the ``LogSeries`` a live log's publications give, so the report reads both alike.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import orjson

from hil_service.listeners import Listener
from hil_service.mcap.reader import LogError
from hil_service.offline.replay import ReplayError, ReplayOptions, replay
from hil_service.offline.series import _SERIES_KINDS, LogSeries, VehicleSeries, _add
from protocols import keys
from protocols.keys import CHANNELS


class _Gathering(Listener):
    """Keeps every publication of the replayed service, as the JSON a log would hold."""

    def __init__(self) -> None:
        self.records: list[tuple[str, dict[str, Any]]] = []

    def on_publish(self, key: str, payload: dict[str, Any], data: bytes, reliable: bool) -> None:
        self.records.append((key, orjson.loads(data)))


def has_estimates(series: LogSeries) -> bool:
    """Whether the log holds any identifier estimate (a live service's log does)."""
    return any(v.channels[ch].t for v in series.vehicles.values() for ch in CHANNELS)


def identify_offline(path: str | Path, series: LogSeries) -> LogSeries | None:
    """``series`` with the vehicles the offline identification gives, or None when the log
    has no raw frames to replay (or they cannot be read)."""
    bus = _Gathering()
    try:
        replay(path, ReplayOptions(), [bus])
    except (ReplayError, LogError, ValueError):
        return None
    vehicles: dict[int, VehicleSeries] = {}
    skipped = 0
    for key, payload in bus.records:
        parsed = keys.parse(key)
        if parsed is None or parsed.kind not in _SERIES_KINDS:
            continue
        vehicle = vehicles.setdefault(parsed.system_id, VehicleSeries(parsed.system_id))
        try:
            _add(vehicle, parsed.kind, parsed.channel, payload)
        except (ValueError, TypeError, KeyError, AttributeError):
            skipped += 1
    if not vehicles:
        return None
    return LogSeries(series.path, series.read, series.config, vehicles, series.skipped + skipped)
