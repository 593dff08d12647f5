"""The Zenoh key space (docs/zenoh.md), ``{id}`` being the vehicle's key id.

A vehicle is a MAVLink system id on a link. Its key id is the plain system id (``7``) when
system ids are unique across the service's links (``serve --vehicle-ids sysid``, the
default), or ``{link}-{sysid}`` (``2-7``: system id 7 on the service's second ``--mavlink``
link) when each link has a system-id space of its own (``--vehicle-ids link``). Inside the
service a vehicle is one int, its *vehicle id*: the system id itself, or
``link * 256 + sysid`` (``vehicle_id``); the functions below take that int and format it.

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


#: Links a service tells apart by number (``--mavlink`` given this many times at most).
MAX_LINKS = 255
_LINK_STRIDE = 256  # a system id is one byte: vehicle id = link * 256 + system id


def vehicle_id(link: int, system_id: int) -> int:
    """The vehicle id of ``system_id`` on link ``link`` (1-based; 0: no link, the plain
    system id)."""
    if not 0 <= link <= MAX_LINKS:
        raise ValueError(f"link must be 0..{MAX_LINKS}, got {link}")
    if not 1 <= system_id <= 255:
        raise ValueError(f"system id must be 1..255, got {system_id}")
    return link * _LINK_STRIDE + system_id


def split_vehicle_id(vehicle: int) -> tuple[int, int]:
    """(link, MAVLink system id) of a vehicle id; link 0 for a plain system id."""
    return divmod(vehicle, _LINK_STRIDE)


def is_vehicle_id(vehicle: int) -> bool:
    link, system_id = divmod(vehicle, _LINK_STRIDE)
    return 0 <= link <= MAX_LINKS and 1 <= system_id <= 255


def key_id(vehicle: int) -> str:
    """The ``{id}`` part of a vehicle's keys: ``7``, or ``2-7`` for system id 7 on link 2."""
    link, system_id = divmod(vehicle, _LINK_STRIDE)
    return str(system_id) if link == 0 else f"{link}-{system_id}"


def _decimal(text: str) -> int | None:
    if not text.isdigit() or not text.isascii() or text != str(int(text)):
        return None
    return int(text)


def parse_key_id(text: str) -> int | None:
    """The vehicle id a key id names (``7`` or ``2-7``), or None: decimals without leading
    zeros, a system id 1..255 and a link 1..MAX_LINKS."""
    link_text, dash, number = text.rpartition("-")
    system_id = _decimal(number)
    if system_id is None or not 1 <= system_id <= 255:
        return None
    if not dash:
        return system_id
    link = _decimal(link_text)
    if link is None or not 1 <= link <= MAX_LINKS:
        return None
    return link * _LINK_STRIDE + system_id


def _check(system_id: int, channel: str | None = None) -> None:
    if not is_vehicle_id(system_id):
        raise ValueError(
            f"vehicle id must be a system id 1..255 or link * 256 + system id, got {system_id}"
        )
    if channel is not None and channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")


def telemetry(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{TELEMETRY}"


def umodel(system_id: int, channel: str) -> str:
    _check(system_id, channel)
    return f"{ROOT}/{key_id(system_id)}/{UMODEL}/{channel}"


def command_ballast(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{COMMAND_BALLAST}"


def setpoint(system_id: int, channel: str) -> str:
    _check(system_id, channel)
    return f"{ROOT}/{key_id(system_id)}/{SETPOINT}/{channel}"


def control(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{CONTROL}"


def health(system_id: int) -> str:
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{HEALTH}"


def supervisor(system_id: int) -> str:
    """Events of the channels' closed-loop supervisors (a trip, a re-arm)."""
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{SUPERVISOR}"


def service(system_id: int) -> str:
    """Liveliness token held while the service runs for this vehicle."""
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{SERVICE}"


def state(system_id: int) -> str:
    """Queryable answering the latest sample, estimates and command."""
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/{STATE}"


def decision_inputs(system_id: int) -> str:
    """MCAP channel of the control inputs each decision used (recorded on change)."""
    _check(system_id)
    return f"{LOG_ROOT}/{key_id(system_id)}/{DECISION_INPUTS}"


def rejected_inputs() -> str:
    """Log channel of the inputs the service refused (any key, valid or not), with why."""
    return f"{LOG_ROOT}/{REJECTED_INPUTS}"


def vehicle_pattern(system_id: int) -> str:
    """Key expression of everything about one vehicle (``glider/{id}/**``)."""
    _check(system_id)
    return f"{ROOT}/{key_id(system_id)}/**"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key taken apart: ``kind`` is one of the kind constants above,
    ``system_id`` the vehicle id (the system id itself unless the key id names a link)."""

    system_id: int
    kind: str
    channel: str | None = None


def parse(key: str) -> ParsedKey | None:
    """The parts of a key of this key space, or None for anything else (no exception).

    Strict: the key id must be a system id (decimal 1..255) or ``{link}-{sysid}``
    (``parse_key_id``; ``system_id`` is then the vehicle id), the kind known, and the
    channel, for kinds that take one, ``depth`` or ``pitch``.
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
    if not sep:
        return None
    system_id = parse_key_id(number)
    if system_id is None:
        return None
    if kind in kinds and kind not in CHANNEL_KINDS:
        return ParsedKey(system_id, kind)
    base, sep, channel = kind.rpartition("/")
    if sep and base in CHANNEL_KINDS and base in kinds and channel in CHANNELS:
        return ParsedKey(system_id, base, channel)
    return None


#: The key kinds published with congestion control BLOCK (docs/zenoh.md): a command or a
#: supervisor's event is never dropped for a slow subscriber; the rest is.
RELIABLE_KINDS = frozenset({COMMAND_BALLAST, SUPERVISOR})


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

    def publications(self) -> tuple[tuple[str, bool], ...]:
        """The keys published on Zenoh, each with whether it is reliable (``RELIABLE_KINDS``);
        ``decision_inputs`` is recorded in the log only."""
        return (
            (self.telemetry, TELEMETRY in RELIABLE_KINDS),
            *((key, UMODEL in RELIABLE_KINDS) for key in self.umodel.values()),
            (self.command_ballast, COMMAND_BALLAST in RELIABLE_KINDS),
            (self.health, HEALTH in RELIABLE_KINDS),
            (self.supervisor, SUPERVISOR in RELIABLE_KINDS),
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
