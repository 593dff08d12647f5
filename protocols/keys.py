"""The Zenoh key space (docs/zenoh.md), ``{id}`` being the MAVLink system id.

The only module that formats or parses a key: everything else calls the functions below
(``parse`` for a key received or read from a log). The MCAP channel of the control inputs
each decision used (``glider-hil/{id}/decision-inputs``) is here too: it is never published
on Zenoh, but replay and the report find it by the same rules.
"""

from __future__ import annotations

from dataclasses import dataclass

CHANNELS = ("depth", "pitch")
ROOT = "glider"
#: Root of the service's own log-only channels (not Zenoh keys).
LOG_ROOT = "glider-hil"

# Key kinds: the part of a key after ``{id}``, without the ``{channel}``.
TELEMETRY = "telemetry"
UMODEL = "umodel"
COMMAND_BALLAST = "command/ballast"
SETPOINT = "setpoint"
CONTROL = "control"
HEALTH = "health"
SUPERVISOR = "supervisor"  # the closed-loop supervisor's trips and re-arms
STATE = "state"
SERVICE = "service"
DECISION_INPUTS = "decision-inputs"
REJECTED_INPUTS = "rejected-inputs"  # service-wide log channel: no system id

#: Kinds followed by ``/{channel}``.
CHANNEL_KINDS = frozenset({UMODEL, SETPOINT})
#: Kinds under ``glider/{id}/`` (Zenoh), and under ``glider-hil/{id}/`` (MCAP only).
ZENOH_KINDS = (
    TELEMETRY,
    UMODEL,
    COMMAND_BALLAST,
    SETPOINT,
    CONTROL,
    HEALTH,
    SUPERVISOR,
    STATE,
    SERVICE,
)
LOG_KINDS = (DECISION_INPUTS,)

#: Subscriptions of the service: every vehicle's operator inputs.
INPUT_SUBSCRIPTIONS = (f"{ROOT}/*/{SETPOINT}/*", f"{ROOT}/*/{CONTROL}")


def _check(system_id: int, channel: str | None = None) -> None:
    if not 1 <= system_id <= 255:
        raise ValueError(f"system id must be 1..255, got {system_id}")
    if channel is not None and channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")


def telemetry(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/{TELEMETRY}"


def umodel(system_id: int, channel: str) -> str:
    _check(system_id, channel)
    return f"{ROOT}/{system_id}/{UMODEL}/{channel}"


def command_ballast(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/{COMMAND_BALLAST}"


def setpoint(system_id: int, channel: str) -> str:
    _check(system_id, channel)
    return f"{ROOT}/{system_id}/{SETPOINT}/{channel}"


def control(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/{CONTROL}"


def health(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{system_id}/{HEALTH}"


def supervisor(system_id: int) -> str:
    """Events of the channels' closed-loop supervisors (a trip, a re-arm)."""
    _check(system_id)
    return f"{ROOT}/{system_id}/{SUPERVISOR}"


def service(system_id: int) -> str:
    """Liveliness token held while the service runs for this vehicle."""
    _check(system_id)
    return f"{ROOT}/{system_id}/{SERVICE}"


def state(system_id: int) -> str:
    """Queryable answering the latest sample, estimates and command."""
    _check(system_id)
    return f"{ROOT}/{system_id}/{STATE}"


def decision_inputs(system_id: int) -> str:
    """MCAP channel of the control inputs each decision used (recorded on change)."""
    _check(system_id)
    return f"{LOG_ROOT}/{system_id}/{DECISION_INPUTS}"


def rejected_inputs() -> str:
    """Log channel of the inputs the service refused (any key, valid or not), with why."""
    return f"{LOG_ROOT}/{REJECTED_INPUTS}"


def vehicle_pattern(system_id: int) -> str:
    """Key expression of everything about one vehicle (``glider/{id}/**``)."""
    _check(system_id)
    return f"{ROOT}/{system_id}/**"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key taken apart: ``kind`` is one of the kind constants above."""

    system_id: int
    kind: str
    channel: str | None = None


def parse(key: str) -> ParsedKey | None:
    """The parts of a key of this key space, or None for anything else (no exception).

    Strict: the system id must be a decimal 1..255, the kind known, and the channel, for
    kinds that take one, ``depth`` or ``pitch``.
    """
    root, sep, rest = key.partition("/")
    if not sep:
        return None
    if root == ROOT:
        kinds: tuple[str, ...] = ZENOH_KINDS
    elif root == LOG_ROOT:
        kinds = LOG_KINDS
    else:
        return None
    number, sep, kind = rest.partition("/")
    if not sep or not number.isdigit() or not number.isascii() or number != str(int(number)):
        return None
    system_id = int(number)
    if not 1 <= system_id <= 255:
        return None
    if kind in kinds and kind not in CHANNEL_KINDS:
        return ParsedKey(system_id, kind)
    base, sep, channel = kind.rpartition("/")
    if sep and base in CHANNEL_KINDS and base in kinds and channel in CHANNELS:
        return ParsedKey(system_id, base, channel)
    return None


@dataclass(frozen=True)
class VehicleKeys:
    """One vehicle's output keys, formatted once: the per-sample path publishes on them."""

    telemetry: str
    umodel: dict[str, str]
    command_ballast: str
    health: str
    decision_inputs: str
    supervisor: str

    @classmethod
    def of(cls, system_id: int) -> VehicleKeys:
        return cls(
            telemetry=telemetry(system_id),
            umodel={channel: umodel(system_id, channel) for channel in CHANNELS},
            command_ballast=command_ballast(system_id),
            health=health(system_id),
            decision_inputs=decision_inputs(system_id),
            supervisor=supervisor(system_id),
        )


#: Schema name (``protocols/schemas/``) for each key kind with a JSON payload, used to
#: validate payloads and label MCAP channels.
SCHEMA_FOR_KIND = {
    TELEMETRY: "telemetry",
    UMODEL: "umodel",
    COMMAND_BALLAST: "command_ballast",
    SETPOINT: "setpoint",
    CONTROL: "control",
    HEALTH: "health",
    SUPERVISOR: "supervisor_event",
    DECISION_INPUTS: "decision_inputs",
}


def schema_for_key(key: str) -> str | None:
    """The schema name of a concrete key, or None for keys without a JSON payload schema."""
    if key == rejected_inputs():
        return "rejected_input"
    parsed = parse(key)
    return None if parsed is None else SCHEMA_FOR_KIND.get(parsed.kind)
