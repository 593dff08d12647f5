"""The service's configuration: one object, written to a log's metadata and read back here.

``ServiceConfig`` is what ``serve`` builds from its flags, what ``HilService`` runs with, what
the recorder stores as the MCAP metadata record ``glider-hil.config`` (``to_metadata``), and
what ``replay``, ``info`` and ``report`` read back (``ServiceConfig.from_stored``). The
record holds three JSON strings, ``service`` (identification, control, vehicles, limits,
whether the link is signed; never the key), ``mapping`` (the units the service ran with)
and ``profile`` (the vehicle profile's name and TOML text). Logs written before a field
existed read with that field's default; a log without ``mapping`` was written with the
default units, one without ``profile`` with the built-in ``glider`` profile. A value of the
wrong JSON type or out of range is refused where it is read (``from_stored``) with a
``StoredConfigError`` naming the log and the stored key, never read as a default.

``ServeConfig`` adds what only a live run needs (the link, Zenoh, the log files); it is not
stored.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from functools import cache
from pathlib import Path
from typing import Any

from hil_service.inputs import SetpointLimits
from hil_service.listeners.zenoh_config import ZenohOptions
from hil_service.live.address import LiveAddress
from hil_service.mcap.reader import StoredConfigError
from hil_service.pipeline import ControlSettings, PipelineSettings, VehiclePipeline
from hil_service.umodel import build_model
from protocols.keys import CHANNELS, MAX_LINKS
from protocols.mapping import TelemetryMapping
from protocols.profiles import (
    DEFAULT_PROFILE,
    Profile,
    ProfileError,
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
    def from_json(cls, stored: Any) -> Units:
        """The units a log stores (``mapping``): all three, each a number; StoredConfigError
        names the one missing or wrong."""
        values = _object(stored, MAPPING_KEY)
        numbers: dict[str, float] = {}
        for name in ("full_scale", "water_density", "surface_pressure"):
            key = f"{MAPPING_KEY}.{name}"
            if name not in values:
                raise StoredConfigError(key, "missing")
            numbers[name] = float(_typed(values[name], float, key))
        try:
            return cls(**numbers)
        except ValueError as error:
            raise StoredConfigError(MAPPING_KEY, str(error)) from None


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
    def vehicle_slots(self) -> int:
        """The most vehicles served: ``max_vehicles``, or the ``system_ids`` list when it
        names more (a listed set is always served whole)."""
        return max(self.max_vehicles, len(self.system_ids or ()))

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
    def from_stored(
        cls, stored: dict[str, Any], log: str | Path | None = None
    ) -> ServiceConfig | None:
        """The configuration a log's metadata describes (``LogReader.config()``), or None
        when the log has none. The signing key is never stored: the result has none (a
        signed log replays without it).

        StoredConfigError, naming ``log`` and the stored key, for a value of the wrong JSON
        type or out of range: such a log is refused, never read with a default instead."""
        try:
            return cls._read_stored(stored)
        except StoredConfigError as error:
            raise _naming(error, log) from None

    @classmethod
    def _read_stored(cls, stored: dict[str, Any]) -> ServiceConfig | None:
        service = stored.get(SERVICE_KEY)
        if service is None or "pipeline" not in _object(service, SERVICE_KEY):
            return None
        pipeline = _pipeline(service["pipeline"])
        profile = stored_profile(stored) or default_profile()
        mapping = stored.get(MAPPING_KEY)
        units = None if mapping is None else Units.from_json(mapping)
        limits = _optional_object(service, "limits", f"{SERVICE_KEY}.limits")
        recorded = _typed(
            _optional_object(service, "profile", f"{SERVICE_KEY}.profile").get("sample_period"),
            float,
            f"{SERVICE_KEY}.profile.sample_period",
            nullable=True,
        )
        periodic = profile.sampling.mode == "periodic"
        system_ids = _system_ids(service.get("system_ids", []))
        control_default = _service_value(service, "control_default", bool, False)
        stale_timeout = _service_value(service, "stale_timeout", float, 3.0)
        max_vehicles = _service_value(service, "max_vehicles", int, DEFAULT_MAX_VEHICLES)
        vehicle_ids = _service_value(service, "vehicle_ids", str, "sysid")
        try:
            return cls(
                system_ids=system_ids,
                control_default=control_default,
                stale_timeout=stale_timeout,
                max_vehicles=max_vehicles,
                vehicle_ids=vehicle_ids,
                pipeline=pipeline,
                units=units,
                limits=SetpointLimits(
                    limits.get("min_depth"), limits.get("max_depth"), limits.get("max_abs_pitch")
                ),
                profile=profile,
                sample_period=(profile.sampling.period if recorded is None else recorded)
                if periodic
                else None,
            )
        except ValueError as error:
            raise _flag_as_stored_key(error) from None


def sample_period_delay_problem(profile: Profile, sample_period: float) -> str:
    """Why ``--sample-period`` cannot sample with ``profile``'s ``[sampling] delay``, or "":
    a profile's delay is checked against its own period, and a shorter period asked for on
    the command line shortens what the sampler can wait."""
    problem = profile.delay_problem(sample_period)
    if not problem:
        return ""
    return f"--sample-period {sample_period:g}: the profile's [sampling] delay {problem}"


def stored_profile(stored: dict[str, Any], log: str | Path | None = None) -> Profile | None:
    """The vehicle profile a log stores (``serve --profile`` and ``import`` store theirs), or
    None when it stores none; StoredConfigError, naming ``log``, when it cannot be read."""
    entry = stored.get(PROFILE_KEY)
    if entry is None:
        return None
    key = f"{PROFILE_KEY}.text"
    try:
        text = _typed(_object(entry, PROFILE_KEY).get("text"), str, key, nullable=True)
        return parse_profile(text, "TOML", stored=True) if text else None
    except ProfileError as error:
        raise _naming(StoredConfigError(key, str(error)), log) from None
    except StoredConfigError as error:
        raise _naming(error, log) from None


def stored_pipeline(stored: dict[str, Any]) -> dict[str, Any] | None:
    """The pipeline settings a log's decoded configuration holds (``service.pipeline``), as
    stored, or None when it holds none (``ServiceConfig.from_stored`` reads them)."""
    service = stored.get(SERVICE_KEY)
    pipeline = service.get("pipeline") if isinstance(service, dict) else None
    return pipeline if isinstance(pipeline, dict) else None


# ---- reading the stored values ------------------------------------------------------------

#: The ``serve`` flag each stored value is set by. The checks of ``ServiceConfig`` and
#: ``SetpointLimits`` name the flag; a value read from a log is named by its stored key.
_STORED_KEYS = {
    "--stale-timeout": f"{SERVICE_KEY}.stale_timeout",
    "--sample-period": f"{SERVICE_KEY}.profile.sample_period",
    "--vehicle-ids": f"{SERVICE_KEY}.vehicle_ids",
    "--sysid": f"{SERVICE_KEY}.system_ids",
    "--max-vehicles": f"{SERVICE_KEY}.max_vehicles",
    "--min-depth": f"{SERVICE_KEY}.limits.min_depth",
    "--max-depth": f"{SERVICE_KEY}.limits.max_depth",
    "--max-pitch": f"{SERVICE_KEY}.limits.max_abs_pitch",
}


def _is_integer(value: Any) -> bool:
    """A JSON integer (JSON true is not one, though Python counts a bool as an int)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    """A JSON number: an integer or a float, not a bool."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


#: A stored value's JSON type, by the Python type it is read as: what the message calls it,
#: and the test.
_KINDS: dict[type, tuple[str, Callable[[Any], bool]]] = {
    bool: ("true or false", lambda value: isinstance(value, bool)),
    int: ("an integer", _is_integer),
    float: ("a number", _is_number),
    str: ("a string", lambda value: isinstance(value, str)),
}


#: Fields of ``PipelineSettings`` and ``ControlSettings`` whose None a log stores as null:
#: the input lags' choice left to the model, a horizon test without the mean's threshold.
#: Named here, not read from the annotations, which a compiled dataclass does not keep.
_NULLABLE_SETTINGS = frozenset({"choose_input_lags", "mean_fit"})


def _naming(error: StoredConfigError, log: str | Path | None) -> StoredConfigError:
    """``error``, naming ``log`` when it is given and the error names no log yet."""
    return error if log is None or error.log is not None else error.of_log(log)


def _flag_as_stored_key(error: ValueError) -> StoredConfigError:
    """A check's ValueError, which names the ``serve`` flag, as a StoredConfigError naming
    the stored key instead: the user of ``replay`` or ``report`` gave no such flag."""
    message = str(error)
    flag = message.split(" ", 1)[0]
    key = _STORED_KEYS.get(flag)
    problem = message[len(flag) :].lstrip() if key is not None else message
    for other, stored_key in _STORED_KEYS.items():
        problem = problem.replace(other, stored_key)
    return StoredConfigError(key or SERVICE_KEY, problem)


def shown_json(value: Any) -> str:
    """A decoded JSON value as an error message quotes it: its JSON, shortened."""
    text = json.dumps(value)
    return text if len(text) <= 80 else f"{text[:77]}..."


def _object(value: Any, key: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise StoredConfigError(key, f"expected an object, got {shown_json(value)}")
    return value


def _optional_object(parent: dict[str, Any], name: str, key: str) -> dict[str, Any]:
    """``parent[name]``, an object; {} when it is absent or null."""
    value = parent.get(name)
    return {} if value is None else _object(value, key)


def _typed(value: Any, kind: type, key: str, nullable: bool = False) -> Any:
    """``value`` when its JSON type is ``kind``'s (or it is null and ``nullable``)."""
    if value is None and nullable:
        return None
    expected, fits = _KINDS[kind]
    if not fits(value):
        or_null = " or null" if nullable else ""
        raise StoredConfigError(key, f"expected {expected}{or_null}, got {shown_json(value)}")
    return value


def _service_value(service: dict[str, Any], name: str, kind: type, default: Any) -> Any:
    """``service[name]`` of JSON type ``kind``, or ``default`` in a log written without it
    (ranges are ``ServiceConfig``'s own checks)."""
    if name not in service:
        return default
    return _typed(service[name], kind, f"{SERVICE_KEY}.{name}")


def _system_ids(value: Any) -> tuple[int, ...]:
    if not isinstance(value, list) or not all(
        _is_integer(sid) and 1 <= sid <= MAX_SYSTEM_IDS for sid in value
    ):
        raise StoredConfigError(
            f"{SERVICE_KEY}.system_ids",
            f"expected a list of system ids 1..{MAX_SYSTEM_IDS}, got {shown_json(value)}",
        )
    return tuple(value)


def _settings_fields(stored: dict[str, Any], defaults: Any, key: str) -> None:
    """Each stored field of a settings dataclass has the JSON type of its default value, or
    is null where the settings take None (``_NULLABLE_SETTINGS``). Fields of other types
    (nested settings, model options) are checked by their readers."""
    for spec in fields(defaults):
        kind = type(getattr(defaults, spec.name))
        if spec.name in stored and kind in _KINDS:
            nullable = spec.name in _NULLABLE_SETTINGS
            _typed(stored[spec.name], kind, f"{key}.{spec.name}", nullable)


def _pipeline(value: Any) -> PipelineSettings:
    """The stored identifier and controller settings, each field of its JSON type, and
    every channel's model built once from them (its options are the model's to check)."""
    key = f"{SERVICE_KEY}.pipeline"
    stored = _object(value, key)
    known = {spec.name for spec in fields(PipelineSettings)}
    for name in stored:
        if name not in known:
            raise StoredConfigError(f"{key}.{name}", "not a setting of this version's pipeline")
    _settings_fields(stored, PipelineSettings(), key)
    control = _optional_object(stored, "control", f"{key}.control")
    _settings_fields(control, ControlSettings(), f"{key}.control")
    options = _optional_object(stored, "model_options", f"{key}.model_options")
    for channel, chosen in options.items():
        _object(chosen, f"{key}.model_options.{channel}")
    burn_in = stored.get("burn_in", 0)
    if burn_in < 0:
        raise StoredConfigError(f"{key}.burn_in", f"must be ≥ 0 samples, got {burn_in}")
    try:
        settings = PipelineSettings.from_json(stored)
    except (TypeError, ValueError) as error:
        raise StoredConfigError(key, str(error)) from None
    for channel in CHANNELS:
        try:
            build_model(settings.model, **settings.options_for(channel))
        except (TypeError, ValueError) as error:
            raise StoredConfigError(f"{key}.model_options.{channel}", str(error)) from None
    try:
        VehiclePipeline(settings)
    except (TypeError, ValueError) as error:
        raise StoredConfigError(key, str(error)) from None
    return settings


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
    #: Seconds the links poll before they sleep (``serve --spin-wait``; docs/lockstep.md,
    #: "Two cores"). Live only: not stored (replay reads no link).
    spin_wait: float = 0.0


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
