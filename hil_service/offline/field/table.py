"""The common form of every field format: samples in SI units, each counted irregularity.

Readers fill ``Columns`` (raw time-ordered rows as the files hold them, already in SI units),
``FieldData.from_columns`` cleans them: rows are put in time order (out-of-order counted),
repeated timestamps keep their last row (counted), rows whose time, depth or pitch is not a
number are dropped (counted), rows whose time, depth or pitch no glider can report or no log
can hold are dropped (counted: ``out_of_range``), and an input column missing in a file is
carried from the previous value within the same dive or left NaN (counted per file).
Nothing is dropped without a count in ``Issues``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from protocols.samples import DEPTH_RANGE

#: The latest log time, ns since 1970-01-01 UTC: MCAP log times are uint64 (2554-07-21).
MAX_LOG_TIME_NS = (1 << 64) - 1
#: Times a log can hold, s since the epoch; the upper bound is exclusive: below it, t·1e9
#: rounds to a uint64.
LOG_TIME_RANGE = (0.0, (MAX_LOG_TIME_NS + 1) / 1e9)
#: Pitch a glider can report, rad: an Euler pitch lies within ±90° by definition (stricter
#: than the ±π a live sample may carry, ``protocols.samples.is_plausible``).
PITCH_LIMIT = math.pi / 2
RANGE_NOTE = (
    f"out of range: a time before 1970 or after 2554 (what a log holds), a depth outside "
    f"{DEPTH_RANGE[0]:g}..{DEPTH_RANGE[1]:g} m or a pitch beyond ±90°"
)


#: Before 1980-01-01 (s since 1970) no glider logged: data that ends there either has
#: times relative to its start, or was read in too small a unit (seconds read as ms land
#: in January 1970).
EARLIEST_GLIDER_TIME = 315_532_800.0
EARLY_TIME_NOTE = (
    "every time falls before 1980, when no glider logged: times relative to the start, or "
    "a time unit too small (seconds read as milliseconds compress the record 1,000-fold)?"
)

#: Dive numbers are stored as int64: a number read from a file must lie within ±2⁶³.
DIVE_LIMIT = 2.0**63


def whole_dive(value: float) -> int:
    """A number read from a file as a dive number (truncated to a whole one); ValueError
    when it is not finite or not within int64."""
    if not (math.isfinite(value) and abs(value) < DIVE_LIMIT):
        raise ValueError(f"dive number {value!r} is not a finite number within ±2^63")
    return int(value)


class FieldError(ValueError):
    """A file that cannot be read: the message names the file (and the line when known)."""


class UnreadableFile(FieldError):
    """A file whose bytes its format's reader cannot take at all: cut short in transfer,
    damaged, not of its kind inside. Among several files of an import it is skipped and
    named (``skip_unreadable``); alone it is the import's error. An error of meaning (units
    the import cannot read, files of two gliders, a sensor list not in the cache) is never
    skipped: reading on would import the wrong numbers, or none the user can fix later."""

    def __init__(self, path: object, message: str) -> None:
        super().__init__(message)
        self.path = str(path)


@dataclass
class Issues:
    """Counts of what the import found and did about it; ``notes``: one line each."""

    rows: int = 0
    out_of_order: int = 0
    repeated_time: int = 0
    nan_rows: int = 0  # rows without a finite time, depth or pitch: dropped
    unparsable_rows: int = 0  # text rows with a field that is no number: dropped
    out_of_range: int = 0  # rows with a time, depth or pitch out of range: dropped
    missing_columns: dict[str, list[str]] = field(default_factory=dict)  # file → columns
    filled_inputs: int = 0  # input values held from the previous sample (missing/NaN)
    surface_rows: int = 0  # samples the vehicle marked at the surface: not identified
    unreadable_files: dict[str, str] = field(default_factory=dict)  # path → why: skipped
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "rows": self.rows,
            "out_of_order": self.out_of_order,
            "repeated_time": self.repeated_time,
            "nan_rows": self.nan_rows,
            "unparsable_rows": self.unparsable_rows,
            "out_of_range": self.out_of_range,
            "missing_columns": {k: list(v) for k, v in self.missing_columns.items()},
            "filled_inputs": self.filled_inputs,
            "surface_rows": self.surface_rows,
            "unreadable_files": dict(self.unreadable_files),
            "notes": list(self.notes),
        }

    def describe(self) -> list[str]:
        lines = [
            f"{self.rows} rows read; {self.out_of_order} out of time order (sorted), "
            f"{self.repeated_time} repeated timestamps (last kept), {self.nan_rows} without "
            f"time/depth/pitch, {self.unparsable_rows} unparsable and {self.out_of_range} "
            f"out of range (dropped), "
            f"{self.filled_inputs} input values held from the previous sample, "
            f"{self.surface_rows} at the surface (not identified)"
            + (
                f"; {len(self.unreadable_files)} file(s) that could not be read skipped"
                if self.unreadable_files
                else ""
            )
        ]
        for path, columns in self.missing_columns.items():
            lines.append(f"{path}: missing column(s) {', '.join(columns)}")
        return lines + list(self.notes)


Item = TypeVar("Item")
Read = TypeVar("Read")


def read_each(
    items: Sequence[Item],
    read: Callable[[Item], Read],
    issues: Issues,
    files: int | None = None,
) -> list[tuple[Item, Read]]:
    """``read`` of each item (a file, or a file with its dive number) in order, beside what
    it returned; an item it raises ``UnreadableFile`` for is skipped (``skip_unreadable``).
    ``files``: how many files the import was given, when ``items`` are what is left of them
    after an earlier pass (default: ``len(items)``)."""
    given = len(items) if files is None else files
    results: list[tuple[Item, Read]] = []
    for item in items:
        try:
            results.append((item, read(item)))
        except UnreadableFile as error:
            skip_unreadable(error, issues, given)
    return results


def skip_unreadable(error: UnreadableFile, issues: Issues, files: int) -> None:
    """A file of an import of ``files`` files that cannot be read at all: skipped, named in
    the notes with why, and listed in ``unreadable_files``. A dive lost in transfer leaves
    the others to identify from; the import fails only when it was the one file."""
    if files < 2:
        raise error
    issues.unreadable_files[error.path] = str(error)
    issues.notes.append(f"{error}: skipped")


def check_something_read(read_files: list[str], issues: Issues, files: int) -> None:
    """The error of an import of ``files`` files none of which could be read (each was
    skipped: ``issues.unreadable_files``)."""
    if files and not read_files:
        first = next(iter(issues.unreadable_files.values()), "")
        raise FieldError(f"none of the {files} files could be read; the first: {first}")


@dataclass
class Columns:
    """Rows as read, one list per quantity (SI units: s since the epoch, m, rad; inputs in
    their native units), ``dive``: the dive (or file) each row belongs to, ``in_dive``:
    False for a row the vehicle marked at the surface."""

    t: list[float] = field(default_factory=list)
    depth: list[float] = field(default_factory=list)
    pitch: list[float] = field(default_factory=list)
    buoyancy: list[float] = field(default_factory=list)
    pitch_input: list[float] = field(default_factory=list)
    dive: list[int] = field(default_factory=list)
    in_dive: list[bool] = field(default_factory=list)

    def extend(self, **values: Any) -> None:
        for name, column in values.items():
            getattr(self, name).extend(column)


@dataclass(frozen=True)
class Conversion:
    """How one quantity was read: the source variable, its unit, and the factor applied."""

    quantity: str
    variable: str
    unit: str
    to: str
    scale: float = 1.0
    offset: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "quantity": self.quantity,
            "variable": self.variable,
            "unit": self.unit,
            "to": self.to,
            "scale": self.scale,
            "offset": self.offset,
        }


@dataclass(frozen=True)
class InputScaling:
    """An input's native range onto model units: u = full_scale·(x − centre)/half_range."""

    centre: float
    half_range: float

    def to_model(self, x: np.ndarray, full_scale: float) -> np.ndarray:
        """Model units of native values; one whose model value lies beyond float range
        (a damaged 1e308 in a file) is ±inf, which the writer clips to full scale and
        counts, without numpy's overflow warning."""
        with np.errstate(over="ignore"):
            return full_scale * (np.asarray(x, dtype=float) - self.centre) / self.half_range

    def as_dict(self) -> dict[str, float]:
        return {"centre": self.centre, "half_range": self.half_range}


@dataclass
class FieldData:
    """Clean, time-ordered samples of one vehicle (every row finite in t, depth, pitch)."""

    format: str
    files: list[str]
    t: np.ndarray
    depth: np.ndarray
    pitch: np.ndarray
    buoyancy: np.ndarray
    pitch_input: np.ndarray
    dive: np.ndarray
    in_dive: np.ndarray
    conversions: list[Conversion]
    scaling: dict[str, InputScaling]
    issues: Issues
    vehicle: str = ""

    @property
    def size(self) -> int:
        return int(self.t.size)

    @classmethod
    def from_columns(
        cls,
        fmt: str,
        files: list[str],
        columns: Columns,
        conversions: list[Conversion],
        scaling: dict[str, InputScaling],
        issues: Issues,
        vehicle: str = "",
    ) -> FieldData:
        t = np.asarray(columns.t, dtype=float)
        data = {
            "depth": np.asarray(columns.depth, dtype=float),
            "pitch": np.asarray(columns.pitch, dtype=float),
            "buoyancy": np.asarray(columns.buoyancy, dtype=float),
            "pitch_input": np.asarray(columns.pitch_input, dtype=float),
            "dive": _dives(fmt, files, columns.dive),
            "in_dive": np.asarray(columns.in_dive, dtype=bool),
        }
        sizes = {t.size, *(a.size for a in data.values())}
        if len(sizes) != 1:
            raise FieldError(f"{fmt}: columns of unequal length {sorted(sizes)} (a reader bug)")
        issues.rows += int(t.size)
        finite = np.isfinite(t) & np.isfinite(data["depth"]) & np.isfinite(data["pitch"])
        issues.nan_rows += int(np.count_nonzero(~finite))
        t = t[finite]
        data = {k: v[finite] for k, v in data.items()}
        if t.size and not np.any(is_log_time(t)):
            raise no_log_time(", ".join(files), float(t[0]), "are they seconds since 1970?")
        plausible = in_range(t, data["depth"], data["pitch"])
        if not plausible.all():
            issues.out_of_range += int(np.count_nonzero(~plausible))
            issues.notes.append(RANGE_NOTE)
        t = t[plausible]
        data = {k: v[plausible] for k, v in data.items()}
        if t.size and float(np.max(t)) < EARLIEST_GLIDER_TIME:
            issues.notes.append(EARLY_TIME_NOTE)
        if t.size > 1:
            issues.out_of_order += int(np.count_nonzero(np.diff(t) < 0))
        order = np.argsort(t, kind="stable")
        t = t[order]
        data = {k: v[order] for k, v in data.items()}
        if t.size > 1:
            # A repeated timestamp keeps its last row (the later record of the same time).
            last = np.ones(t.size, dtype=bool)
            last[:-1] = np.diff(t) > 0
            issues.repeated_time += int(np.count_nonzero(~last))
            t = t[last]
            data = {k: v[last] for k, v in data.items()}
        issues.surface_rows += int(np.count_nonzero(~data["in_dive"]))
        for name in ("buoyancy", "pitch_input"):
            issues.filled_inputs += _hold_inputs(data[name], data["dive"])
        return cls(
            fmt,
            files,
            t,
            data["depth"],
            data["pitch"],
            data["buoyancy"],
            data["pitch_input"],
            data["dive"],
            data["in_dive"],
            conversions,
            scaling,
            issues,
            vehicle,
        )


def _dives(fmt: str, files: list[str], dive: list[int]) -> np.ndarray:
    """The dive column as int64; a number beyond it is an error naming the files (each
    reader checks its own numbers first, to name the one file)."""
    try:
        return np.asarray(dive, dtype=np.int64)
    except OverflowError as error:
        raise FieldError(f"{', '.join(files)}: a dive number beyond int64 ({fmt})") from error


def is_log_time(t: np.ndarray) -> np.ndarray:
    """Which of the times (s since the epoch) a log can hold (``LOG_TIME_RANGE``)."""
    return (t >= LOG_TIME_RANGE[0]) & (t < LOG_TIME_RANGE[1])


def in_range(t: np.ndarray, depth: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Which rows a glider can report and a log can hold: a log time, a depth in
    ``DEPTH_RANGE`` and a pitch within ``PITCH_LIMIT``. Everything beyond is a damaged
    value, and would not fit the telemetry's 32-bit floats or the log's uint64 times."""
    depth_ok = (depth >= DEPTH_RANGE[0]) & (depth <= DEPTH_RANGE[1])
    return is_log_time(t) & depth_ok & (np.abs(pitch) <= PITCH_LIMIT)


def no_log_time(where: str, first: float, hint: str) -> FieldError:
    """The error for data none of whose times a log can hold: most likely a wrong unit."""
    return FieldError(
        f"{where}: no time between 1970-01-01 and 2554-07-21 UTC, what a log can hold "
        f"(the first: {first:g} s since 1970); {hint}"
    )


def _hold_inputs(values: np.ndarray, dive: np.ndarray) -> int:
    """Fill NaN inputs in place with the previous value of the same dive; the count filled
    (a NaN before any value of its dive stays NaN and its sample is not identified)."""
    filled = 0
    for k in range(1, values.size):
        if not np.isfinite(values[k]) and dive[k] == dive[k - 1] and np.isfinite(values[k - 1]):
            values[k] = values[k - 1]
            filled += 1
    return filled
