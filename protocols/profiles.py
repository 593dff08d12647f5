"""Vehicle profiles: where each signal comes from, how ballast is read back and commanded,
and how samples are formed, read from a TOML file (docs/profiles.md describes every field).

Two are built in (``protocols/profiles/*.toml``): ``glider`` (glider-hil's own emulator, the
contract of ``protocols/mapping.py``, lockstep timestamps) and ``ardusub`` (asynchronous
streams, SERVO_OUTPUT_RAW PWM, DO_SET_SERVO). ``load_profile`` takes a built-in name or a
file path; a bad file raises ``ProfileError`` naming the file and the line.

A profile turns a received message into *readings* (signal, source rank, value) and a clock
reading (which clock, raw value), which ``hil_service.sources.sampler`` turns into samples; and it
turns a ballast command into the messages that carry it. One module over 500 lines: the
profile's dataclasses and their TOML parser (``_Parser``) change together, field by field.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field, replace
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple, NoReturn

from protocols.mavlink_io import MavMessage, dialect
from protocols.readings import MessageReader
from protocols.safety import SAFE_INPUTS
from protocols.units import (
    FULL_SCALE_RANGE,
    SURFACE_PRESSURE_RANGE,
    WATER_DENSITY_RANGE,
    InputScale,
    PressureDepth,
    range_problem,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

BUILTIN = ("glider", "ardusub")
DEFAULT_PROFILE = "glider"
SIGNALS = ("depth", "pitch", "pitch_rate", "climb")
REQUIRED_SIGNALS = ("depth", "pitch")
CONVERSIONS = ("linear", "pressure_to_depth")
MODES = ("lockstep", "periodic")
READBACKS = {"SERVO_OUTPUT_RAW": ("pwm", 16), "ACTUATOR_OUTPUT_STATUS": ("normalised", 32)}
COMMANDS = {"DO_SET_SERVO": ("pwm", 16), "DO_SET_ACTUATOR": ("normalised", 6)}
#: Clock kinds of ``hil_service.sources.sampler``: name → (seconds per tick, wrap modulus or 0).
CLOCKS = {"ms32": (1e-3, 1 << 32), "us32": (1e-6, 1 << 32), "us64": (1e-6, 0)}
AUTOPILOT_COMPONENT = 1
#: The shortest sampling period, s. MAVLink stamps the messages a periodic sample is formed
#: from in whole milliseconds (``time_boot_ms``): ticks closer than 1 ms cannot be told apart,
#: and a vehicle's clock advancing 1 ms would make thousands of them due at once.
MIN_SAMPLE_PERIOD = 1e-3
#: The longest sampling period, s: under half the wrap of a 32-bit µs clock (2^31 µs ≈
#: 2147 s, e.g. ``SERVO_OUTPUT_RAW.time_usec``), since a wrapping clock is unwrapped to the
#: candidate nearest the last stamp, and ``MAV_CMD_SET_MESSAGE_INTERVAL`` asks for a
#: stream's interval as an int32 of µs. Every staleness limit (twice a period) stays finite.
MAX_SAMPLE_PERIOD = 2000.0
#: The largest magnitude of any number in a profile (a scale, an offset, an interval):
#: far beyond any real one, and a value read or sent with it stays a finite float32.
MAX_NUMBER = 1e9
#: The smallest magnitude of a signal's ``scale``, the reciprocal of ``MAX_NUMBER``: finer
#: than any real unit conversion (degE7 to degrees is 1e-7), so a smaller one is a slip, and
#: at 1e-300 a reading is below float32's range (it would be 0 in any float32 it meets).
MIN_SCALE = 1.0 / MAX_NUMBER
#: The longest a periodic sample waits for late messages (``[sampling] delay``), in the
#: shortest of the sample period and the intervals the profile asks for: the sampler
#: (``hil_service.sources.sampler``) keeps the last 16 values of each source, 15 intervals
#: back, and takes a stamp more than max(2 s, 10 periods) behind the newest for a clock
#: step, not a late message. A sample waiting longer finds the values of its time gone.
MAX_DELAY_INTERVALS = 10


class ProfileError(ValueError):
    """A profile that cannot be used; the message names the file and, where known, the line."""


def sample_period_problem(period: float) -> str:
    """Why ``period`` (s) cannot be a sampling period, or "" when it can: it must lie in
    ``MIN_SAMPLE_PERIOD``..``MAX_SAMPLE_PERIOD`` (NaN lies in no range)."""
    if isinstance(period, bool) or not isinstance(period, (int, float)):
        return f"must be a number of s, got {period!r}"
    if not MIN_SAMPLE_PERIOD <= period <= MAX_SAMPLE_PERIOD:
        return (
            f"must be {MIN_SAMPLE_PERIOD:g}..{MAX_SAMPLE_PERIOD:g} s (MAVLink stamps are in "
            f"ms; 32-bit µs clocks wrap), got {period!r}"
        )
    return ""


class Reading(NamedTuple):
    """One value of one signal from one message: ``rank`` 0 is the preferred source."""

    signal: str
    rank: int
    value: float


@dataclass(frozen=True)
class Source:
    """One place a signal is read from: ``value = field·scale + offset`` (``linear``) or
    depth from absolute pressure in hPa (``pressure_to_depth``)."""

    message: str
    field: str
    index: int | None = None
    convert: str = "linear"
    scale: float = 1.0
    offset: float = 0.0
    interval: float | None = None  # s requested for the message; None: the sample period
    stale_after: float | None = None  # s; None: twice the interval
    optional: bool = False


@dataclass(frozen=True)
class PwmRange:
    minimum: int = 1100
    maximum: int = 1900
    neutral: int = 1500

    def to_wire(self, pwm: float) -> float:
        """µs → −1..1, linear on each side of neutral."""
        if pwm >= self.neutral:
            return min((pwm - self.neutral) / (self.maximum - self.neutral), 1.0)
        return max((pwm - self.neutral) / (self.neutral - self.minimum), -1.0)

    def from_wire(self, wire: float) -> int:
        wire = min(max(wire, -1.0), 1.0)
        span = self.maximum - self.neutral if wire >= 0 else self.neutral - self.minimum
        return round(self.neutral + wire * span)


@dataclass(frozen=True)
class Ballast:
    readback: str = "ACTUATOR_OUTPUT_STATUS"
    command: str = "DO_SET_ACTUATOR"
    full_scale: float = InputScale.full_scale  # model units at wire 1.0 (the paper's ±2)
    pwm: PwmRange = field(default_factory=PwmRange)
    depth_output: int = 1  # servo number (PWM) or actuator number (normalised), 1-based
    pitch_output: int = 2
    interval: float | None = None
    stale_after: float | None = None

    def output(self, channel: str) -> int:
        return self.depth_output if channel == "depth" else self.pitch_output

    def readback_wire(self, message: MavMessage, channel: str) -> float:
        return self._wire(message, self.output(channel))

    def _wire(self, message: MavMessage, n: int) -> float:
        """Output ``n``'s value in a readback message, on the wire's −1..1."""
        if self.readback == "SERVO_OUTPUT_RAW":
            return self.pwm.to_wire(getattr(message, f"servo{n}_raw"))
        return float(message.actuator[n - 1])

    def applied(self, message: MavMessage) -> tuple[float, float]:
        """The applied inputs (model units) in a readback message: ``readback_wire`` of
        each channel times ``full_scale``. Asked for every telemetry step from compiled
        code, where each Python call is a frame: the actuator readback is read here in one."""
        scale = self.full_scale
        if self.readback == "SERVO_OUTPUT_RAW":
            return (
                self._wire(message, self.depth_output) * scale,
                self._wire(message, self.pitch_output) * scale,
            )
        actuator = message.actuator
        return (
            float(actuator[self.depth_output - 1]) * scale,
            float(actuator[self.pitch_output - 1]) * scale,
        )


@dataclass(frozen=True)
class Sampling:
    mode: str = "lockstep"
    period: float | None = None  # s, periodic mode
    delay: float | None = None  # s waited for late messages before a sample; None: period/2


@dataclass(frozen=True)
class ControlChoices:
    """The profile's ``[control]`` table: what the service may do to this kind of vehicle
    when it must not command from its model (docs/control.md, "Do no harm")."""

    safe_input: str = "neutral"  # SAFE_INPUTS: where a tripped channel's input goes
    #: The probing excitation of a channel asked to command whose model does not pass the
    #: horizon test, a share of the actuator's range (0: none; docs/control.md, "Probing").
    probe: float = 0.0


@dataclass(frozen=True)
class Profile:
    name: str
    description: str = ""
    sampling: Sampling = field(default_factory=Sampling)
    pressure: PressureDepth = field(default_factory=PressureDepth)
    signals: dict[str, tuple[Source, ...]] = field(default_factory=dict)
    ballast: Ballast = field(default_factory=Ballast)
    control: ControlChoices = field(default_factory=ControlChoices)
    #: The TOML text it was read from (stored in logs' metadata).
    text: str = ""

    # ---- what to ask for and how stale is too stale --------------------------------
    def messages(self) -> tuple[str, ...]:
        """Every message the profile reads, readback included, in a stable order."""
        names = [s.message for sources in self.signals.values() for s in sources]
        names.append(self.ballast.readback)
        return tuple(dict.fromkeys(names))

    def intervals(self, sample_period: float) -> dict[str, float]:
        """The interval (s) to request for each message: the shortest asked of it."""
        wanted: dict[str, float] = {}
        pairs = [(s.message, s.interval) for sources in self.signals.values() for s in sources]
        pairs.append((self.ballast.readback, self.ballast.interval))
        for message, interval in pairs:
            value = sample_period if interval is None else interval
            wanted[message] = min(wanted.get(message, math.inf), value)
        return wanted

    def staleness(self, sample_period: float) -> dict[str, tuple[float, ...]]:
        """Per signal (``u_depth``/``u_pitch`` included), each source's staleness limit (s)."""

        def limit(interval: float | None, stale_after: float | None) -> float:
            if stale_after is not None:
                return stale_after
            return 2.0 * (sample_period if interval is None else interval)

        limits = {
            name: tuple(limit(s.interval, s.stale_after) for s in sources)
            for name, sources in self.signals.items()
        }
        ballast = (limit(self.ballast.interval, self.ballast.stale_after),)
        limits["u_depth"] = ballast
        limits["u_pitch"] = ballast
        return limits

    def delay_limit(self, sample_period: float) -> float:
        """The longest ``[sampling] delay`` (s) sampling at ``sample_period`` can use:
        ``MAX_DELAY_INTERVALS`` times the shortest of it and the intervals asked for."""
        shortest = min(sample_period, *self.intervals(sample_period).values())
        return MAX_DELAY_INTERVALS * shortest

    def delay_problem(self, sample_period: float) -> str:
        """Why ``[sampling] delay`` cannot serve sampling at ``sample_period`` (beyond
        ``delay_limit``), or "" when it can or the profile gives none."""
        delay = self.sampling.delay
        if delay is None:
            return ""
        limit = self.delay_limit(sample_period)
        # The limit is computed in binary: it may fall a rounding short of the decimal
        # a file states for it.
        if delay > limit * (1 + 1e-9):
            return (
                f"must be at most {limit:g} s, {MAX_DELAY_INTERVALS} times the shortest of the "
                f"period and the intervals asked for ({limit / MAX_DELAY_INTERVALS:g} s): a "
                f"sample waiting longer finds the values of its time gone, got {delay!r}"
            )
        return ""

    def step_messages(self) -> tuple[str, ...]:
        """The messages a lockstep step needs, all stamped with the step's time: the
        preferred source of every signal that is not optional, and the ballast readback."""
        names = [
            sources[0].message
            for sources in self.signals.values()
            if not all(s.optional for s in sources)
        ]
        names.append(self.ballast.readback)
        return tuple(dict.fromkeys(names))

    def with_units(
        self,
        full_scale: float | None = None,
        water_density: float | None = None,
        surface_hpa: float | None = None,
    ) -> Profile:
        """This profile with other units (None: keep the profile's); the text is kept."""
        pressure = replace(
            self.pressure,
            water_density=self.pressure.water_density if water_density is None else water_density,
            surface_hpa=self.pressure.surface_hpa if surface_hpa is None else surface_hpa,
        )
        ballast = replace(
            self.ballast,
            full_scale=self.ballast.full_scale if full_scale is None else full_scale,
        )
        if pressure == self.pressure and ballast == self.ballast:
            return self
        return replace(self, pressure=pressure, ballast=ballast)

    def optional_signals(self) -> frozenset[str]:
        return frozenset(
            name for name, sources in self.signals.items() if all(s.optional for s in sources)
        )

    # ---- reading messages ------------------------------------------------------------
    @cached_property
    def reader(self) -> MessageReader:
        """The compiled loop of ``readings`` (``protocols.readings``), built once: what the
        per-sample path calls, without a ``Reading`` per value."""
        plan: dict[str, list[tuple[str, int, Source]]] = {}
        for name, sources in self.signals.items():
            for rank, source in enumerate(sources):
                plan.setdefault(source.message, []).append((name, rank, source))
        return MessageReader(plan, self.pressure, self.ballast)

    def readings(self, message: MavMessage) -> list[Reading]:
        """Every signal value ``message`` carries under this profile (unit-converted)."""
        return [Reading(*reading) for reading in self.reader.readings(message)]

    # ---- commanding ------------------------------------------------------------------
    def command_messages(
        self, u_depth: float, u_pitch: float, target_system: int
    ) -> list[MavMessage]:
        """COMMAND_LONGs carrying a ballast command (model units; NaN leaves a channel)."""
        ballast = self.ballast
        wires = {
            "depth": u_depth / ballast.full_scale if math.isfinite(u_depth) else math.nan,
            "pitch": u_pitch / ballast.full_scale if math.isfinite(u_pitch) else math.nan,
        }
        if ballast.command == "DO_SET_SERVO":
            return [
                _command_long(
                    target_system,
                    dialect.MAV_CMD_DO_SET_SERVO,
                    [float(ballast.output(ch)), float(ballast.pwm.from_wire(wire))],
                )
                for ch, wire in wires.items()
                if not math.isnan(wire)
            ]
        params = [math.nan] * 6
        for ch, wire in wires.items():
            params[ballast.output(ch) - 1] = min(max(wire, -1.0), 1.0)
        return [_command_long(target_system, dialect.MAV_CMD_DO_SET_ACTUATOR, params)]


def _command_long(target_system: int, command: int, params: list[float]) -> MavMessage:
    values = [*params, *([math.nan] * (7 - len(params)))]
    values[6] = 0.0 if math.isnan(values[6]) else values[6]  # param7: index, never NaN
    return dialect.MAVLink_command_long_message(
        target_system, AUTOPILOT_COMPONENT, command, 0, *values
    )


_CLOCK_FIELDS: dict[type, tuple[str, str] | None] = {}


def _clock_field(cls: Any) -> tuple[str, str] | None:
    names = cls.fieldnames
    if "time_boot_ms" in names:
        return "ms32", "time_boot_ms"
    if "time_usec" in names:
        ftype = cls.fieldtypes[names.index("time_usec")]
        return ("us64" if ftype == "uint64_t" else "us32"), "time_usec"
    return None


def clock_of(message_name: str) -> tuple[str, str] | None:
    """The clock a message type carries: (``ms32``/``us32``/``us64``, field name), or None."""
    cls = getattr(dialect, f"MAVLink_{message_name.lower()}_message", None)
    return None if cls is None else _clock_field(cls)


def message_clock(message: MavMessage) -> tuple[str, int] | None:
    """The vehicle-clock stamp a message carries: (``ms32``/``us32``/``us64``, raw value),
    or None (VFR_HUD has none)."""
    cls = type(message)
    try:
        found = _CLOCK_FIELDS[cls]
    except KeyError:
        found = _CLOCK_FIELDS[cls] = _clock_field(cls)
    if found is None:
        return None
    return found[0], int(getattr(message, found[1]))


# ---- loading ---------------------------------------------------------------------------
def builtin_text(name: str) -> str:
    return resources.files("protocols").joinpath(f"profiles/{name}.toml").read_text()


def load_profile(name_or_path: str | Path) -> Profile:
    """A built-in profile by name, or a profile file."""
    if str(name_or_path) in BUILTIN:
        return parse_profile(builtin_text(str(name_or_path)), f"<built-in {name_or_path}>")
    path = Path(name_or_path)
    if not path.is_file():
        raise ProfileError(
            f"no profile {str(name_or_path)!r}: neither a built-in ({', '.join(BUILTIN)}) "
            "nor a file"
        )
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark, as editors write
    except (OSError, UnicodeDecodeError) as error:
        raise ProfileError(f"{path}: cannot read: {error}") from error
    return parse_profile(text, str(path))


def parse_profile(text: str, origin: str = "<profile>", stored: bool = False) -> Profile:
    """The profile ``text`` describes; ProfileError naming ``origin`` and the line.

    ``stored``: the text a log stores, read back to replay it. The log ran with that
    profile, so what is refused only as advice to whoever writes a profile (a key the run
    ignores, a delay the sampler cannot serve, a zero scale, an empty name) is let through;
    what the service cannot run with is refused as always."""
    try:
        data = tomllib.loads(text)
        return _Parser(text, origin, stored).profile(data)
    except tomllib.TOMLDecodeError as error:
        raise ProfileError(f"{origin}: not valid TOML: {error}") from error
    except RecursionError:  # tomllib reads nested arrays and tables recursively
        raise ProfileError(
            f"{origin}: arrays or tables nested too deeply to read (no profile field nests)"
        ) from None


#: The parser's defaults are the dataclasses' own (the units': ``protocols.units``).
_PRESSURE = PressureDepth()
_INPUTS = InputScale()


def _shown(value: Any) -> str:
    """``value`` for an error message: its repr, cut short (an array may be long)."""
    text = repr(value)
    return text if len(text) <= 60 else f"{text[:57]}..."


_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\-\"']+)\s*=")


class _Parser:
    """Checks a decoded TOML document field by field, naming the line of what is wrong."""

    def __init__(self, text: str, origin: str, stored: bool = False):
        self.lines = text.splitlines()
        self.origin = origin
        self.text = text
        #: Read back from a log (``parse_profile``): the advice below is not given.
        self.stored = stored

    def advise(self, message: str, table: str, key: str, occurrence: int = 0) -> None:
        """Refuse what a profile a user writes should not say (a key the run would ignore,
        a value that makes the signal useless), unless the profile is read back from a
        log, which ran with it."""
        if not self.stored:
            self.fail(message, table, key, occurrence)

    # -- locating lines --
    def _line(self, table: str, key: str | None = None, occurrence: int = 0) -> int | None:
        """The 1-based line of ``key`` in the ``occurrence``-th ``[table]``/``[[table]]``
        (or of the header itself), or None."""
        seen = -1
        inside = table == ""
        for number, line in enumerate(self.lines, start=1):
            header = _HEADER.match(line)
            if header:
                name = header.group(1).replace(" ", "")
                inside = name == table
                if inside:
                    seen += 1
                    if key is None and seen == occurrence:
                        return number
                continue
            if key is not None and inside and (seen == occurrence or table == ""):
                match = _KEY.match(line)
                if match and match.group(1).strip("\"'") == key:
                    return number
        return None

    def fail(
        self, message: str, table: str, key: str | None = None, occurrence: int = 0
    ) -> NoReturn:
        line = self._line(table, key, occurrence)
        if line is None and key is not None:
            line = self._line(table, None, occurrence)
        where = f"{self.origin} line {line}" if line is not None else self.origin
        place = f"[{table}]" if table else "top level"
        what = f"{place} {key}" if key else place
        raise ProfileError(f"{where}: {what}: {message}")

    # -- typed getters --
    def _table(self, data: dict, name: str, allowed: set[str]) -> dict:
        value = data.get(name.split(".")[-1], {})
        if not isinstance(value, dict):
            self.fail("must be a table", name)
        for key in value:
            if key not in allowed:
                self.fail(f"unknown field (known: {', '.join(sorted(allowed))})", name, key)
        return value

    def _number(
        self,
        table: dict,
        name: str,
        key: str,
        default: Any,
        occurrence: int = 0,
        positive: bool = False,
        bounds: tuple[float, float] | None = None,
        unit: str = "",
    ) -> Any:
        """A number of at most ``MAX_NUMBER`` in magnitude (``positive``: > 0), within
        ``bounds`` (in ``unit``) if given; None if absent and without a default."""
        value = table.get(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(f"must be a number, got {_shown(value)}", name, key, occurrence)
        if not math.isfinite(value) or (positive and value <= 0):
            self.fail(f"must be a positive finite number, got {value!r}", name, key, occurrence)
        if bounds is not None:
            problem = range_problem(value, bounds, unit)
            if problem:
                self.fail(problem, name, key, occurrence)
        elif abs(value) > MAX_NUMBER:
            self.fail(
                f"must be at most {MAX_NUMBER:g} in magnitude, got {value!r}", name, key, occurrence
            )
        return float(value)

    def _string(
        self,
        table: dict,
        name: str,
        key: str,
        default: str | None,
        choices: Any = None,
        occurrence: int = 0,
    ) -> str:
        value = table.get(key, default)
        if value is None:
            self.fail("is required", name, key, occurrence)
        if not isinstance(value, str):
            self.fail(f"must be a string, got {value!r}", name, key, occurrence)
        if choices is not None and value not in choices:
            self.fail(f"{value!r} is not one of {', '.join(choices)}", name, key, occurrence)
        return value

    def _integer(self, table: dict, name: str, key: str, default: int, low: int, high: int) -> int:
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            self.fail(f"must be an integer {low}..{high}, got {value!r}", name, key)
        return value

    # -- the document --
    def profile(self, data: dict) -> Profile:
        for key in data:
            if key not in {"profile", "sampling", "units", "signals", "ballast", "control"}:
                self.fail(
                    "unknown table (known: profile, sampling, units, signals, ballast, control)",
                    "",
                    key,
                )
        head = self._table(data, "profile", {"name", "description"})
        name = self._string(head, "profile", "name", None)
        if not name.strip():
            self.advise("must not be empty: logs store the profile by its name", "profile", "name")
        description = self._string(head, "profile", "description", "")
        sampling = self._sampling(self._table(data, "sampling", {"mode", "period", "delay"}))
        units = self._table(data, "units", {"water_density", "surface_pressure_hpa"})
        # Checked here against PressureDepth's bounds, so that a bad value names its line.
        pressure = PressureDepth(
            self._number(
                units,
                "units",
                "water_density",
                _PRESSURE.water_density,
                bounds=WATER_DENSITY_RANGE,
                unit="kg/m³",
            ),
            self._number(
                units,
                "units",
                "surface_pressure_hpa",
                _PRESSURE.surface_hpa,
                bounds=SURFACE_PRESSURE_RANGE,
                unit="hPa",
            ),
        )
        signals = self._signals(data.get("signals", {}))
        ballast = self._ballast(data.get("ballast", {}))
        control = self._table(data, "control", {"safe_input", "probe"})
        choices = ControlChoices(
            self._string(control, "control", "safe_input", "neutral", SAFE_INPUTS),
            self._number(
                control, "control", "probe", 0.0, bounds=(0.0, 1.0), unit="(a share of the range)"
            ),
        )
        profile = Profile(
            name, description, sampling, pressure, signals, ballast, choices, self.text
        )
        self._check_delay(profile)
        if sampling.mode == "lockstep":
            for message in profile.step_messages():
                if clock_of(message) is None:
                    self.fail(
                        f"lockstep groups a step's messages by their timestamp, and {message} "
                        "carries none: make its signal optional or sample periodically",
                        "sampling",
                        "mode",
                    )
        return profile

    def _check_delay(self, profile: Profile) -> None:
        """``[sampling] delay`` is for periodic sampling, and at most ``delay_limit``."""
        sampling = profile.sampling
        if sampling.delay is None:
            return
        if sampling.mode != "periodic" or sampling.period is None:
            self.advise(
                "is for periodic sampling (lockstep waits for no late message)",
                "sampling",
                "delay",
            )
            return
        problem = profile.delay_problem(sampling.period)
        if problem:
            self.advise(problem, "sampling", "delay")

    def _sampling(self, table: dict) -> Sampling:
        mode = self._string(table, "sampling", "mode", Sampling.mode, MODES)
        # Bounded by sample_period_problem, which says why.
        period = self._number(
            table, "sampling", "period", None, positive=True, bounds=(0.0, math.inf)
        )
        problem = "" if period is None else sample_period_problem(period)
        if problem:
            self.fail(problem, "sampling", "period")
        delay = self._number(table, "sampling", "delay", None)
        if delay is not None and delay < 0:
            self.fail(f"must be ≥ 0, got {delay!r}", "sampling", "delay")
        if mode == "periodic" and period is None:
            self.fail("periodic sampling needs a period (s)", "sampling", "mode")
        if mode == "lockstep" and period is not None:
            self.advise(
                "is for periodic sampling (lockstep takes one sample per plant step, at the "
                "timestamp its messages share)",
                "sampling",
                "period",
            )
        return Sampling(mode, period, delay)

    def _signals(self, table: Any) -> dict[str, tuple[Source, ...]]:
        if not isinstance(table, dict):
            self.fail("must be a table of [[signals.NAME]] entries", "signals")
        signals: dict[str, tuple[Source, ...]] = {}
        for name, entries in table.items():
            if name not in SIGNALS:
                self.fail(
                    f"unknown signal {name!r} (known: {', '.join(SIGNALS)})", f"signals.{name}"
                )
            if not isinstance(entries, list) or not entries:
                self.fail("must be one or more [[signals.NAME]] entries", f"signals.{name}")
            signals[name] = tuple(
                self._source(entry, f"signals.{name}", i) for i, entry in enumerate(entries)
            )
        for name in REQUIRED_SIGNALS:
            if name not in signals:
                self.fail(f"signal {name!r} is required: add a [[signals.{name}]] entry", "signals")
        return signals

    def _source(self, entry: dict, name: str, occurrence: int) -> Source:
        allowed = {
            "message",
            "field",
            "index",
            "convert",
            "scale",
            "offset",
            "interval",
            "stale_after",
            "optional",
        }
        for key in entry:
            if key not in allowed:
                self.fail(
                    f"unknown field (known: {', '.join(sorted(allowed))})", name, key, occurrence
                )
        message = self._string(entry, name, "message", None, occurrence=occurrence)
        message_class = getattr(dialect, f"MAVLink_{message.lower()}_message", None)
        if message_class is None:
            self.fail(f"no message {message!r} in the common dialect", name, "message", occurrence)
        field_name = self._string(entry, name, "field", None, occurrence=occurrence)
        if field_name not in message_class.fieldnames:
            self.fail(
                f"{message} has no field {field_name!r} (fields: "
                f"{', '.join(message_class.fieldnames)})",
                name,
                "field",
                occurrence,
            )
        position = message_class.fieldnames.index(field_name)
        # Array lengths are in wire order (ordered_fieldnames), types in declaration order.
        length = message_class.array_lengths[message_class.ordered_fieldnames.index(field_name)]
        if message_class.fieldtypes[position] == "char":
            self.fail(f"{message}.{field_name} is text, not a number", name, "field", occurrence)
        index = entry.get("index")
        if length and index is None:
            self.fail(
                f"{message}.{field_name} is an array of {length}: give index",
                name,
                "field",
                occurrence,
            )
        if index is not None and (
            isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < length
        ):
            self.fail(
                f"must be an integer 0..{length - 1}"
                if length
                else f"{message}.{field_name} is not an array",
                name,
                "index",
                occurrence,
            )
        optional = entry.get("optional", False)
        if not isinstance(optional, bool):
            self.fail("must be true or false", name, "optional", occurrence)
        convert = self._string(entry, name, "convert", Source.convert, CONVERSIONS, occurrence)
        if convert == "pressure_to_depth":
            self._refuse_linear_terms(entry, name, occurrence)
        scale = self._number(entry, name, "scale", Source.scale, occurrence)
        if abs(scale) < MIN_SCALE:
            why = (
                "must not be 0: every reading would be the offset, whatever the vehicle sends"
                if scale == 0
                else f"must be at least {MIN_SCALE:g} in magnitude, got {scale!r}: finer "
                "than any unit conversion (degE7 to degrees is 1e-7)"
            )
            self.advise(why, name, "scale", occurrence)
        return Source(
            message=message,
            field=field_name,
            index=index,
            convert=convert,
            scale=scale,
            offset=self._number(entry, name, "offset", Source.offset, occurrence),
            interval=self._number(entry, name, "interval", None, occurrence, positive=True),
            stale_after=self._number(entry, name, "stale_after", None, occurrence, positive=True),
            optional=optional,
        )

    def _refuse_linear_terms(self, entry: dict, name: str, occurrence: int) -> None:
        """``scale`` and ``offset`` are the linear conversion's: ``pressure_to_depth`` reads
        depth from pressure with the ``[units]`` alone, and would drop them unread."""
        for key in ("scale", "offset"):
            if key in entry:
                self.advise(
                    'is for convert = "linear": pressure_to_depth converts hPa to depth with '
                    "[units] water_density and surface_pressure_hpa alone",
                    name,
                    key,
                    occurrence,
                )

    def _ballast(self, table: Any) -> Ballast:
        allowed = {
            "readback",
            "command",
            "full_scale",
            "pwm_min",
            "pwm_max",
            "pwm_neutral",
            "interval",
            "stale_after",
            "depth",
            "pitch",
        }
        table = self._table({"ballast": table}, "ballast", allowed)
        readback = self._string(table, "ballast", "readback", Ballast.readback, READBACKS)
        command = self._string(table, "ballast", "command", Ballast.command, COMMANDS)
        pwm = PwmRange(
            self._integer(table, "ballast", "pwm_min", PwmRange.minimum, 500, 2500),
            self._integer(table, "ballast", "pwm_max", PwmRange.maximum, 500, 2500),
            self._integer(table, "ballast", "pwm_neutral", PwmRange.neutral, 500, 2500),
        )
        if not pwm.minimum < pwm.neutral < pwm.maximum:
            self.fail(
                f"needs pwm_min < pwm_neutral < pwm_max, got {pwm.minimum}, "
                f"{pwm.neutral}, {pwm.maximum}",
                "ballast",
                "pwm_neutral",
            )
        outputs = []
        for channel in ("depth", "pitch"):
            sub = self._table(table, f"ballast.{channel}", {"output"})
            high = min(READBACKS[readback][1], COMMANDS[command][1])
            default = Ballast.depth_output if channel == "depth" else Ballast.pitch_output
            outputs.append(self._integer(sub, f"ballast.{channel}", "output", default, 1, high))
        if outputs[0] == outputs[1]:
            self.fail("depth and pitch need different outputs", "ballast.pitch", "output")
        return Ballast(
            readback=readback,
            command=command,
            full_scale=self._number(
                table,
                "ballast",
                "full_scale",
                _INPUTS.full_scale,
                bounds=FULL_SCALE_RANGE,
                unit="model units",
            ),
            pwm=pwm,
            depth_output=outputs[0],
            pitch_output=outputs[1],
            interval=self._number(table, "ballast", "interval", None, positive=True),
            stale_after=self._number(table, "ballast", "stale_after", None, positive=True),
        )
