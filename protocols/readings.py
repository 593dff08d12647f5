"""A profile's readings of a message (``Profile.readings``), compiled: the loop that runs
for every telemetry message.

``protocols/profiles.py`` (the profile's dataclasses and its TOML parser) is interpreted; its
``readings`` builds one ``MessageReader`` per profile and hands every message to it. The
conversions stay the profile's own: ``PressureDepth.depth_m`` and ``Ballast.applied`` are
called, not repeated; only the linear conversion (``field·scale + offset``, the field as it is
for scale 1 and offset 0) is done here, as ``Profile`` wrote it.
"""

from __future__ import annotations

from typing import Any

from protocols.mavlink_io import MavMessage, type_of

#: A source as this loop reads it: signal, rank, field, array index (-1: none), converted
#: from pressure to depth, scale, offset, field as it is (scale 1 and offset 0).
Entry = tuple[str, int, str, int, bool, float, float, bool]


class MessageReader:
    """Readings ``(signal, rank, value)`` of a message under one profile."""

    def __init__(self, sources: dict[str, list[tuple[str, int, Any]]], pressure: Any, ballast: Any):
        """``sources``: message type → (signal, rank, ``profiles.Source``) in the profile's
        order; ``pressure`` its ``PressureDepth``; ``ballast`` its ``Ballast``."""
        self._entries: dict[str, list[Entry]] = {
            kind: [
                (
                    name,
                    rank,
                    str(source.field),
                    -1 if source.index is None else int(source.index),
                    source.convert == "pressure_to_depth",
                    float(source.scale),
                    float(source.offset),
                    source.scale == 1.0 and source.offset == 0.0,
                )
                for name, rank, source in entries
            ]
            for kind, entries in sources.items()
        }
        self._pressure = pressure
        self._ballast = ballast
        self._readback: str = ballast.readback

    def readings(self, message: MavMessage) -> list[tuple[str, int, float]]:
        kind = type_of(message)
        found: list[tuple[str, int, float]] = []
        entries = self._entries.get(kind)
        if entries is not None:
            for name, rank, field, index, pressure, scale, offset, as_is in entries:
                raw = getattr(message, field)
                if index >= 0:
                    raw = raw[index]
                value = float(raw)
                if pressure:
                    value = float(self._pressure.depth_m(value))
                elif not as_is:
                    value = value * scale + offset
                found.append((name, rank, value))
        if kind == self._readback:
            u_depth, u_pitch = self._ballast.applied(message)
            found.append(("u_depth", 0, float(u_depth)))
            found.append(("u_pitch", 0, float(u_pitch)))
        return found
