"""The service's configuration: one object, written to a log's metadata and read back here.

``ServiceConfig`` is what ``serve`` builds from its flags, what ``HilService`` runs with, what
the recorder stores as the MCAP metadata record ``glider-hil.config`` (``to_metadata``), and
what ``replay``, ``info`` and ``report`` read back (``ServiceConfig.from_stored``). The
record holds three JSON strings, ``service`` (identification, control, vehicles, limits,
whether the link is signed; never the key), ``mapping`` (the units the service ran with)
and ``profile`` (the vehicle profile's name and TOML text). Logs written before a field
existed read with that field's default; a log without ``mapping`` was written with the
default units, one without ``profile`` with the built-in ``glider`` profile.

``ServeConfig`` adds what only a live run needs (the link, Zenoh, the log files); it is not
stored.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cache
from typing import Any

from hil_service.inputs import SetpointLimits
from hil_service.listeners.zenoh_config import ZenohOptions
from hil_service.live.address import LiveAddress
from hil_service.pipeline import PipelineSettings
from protocols.keys import MAX_LINKS
from protocols.mapping import TelemetryMapping
from protocols.profiles import (
    DEFAULT_PROFILE,
    Profile,
    load_profile,
    parse_profile,
    sample_period_problem,
)
from protocols.units import InputScale, PressureDepth

#: Keys of the metadata record (``hil_service.mcap.recorder.CONFIG_METADATA``).
SERVICE_KEY = "service"
MAPPING_KEY = "mapping"
PROFILE_KEY = "profile"  # the vehicle profile: {"name", "text"} (docs/profiles.md)
#: Vehicles a service takes on a link without ``--sysid`` unless ``--max-vehicles`` says.
DEFAULT_MAX_VEHICLES = 32
MAX_SYSTEM_IDS = 255  # a MAVLink system id is one byte (0 is the broadcast id)
#: ``--vehicle-ids``: ``sysid`` (a system id is one vehicle on every link) or ``link`` (a
#: vehicle is a system id on one of the service's links; hil_service/vehicle_links.py).
VEHICLE_ID_MODES = ("sysid", "link")


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
    """The unit conversions of the MAVLink link (docs/mavlink.md); the defaults are
    ``protocols.units``'."""

    full_scale: float = InputScale.full_scale  # model units at wire 1.0
    water_density: float = PressureDepth.water_density  # kg/m³
    surface_pressure: float = PressureDepth.surface_hpa  # hPa

    def __post_init__(self) -> None:
        self.mapping()  # a bad value is refused here, with the unit's own message

    def mapping(self) -> TelemetryMapping:
        return TelemetryMapping(
            pressure=PressureDepth(self.water_density, self.surface_pressure),
            inputs=InputScale(self.full_scale),
        )

    @classmethod
    def of(cls, profile: Profile) -> Units:
        """The units a vehicle profile states."""
        return cls(
            profile.ballast.full_scale,
            profile.pressure.water_density,
            profile.pressure.surface_hpa,
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


@cache
def default_profile() -> Profile:
    """The built-in ``glider`` profile (parsed once; a profile is immutable)."""
    return load_profile(DEFAULT_PROFILE)


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
    #: Units that override the profile's (``serve --full-scale`` and the like); None: the
    #: profile's own.
    units: Units | None = None
    limits: SetpointLimits = field(default_factory=SetpointLimits)
    #: The vehicle profile (docs/profiles.md): where each signal is read, how the ballast is
    #: commanded, and how samples are formed: ``lockstep`` (one timestamp per plant step,
    #: ``glider``) or ``periodic`` (every ``sample_period`` s of the vehicle's streams, as
    #: its companion computer: heartbeat, stream requests).
    profile: Profile = field(default_factory=default_profile)
    sample_period: float | None = None
    #: Release every step from the start (docs/lockstep.md); without it, lockstep starts
    #: when a vehicle announces it. Live only: not stored (replay sends nothing).
    lockstep: bool = False
    #: Vehicles served on a link without a ``system_ids`` list (``serve --max-vehicles``):
    #: the first this many system ids heard; a listed set is always served whole.
    max_vehicles: int = DEFAULT_MAX_VEHICLES
    #: How vehicles are told apart (``serve --vehicle-ids``, docs/fleet.md): ``sysid``, or
    #: ``link``: each link has a system-id space of its own, a vehicle is (link, system id).
    vehicle_ids: str = "sysid"

    def __post_init__(self) -> None:
        if not (0 < self.health_period < float("inf")):
            raise ValueError(f"--health-period must be positive s, got {self.health_period}")
        # With NaN, health's "no sample for longer than this" is never true: never stale.
        if not (0 < self.stale_timeout < float("inf")):
            raise ValueError(
                f"--stale-timeout must be a positive finite number of s, got {self.stale_timeout}"
            )
        period_problem = (
            "" if self.sample_period is None else sample_period_problem(self.sample_period)
        )
        if period_problem:
            raise ValueError(f"--sample-period {period_problem}")
        if self.vehicle_ids not in VEHICLE_ID_MODES:
            raise ValueError(
                f"--vehicle-ids must be one of {', '.join(VEHICLE_ID_MODES)}, "
                f"got {self.vehicle_ids!r}"
            )
        if self.vehicle_ids == "link" and self.system_ids:
            raise ValueError(
                "--sysid names system ids of one id space: not with --vehicle-ids link "
                "(every link's vehicles are served, up to --max-vehicles)"
            )
        most = MAX_SYSTEM_IDS if self.vehicle_ids == "sysid" else MAX_SYSTEM_IDS * MAX_LINKS
        if not 1 <= self.max_vehicles <= most:
            what = "MAVLink system ids" if self.vehicle_ids == "sysid" else "255 per link"
            raise ValueError(f"--max-vehicles must be 1..{most} ({what}), got {self.max_vehicles}")

    @property
    def periodic(self) -> bool:
        return self.profile.sampling.mode == "periodic"

    def effective_units(self) -> Units:
        """The units the service runs with: the overrides, else the profile's."""
        return Units.of(self.profile) if self.units is None else self.units

    def vehicle_profile(self) -> Profile:
        """The profile with the units the service runs with."""
        units = self.effective_units()
        return self.profile.with_units(
            units.full_scale, units.water_density, units.surface_pressure
        )

    def mapping(self) -> TelemetryMapping:
        return self.effective_units().mapping()

    def to_json(self) -> dict[str, Any]:
        """The ``service`` part of the stored configuration (``vehicle_ids`` only when not
        the default: a log of one id space stores no ``vehicle_ids``, as the logs of
        services without that option do)."""
        stored = {
            "system_ids": list(self.system_ids),
            "control_default": self.control_default,
            "stale_timeout": self.stale_timeout,
            "pipeline": self.pipeline.to_json(),
            "signing": self.security.to_json(),
            "limits": _limits_json(self.limits),
            "max_vehicles": self.max_vehicles,
            "profile": {"name": self.profile.name, "sample_period": self.sample_period},
        }
        if self.vehicle_ids != "sysid":
            stored["vehicle_ids"] = self.vehicle_ids
        return stored

    def stored(self) -> dict[str, Any]:
        """The configuration as a log stores it, decoded (what ``info`` prints)."""
        return {
            SERVICE_KEY: self.to_json(),
            MAPPING_KEY: self.effective_units().to_json(),
            PROFILE_KEY: {"name": self.profile.name, "text": self.profile.text},
        }

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
        profile = stored_profile(stored) or default_profile()
        periodic = profile.sampling.mode == "periodic"
        recorded = (service.get("profile") or {}).get("sample_period")
        return cls(
            system_ids=tuple(service.get("system_ids", ())),
            control_default=service.get("control_default", False),
            stale_timeout=service.get("stale_timeout", 3.0),
            max_vehicles=service.get("max_vehicles", DEFAULT_MAX_VEHICLES),
            vehicle_ids=service.get("vehicle_ids", "sysid"),
            pipeline=PipelineSettings.from_json(service["pipeline"]),
            units=Units.from_json(stored[MAPPING_KEY]) if stored.get(MAPPING_KEY) else None,
            limits=SetpointLimits(
                limits.get("min_depth"), limits.get("max_depth"), limits.get("max_abs_pitch")
            ),
            profile=profile,
            sample_period=(profile.sampling.period if recorded is None else recorded)
            if periodic
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
    #: Further links (``serve --mavlink`` given again): links 2, 3, … (``LinkSet``).
    more_mavlink: tuple[str, ...] = ()


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
