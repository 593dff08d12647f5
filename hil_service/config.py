"""The service's configuration: one object, written to a log's metadata and read back here.

``ServiceConfig`` is what ``serve`` builds from its flags, what ``HilService`` runs with, what
the recorder stores as the MCAP metadata record ``glider-hil.config`` (``to_metadata``), and
what ``replay``, ``info`` and ``report`` read back (``ServiceConfig.from_stored``). The
record holds two JSON strings, ``service`` (identification, control, vehicles, limits,
whether the link is signed; never the key) and ``mapping`` (the unit conversions of the
MAVLink mapping). Logs written before a field existed read with that field's default; a
log without ``mapping`` was written with the default units.

``ServeConfig`` adds what only a live run needs (the link, Zenoh, the log files); it is not
stored.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from hil_service.inputs import SetpointLimits
from hil_service.live.address import LiveAddress
from hil_service.pipeline import PipelineSettings
from hil_service.zenoh_config import ZenohOptions
from protocols.mapping import TelemetryMapping
from protocols.profiles import Profile, parse_profile
from protocols.units import InputScale, PressureDepth

#: Keys of the metadata record (``hil_service.mcap.recorder.CONFIG_METADATA``).
SERVICE_KEY = "service"
MAPPING_KEY = "mapping"
PROFILE_KEY = "profile"  # a periodic vehicle profile: {"name", "text"} (docs/profiles.md)
#: Vehicles a service takes on a link without ``--sysid`` unless ``--max-vehicles`` says.
DEFAULT_MAX_VEHICLES = 32
MAX_SYSTEM_IDS = 255  # a MAVLink system id is one byte (0 is the broadcast id)


@dataclass(frozen=True)
class LinkSecurity:
    """MAVLink 2 signing on the vehicle link. The key itself is never logged or published."""

    key: bytes | None = field(default=None, repr=False)
    #: With a key: still accept unsigned telemetry (counted), e.g. while a fleet migrates.
    accept_unsigned: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"signed": self.key is not None, "accept_unsigned": self.accept_unsigned}


@dataclass(frozen=True)
class Units:
    """The unit conversions of the MAVLink mapping (docs/mavlink.md)."""

    full_scale: float = 2.0  # model units at wire 1.0
    water_density: float = 1025.0  # kg/m³
    surface_pressure: float = 1013.25  # hPa

    def __post_init__(self) -> None:
        self.mapping()  # a bad value is refused here, with the unit's own message

    def mapping(self) -> TelemetryMapping:
        return TelemetryMapping(
            pressure=PressureDepth(self.water_density, self.surface_pressure),
            inputs=InputScale(self.full_scale),
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "full_scale": self.full_scale,
            "water_density": self.water_density,
            "surface_pressure": self.surface_pressure,
        }

    @classmethod
    def from_json(cls, stored: dict[str, Any] | None) -> Units:
        if not stored:
            return cls()
        return cls(
            full_scale=float(stored["full_scale"]),
            water_density=float(stored["water_density"]),
            surface_pressure=float(stored["surface_pressure"]),
        )


def _limits_json(limits: SetpointLimits) -> dict[str, float | None]:
    return {
        "min_depth": limits.min_depth,
        "max_depth": limits.max_depth,
        "max_abs_pitch": limits.max_abs_pitch,
    }


@dataclass(frozen=True)
class ServiceConfig:
    system_ids: tuple[int, ...] = ()  # empty: every vehicle on the link
    service_system_id: int = 255
    control_default: bool = False  # control state before any control message arrives
    stale_timeout: float = 3.0  # wall s without a sample → no commands
    health_period: float = 1.0  # wall s
    pipeline: PipelineSettings = field(default_factory=PipelineSettings)
    security: LinkSecurity = field(default_factory=LinkSecurity)
    units: Units = field(default_factory=Units)
    limits: SetpointLimits = field(default_factory=SetpointLimits)
    #: A periodic vehicle profile (docs/profiles.md): sample the vehicle's streams every
    #: ``sample_period`` s, command it as the profile says, and behave as its companion
    #: computer (heartbeat, stream requests). None: the lockstep ``glider`` contract.
    profile: Profile | None = None
    sample_period: float | None = None
    #: Release every step from the start (docs/lockstep.md); without it, lockstep starts
    #: when a vehicle announces it. Live only: not stored (replay sends nothing).
    lockstep: bool = False
    #: Vehicles served on a link without a ``system_ids`` list (``serve --max-vehicles``):
    #: the first this many system ids heard; a listed set is always served whole.
    max_vehicles: int = DEFAULT_MAX_VEHICLES

    def __post_init__(self) -> None:
        if not 1 <= self.max_vehicles <= MAX_SYSTEM_IDS:
            raise ValueError(
                f"--max-vehicles must be 1..{MAX_SYSTEM_IDS} (MAVLink system ids), "
                f"got {self.max_vehicles}"
            )

    def mapping(self) -> TelemetryMapping:
        return self.units.mapping()

    def to_json(self) -> dict[str, Any]:
        """The ``service`` part of the stored configuration."""
        return {
            "system_ids": list(self.system_ids),
            "control_default": self.control_default,
            "stale_timeout": self.stale_timeout,
            "pipeline": self.pipeline.to_json(),
            "signing": self.security.to_json(),
            "limits": _limits_json(self.limits),
            "max_vehicles": self.max_vehicles,
            **(
                {}
                if self.profile is None
                else {"profile": {"name": self.profile.name, "sample_period": self.sample_period}}
            ),
        }

    def stored(self) -> dict[str, Any]:
        """The configuration as a log stores it, decoded (what ``info`` prints)."""
        stored = {SERVICE_KEY: self.to_json(), MAPPING_KEY: self.units.to_json()}
        if self.profile is not None:
            stored[PROFILE_KEY] = {"name": self.profile.name, "text": self.profile.text}
        return stored

    def to_metadata(self) -> dict[str, str]:
        """The MCAP metadata record's content (string values, as MCAP requires)."""
        return {name: json.dumps(value) for name, value in self.stored().items()}

    @classmethod
    def from_stored(cls, stored: dict[str, Any]) -> ServiceConfig | None:
        """The configuration a log's metadata describes (``LogReader.config()``), or None
        when the log has none. The signing key is never stored: the result has none (a
        signed log replays without it)."""
        service = stored.get(SERVICE_KEY)
        if not isinstance(service, dict) or "pipeline" not in service:
            return None
        limits = service.get("limits") or {}
        profile = stored_profile(stored)
        periodic = profile is not None and profile.sampling.mode == "periodic"
        recorded = service.get("profile") or {}
        return cls(
            system_ids=tuple(service.get("system_ids", ())),
            control_default=service.get("control_default", False),
            stale_timeout=service.get("stale_timeout", 3.0),
            max_vehicles=service.get("max_vehicles", DEFAULT_MAX_VEHICLES),
            pipeline=PipelineSettings.from_json(service["pipeline"]),
            units=Units.from_json(stored.get(MAPPING_KEY)),
            limits=SetpointLimits(
                limits.get("min_depth"), limits.get("max_depth"), limits.get("max_abs_pitch")
            ),
            profile=profile if periodic else None,
            sample_period=(recorded.get("sample_period") or profile.sampling.period)
            if periodic and profile is not None
            else None,
        )


def stored_profile(stored: dict[str, Any]) -> Profile | None:
    """The vehicle profile a log stores (``serve --profile`` and ``import`` store theirs)."""
    entry = stored.get(PROFILE_KEY) or {}
    text = entry.get("text") if isinstance(entry, dict) else None
    return parse_profile(text, "(the log's stored profile)") if text else None


@dataclass(frozen=True)
class LogOptions:
    """Where and how ``serve`` writes its MCAP files."""

    directory: str | None = "logs"  # None: no log
    max_bytes: int = 256 * 1024 * 1024  # rotate after this size
    max_seconds: float = 3600.0  # rotate after this long


@dataclass(frozen=True)
class ServeConfig:
    """Everything ``glider-hil serve`` runs with: the stored part plus the live-only part."""

    service: ServiceConfig = field(default_factory=ServiceConfig)
    mavlink: str = "udpin:127.0.0.1:14550"  # pymavlink connection string
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    log: LogOptions = field(default_factory=LogOptions)
    duration: float | None = None  # wall s, then stop
    foxglove: LiveAddress | None = None  # the live view's address (None: no live view)


def parse_system_ids(text: str) -> tuple[int, ...]:
    """``--sysid`` values: ``7``, ``1-50`` or a comma list of both (``1-3,9``), each id a
    MAVLink system id (1..255); ValueError names what is wrong."""
    ids: list[int] = []
    for part in text.split(","):
        part = part.strip()
        low_text, dash, high_text = part.partition("-")
        try:
            low = int(low_text)
            high = int(high_text) if dash else low
        except ValueError:
            raise ValueError(f"--sysid {text!r}: expected N, N-M or a comma list") from None
        if not 1 <= low <= high <= 255:
            raise ValueError(f"--sysid {text!r}: ids are 1..255 and a range runs low-high")
        ids.extend(range(low, high + 1))
    return tuple(dict.fromkeys(ids))
