"""The Zenoh key space of DESIGN.md section 3, ``{id}`` being the MAVLink system id."""

from __future__ import annotations

from dataclasses import dataclass

CHANNELS = ("depth", "pitch")
ROOT = "glider"


def _check(system_id: int, channel: str | None = None) -> None:
    if not 1 <= system_id <= 255:
        raise ValueError(f"system id must be 1..255, got {system_id}")
    if channel is not None and channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")


def telemetry(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/telemetry"


def umodel(system_id: int, channel: str) -> str:
    _check(system_id, channel)
    return f"{ROOT}/{system_id}/umodel/{channel}"


def command_ballast(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/command/ballast"


def setpoint(system_id: int, channel: str) -> str:
    _check(system_id, channel)
    return f"{ROOT}/{system_id}/setpoint/{channel}"


def control(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/control"


def health(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/health"


def service(system_id: int) -> str:
    """Liveliness token held while the service runs for this vehicle."""
    _check(system_id)
    return f"{ROOT}/{system_id}/service"


def state(system_id: int) -> str:
    """Queryable answering the latest sample, estimates and command."""
    _check(system_id)
    return f"{ROOT}/{system_id}/state"


@dataclass(frozen=True)
class VehicleKeys:
    """One vehicle's output keys, formatted once: the per-sample path publishes on them."""

    telemetry: str
    umodel: dict[str, str]
    command_ballast: str
    health: str

    @classmethod
    def of(cls, system_id: int) -> VehicleKeys:
        return cls(
            telemetry=telemetry(system_id),
            umodel={channel: umodel(system_id, channel) for channel in CHANNELS},
            command_ballast=command_ballast(system_id),
            health=health(system_id),
        )


#: Schema name for each key kind, used to validate payloads and label MCAP channels.
SCHEMA_FOR_KIND = {
    "telemetry": "telemetry",
    "umodel": "umodel",
    "command": "command_ballast",
    "setpoint": "setpoint",
    "control": "control",
    "health": "health",
}


def schema_for_key(key: str) -> str | None:
    """The schema name of a concrete key, or None for keys without a JSON payload."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        return None
    return SCHEMA_FOR_KIND.get(parts[2])
