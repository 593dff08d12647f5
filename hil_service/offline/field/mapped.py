"""Any CSV (or Parquet, with ``pyarrow`` installed) with a TOML mapping file.

The mapping says which column is the time, the depth (or the pressure), the pitch, the
buoyancy input and the pitch input, their units and the inputs' full scale; its format and
an example are in docs/field-data.md. A mapping with an unknown table or key, a unit not
listed, or a column the file lacks is an error naming the file and the line; so is a
header naming twice a column the mapping uses. A row the CSV parser refuses (a field over
its size limit) is counted unparsable, as a row with a field that is no number.
"""

from __future__ import annotations

import csv
import math
import sys
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from hil_service.offline.field.table import (
    Columns,
    Conversion,
    FieldData,
    FieldError,
    InputScaling,
    Issues,
    UnreadableFile,
    check_something_read,
    is_log_time,
    no_log_time,
    read_each,
    whole_dive,
)
from protocols.input_files import not_a_file
from protocols.payload_json import is_finite_number
from protocols.units import SURFACE_PRESSURE_RANGE, WATER_DENSITY_RANGE, range_problem

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

STANDARD_GRAVITY = 9.80665
#: unit → (factor to SI, offset): time to s, depth to m, pitch to rad, pressure to Pa.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0, "h": 3600.0, "days": 86400.0}
DEPTH_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
PRESSURE_UNITS = {"dbar": 1e4, "bar": 1e5, "kPa": 1e3, "hPa": 1e2, "Pa": 1.0, "mbar": 1e2}
PITCH_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}
UNPARSABLE_NOTE = "unparsable row dropped"
TABLES: dict[str, set[str]] = {
    "file": {"kind", "delimiter", "comment"},
    "time": {"column", "unit", "format"},
    "depth": {"column", "unit"},
    "pressure": {"column", "unit", "water_density", "surface"},
    "pitch": {"column", "unit"},
    "buoyancy": {"column", "unit", "centre", "full_scale"},
    "pitch_input": {"column", "unit", "centre", "full_scale"},
    "dive": {"column"},
    "surface": {"column", "values"},
}
REQUIRED_TABLES = ("time", "pitch", "buoyancy", "pitch_input")
#: The TOML type of each key's value: text, a number, or a list (``[surface] values``).
TEXT_KEYS = frozenset({"column", "unit", "format", "kind", "delimiter", "comment"})
NUMBER_KEYS = frozenset({"centre", "full_scale", "water_density", "surface"})
#: Keys whose number must be > 0: a scale or a density divides.
POSITIVE_KEYS = frozenset({"full_scale", "water_density"})
#: An input's centre and full scale are in its own unit (cc, mm, in, m³, counts): ±1e12
#: holds any actuator's reading (a 32-bit counter's 4.3e9 with room) and 1e-9 is below a
#: 1 cc engine's full scale in m³ (1e-6); beyond them the number is a typo, and 1e308 would
#: overflow the scaling. The water density is the service's own range (protocols.units).
NUMBER_BOUNDS: dict[str, tuple[float, float, str]] = {
    "centre": (-1e12, 1e12, "in the column's unit"),
    "full_scale": (1e-9, 1e12, "in the column's unit"),
    "water_density": (*WATER_DENSITY_RANGE, "kg/m³"),
}
#: Pa: the pressure a ``[pressure] surface`` offset may take at most either way, the
#: 10,000 hPa of a pressurised tank that bounds the service's surface pressure.
SURFACE_LIMIT_PA = SURFACE_PRESSURE_RANGE[1] * 100.0
FILE_KINDS = ("csv", "parquet")


@dataclass(frozen=True)
class Mapping:
    origin: str
    data: dict[str, Any]
    lines: dict[str, int]  # "table" or "table.key" → line in the mapping file

    def where(self, table: str, key: str | None = None) -> str:
        line = self.lines.get(f"{table}.{key}") or self.lines.get(table)
        return f"{self.origin}:{line}" if line else self.origin

    def get(self, table: str, key: str, default: Any = None) -> Any:
        return self.data.get(table, {}).get(key, default)

    def error(self, table: str, key: str, problem: str) -> FieldError:
        """An error naming the mapping file, its line, the table and the key."""
        return FieldError(f"{self.where(table, key)}: [{table}] {key} {problem}")


def _lines(text: str) -> dict[str, int]:
    lines: dict[str, int] = {}
    table = ""
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if line.startswith("[") and line.endswith("]"):
            table = line.strip("[]").strip()
            lines.setdefault(table, number)
        elif "=" in line and table:
            lines.setdefault(f"{table}.{line.split('=', 1)[0].strip()}", number)
    return lines


def load_mapping(path: str | Path) -> Mapping:
    """The mapping file, checked: every value is of its key's type and makes sense (a
    finite number within its bounds, a scale > 0, one delimiter character, …); else an
    error naming the file, line, table and key."""
    origin = str(path)
    problem = not_a_file(path, "mapping file")
    if problem:
        raise FieldError(problem)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise FieldError(f"{origin}: cannot be read ({error})") from error
    except UnicodeDecodeError as error:
        raise FieldError(f"{origin}: not UTF-8 text, as TOML must be ({error})") from error
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise FieldError(f"{origin}: not TOML: {error}") from error
    mapping = Mapping(origin, data, _lines(text))
    _check_keys(mapping)
    _check_tables(mapping)
    _check_units(mapping)
    _check_surface(mapping)
    _check_file(mapping)
    return mapping


def _check_keys(mapping: Mapping) -> None:
    """Known tables and keys only, each value of its key's type, every number finite."""
    for table, value in mapping.data.items():
        if table not in TABLES:
            raise FieldError(
                f"{mapping.where(table)}: unknown table [{table}] (known: "
                f"{', '.join(sorted(TABLES))})"
            )
        if not isinstance(value, dict):
            raise FieldError(f"{mapping.where(table)}: {table} must be a table")
        for key, given in value.items():
            if key not in TABLES[table]:
                raise FieldError(
                    f"{mapping.where(table, key)}: unknown key {key!r} in [{table}] (known: "
                    f"{', '.join(sorted(TABLES[table]))})"
                )
            _check_value(mapping, table, key, given)


def _check_value(mapping: Mapping, table: str, key: str, value: Any) -> None:
    if key in TEXT_KEYS and not isinstance(value, str):
        raise mapping.error(table, key, f"must be a string, got {value!r}")
    if key in NUMBER_KEYS:
        if not is_finite_number(value):
            raise mapping.error(table, key, f"must be a finite number, got {value!r}")
        if key in POSITIVE_KEYS and not value > 0:
            raise mapping.error(table, key, f"must be > 0, got {value!r}")
        if key in NUMBER_BOUNDS:
            low, high, unit = NUMBER_BOUNDS[key]
            problem = range_problem(value, (low, high), unit)
            if problem:
                raise mapping.error(table, key, problem)
    if key == "values" and not (
        isinstance(value, list)
        and all(isinstance(v, (str, int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise mapping.error(table, key, f"must be a list of strings or numbers, got {value!r}")


def _check_tables(mapping: Mapping) -> None:
    data = mapping.data
    for table in REQUIRED_TABLES:
        if table not in data:
            raise FieldError(f"{mapping.origin}: the mapping needs a [{table}] table")
    if ("depth" in data) == ("pressure" in data):
        raise FieldError(f"{mapping.origin}: give exactly one of [depth] or [pressure]")
    for table in ("buoyancy", "pitch_input"):
        if "column" not in data[table] or "full_scale" not in data[table]:
            raise FieldError(f"{mapping.where(table)}: [{table}] needs column and full_scale")


def _check_units(mapping: Mapping) -> None:
    data = mapping.data
    if "unit" in data["time"] and "format" in data["time"]:
        raise mapping.error(
            "time", "format", "and unit both given: a number in a unit, or a text in a format"
        )
    for table, units in (
        ("time", TIME_UNITS),
        ("depth", DEPTH_UNITS),
        ("pressure", PRESSURE_UNITS),
        ("pitch", PITCH_UNITS),
    ):
        if table not in data:
            continue
        if "column" not in data[table]:
            raise FieldError(f"{mapping.where(table)}: [{table}] needs a column")
        unit = data[table].get("unit")
        if table == "time" and unit is None:
            continue  # a datetime text column (ISO 8601, or the strptime format given)
        if unit not in units:
            raise FieldError(
                f"{mapping.where(table, 'unit')}: unit {unit!r} of [{table}] is not one of "
                f"{', '.join(units)}"
            )


def _check_surface(mapping: Mapping) -> None:
    """A ``[pressure] surface`` offset within ±``SURFACE_LIMIT_PA``, in the column's unit."""
    surface = mapping.get("pressure", "surface")
    if surface is None:
        return
    unit = mapping.data["pressure"]["unit"]
    limit = SURFACE_LIMIT_PA / PRESSURE_UNITS[unit]
    if not abs(surface) <= limit:
        raise mapping.error(
            "pressure",
            "surface",
            f"must be within ±{limit:g} {unit} ({SURFACE_PRESSURE_RANGE[1]:,.0f} hPa, a "
            f"pressurised tank's), got {surface!r}",
        )


def _check_file(mapping: Mapping) -> None:
    kind = mapping.get("file", "kind")
    if kind is not None and kind not in FILE_KINDS:
        raise mapping.error("file", "kind", f"must be one of {', '.join(FILE_KINDS)}, got {kind!r}")
    delimiter = mapping.get("file", "delimiter")
    if delimiter is not None and (len(delimiter) != 1 or delimiter in '"\r\n'):
        raise mapping.error(
            "file", "delimiter", f"must be one character, not a quote or newline: {delimiter!r}"
        )


def _rows(
    path: Path, mapping: Mapping
) -> tuple[int, list[str], list[tuple[int, list[str] | None]]]:
    """(the header's line, the header, (line, row) of every later line) of a file; the row
    is None where the CSV parser refuses the line."""
    kind = mapping.get("file", "kind", "parquet" if path.suffix == ".parquet" else "csv")
    if kind == "parquet":
        return _parquet_rows(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as error:
        raise UnreadableFile(path, f"{path}: cannot be read ({error})") from error
    comment = mapping.get("file", "comment", "#")
    delimiter = mapping.get("file", "delimiter", ",")
    numbered = [
        (number, line)
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not (comment and line.startswith(comment))
    ]
    if not numbered:
        raise UnreadableFile(path, f"{path}:1: empty file (no header)")
    # One line, one row (a quoted field spanning lines is not supported): line numbers stay
    # the file's own, for the errors.
    parsed = [(n, _csv_row(line, delimiter)) for n, line in numbered]
    (header_line, header), body = parsed[0], parsed[1:]
    if header is None:
        raise UnreadableFile(path, f"{path}:{header_line}: a header the CSV parser refuses")
    return header_line, [h.strip() for h in header], body


def _csv_row(line: str, delimiter: str) -> list[str] | None:
    """One line's fields; None for a line the parser refuses (a field longer than
    ``csv.field_size_limit()``, 128 kB)."""
    try:
        return next(csv.reader([line], delimiter=delimiter))
    except csv.Error:
        return None


def _parquet_rows(path: Path) -> tuple[int, list[str], list[tuple[int, list[str] | None]]]:
    """A Parquet file as the CSV path's rows: row k (from 1 after the header) is "line"
    k + 1, each cell as text (a null cell empty), so both kinds are parsed and counted by
    the same code."""
    try:
        import pyarrow.parquet as pq  # the [field] extra (pyproject.toml)
    except ImportError as error:
        raise FieldError(
            f"{path}: reading Parquet needs pyarrow: pip install 'glider-hil[field]' "
            "(or pip install pyarrow)"
        ) from error
    try:
        table = pq.read_table(path)
    except Exception as error:  # ArrowInvalid, OSError, …: whatever a damaged file raises
        raise UnreadableFile(path, f"{path}: not a readable Parquet file ({error})") from error
    header = [str(name) for name in table.column_names]
    columns = [table.column(name).to_pylist() for name in table.column_names]
    records = zip(*columns, strict=True) if columns else iter(())
    body: list[tuple[int, list[str] | None]] = [
        (k + 2, ["" if v is None else str(v) for v in r]) for k, r in enumerate(records)
    ]
    return 1, header, body


def read_mapped(paths: list[Path], mapping_path: str | Path) -> FieldData:
    mapping = load_mapping(mapping_path)
    issues = Issues()
    columns = Columns()
    read = read_each(
        list(enumerate(paths)),
        lambda item: _read_file(item[1], item[0], mapping, columns, issues),
        issues,
    )
    read_files = [str(path) for (_, path), _ in read]
    check_something_read(read_files, issues, len(paths))
    if not columns.t and issues.unparsable_rows:
        first = next(n for n in issues.notes if n.endswith(UNPARSABLE_NOTE))
        raise FieldError(
            f"{', '.join(read_files)}: every row unparsable ({issues.unparsable_rows}; "
            f"the first: {first})"
        )
    data = mapping.data
    depth_table = "depth" if "depth" in data else "pressure"
    conversions = [
        Conversion("t", data["time"]["column"], str(data["time"].get("unit", "datetime")), "s"),
        Conversion(
            "depth",
            data[depth_table]["column"],
            str(data[depth_table]["unit"]),
            "m",
            _depth_factor(mapping),
        ),
        Conversion(
            "pitch",
            data["pitch"]["column"],
            data["pitch"]["unit"],
            "rad",
            PITCH_UNITS[data["pitch"]["unit"]],
        ),
        *(
            Conversion(
                q, data[q]["column"], str(data[q].get("unit", "")), str(data[q].get("unit", ""))
            )
            for q in ("buoyancy", "pitch_input")
        ),
    ]
    scaling = {
        q: InputScaling(float(data[q].get("centre", 0.0)), float(data[q]["full_scale"]))
        for q in ("buoyancy", "pitch_input")
    }
    return FieldData.from_columns(
        "csv", read_files, columns, conversions, scaling, issues, vehicle=""
    )


def _depth_factor(mapping: Mapping) -> float:
    if "depth" in mapping.data:
        return DEPTH_UNITS[mapping.data["depth"]["unit"]]
    density = float(mapping.get("pressure", "water_density", 1025.0))
    return PRESSURE_UNITS[mapping.data["pressure"]["unit"]] / (density * STANDARD_GRAVITY)


def _read_file(path: Path, number: int, mapping: Mapping, columns: Columns, issues: Issues) -> None:
    header_line, header, rows = _rows(path, mapping)
    index = {name: i for i, name in enumerate(header)}
    data = mapping.data
    depth_table = "depth" if "depth" in data else "pressure"
    needed = {"time": data["time"]["column"], depth_table: data[depth_table]["column"]}
    needed["pitch"] = data["pitch"]["column"]
    for table, column in needed.items():
        if column not in index:
            raise FieldError(
                f"{path}:{header_line}: no column {column!r} (the mapping's [{table}] column, "
                f"{mapping.where(table, 'column')}); the header has {', '.join(header)}"
            )
    optional = {q: data[q]["column"] for q in ("buoyancy", "pitch_input")}
    absent = [c for c in optional.values() if c not in index]
    dive_column = mapping.get("dive", "column")
    surface_column = mapping.get("surface", "column")
    used = [*needed.values(), *optional.values(), dive_column, surface_column]
    twice = sorted({c for c in used if c is not None and header.count(c) > 1})
    if twice:
        raise FieldError(
            f"{path}:{header_line}: the header names column(s) {', '.join(map(repr, twice))} "
            "more than once: which one the mapping means is unknown"
        )
    surface_values = {str(v) for v in mapping.get("surface", "values", [])}
    for column in (dive_column, surface_column):
        if column is not None and column not in index:
            absent.append(column)
    if absent:
        issues.missing_columns[str(path)] = absent
    time_unit = data["time"].get("unit")
    time_format = data["time"].get("format")
    depth_factor = _depth_factor(mapping)
    surface_offset = float(mapping.get("pressure", "surface", 0.0))
    first_row = len(columns.t)
    for line_no, row in rows:
        if row is not None and not any(cell.strip() for cell in row):
            continue
        try:
            if row is None:
                raise ValueError("a line the CSV parser refuses")
            if len(row) != len(header):  # a row cut short (or run together): not a sample
                raise ValueError("not as many fields as the header")
            t = _time(row[index[needed["time"]]], time_unit, time_format)
            depth = (_float(row[index[needed[depth_table]]]) - surface_offset) * depth_factor
            pitch = _float(row[index[needed["pitch"]]]) * PITCH_UNITS[data["pitch"]["unit"]]
            inputs = {
                q: _float(row[index[c]]) if c in index else math.nan for q, c in optional.items()
            }
            dive = whole_dive(_float(row[index[dive_column]])) if dive_column in index else number
        except (ValueError, IndexError, OverflowError):  # int(inf): OverflowError
            issues.unparsable_rows += 1
            if issues.unparsable_rows <= 5:
                issues.notes.append(f"{path}:{line_no}: {UNPARSABLE_NOTE}")
            continue
        surface = surface_column in index and _one_of(row[index[surface_column]], surface_values)
        columns.t.append(t)
        columns.depth.append(depth)
        columns.pitch.append(pitch)
        columns.buoyancy.append(inputs["buoyancy"])
        columns.pitch_input.append(inputs["pitch_input"])
        columns.dive.append(dive)
        columns.in_dive.append(not surface)
    _check_times(path, columns.t[first_row:], mapping)


def _check_times(path: Path, times: list[float], mapping: Mapping) -> None:
    """A file none of whose times a log can hold is an error: its time unit (or format) is
    most likely not the one the mapping says, and every row would be dropped."""
    finite = np.asarray([t for t in times if math.isfinite(t)], dtype=float)
    if finite.size and not np.any(is_log_time(finite)):
        unit = mapping.get("time", "unit")
        said = f"unit {unit!r}" if unit is not None else "format"
        raise no_log_time(
            str(path),
            float(finite[0]),
            f"is the time {said} ({mapping.where('time', 'unit' if unit else 'format')}) "
            "the file's?",
        )


def _one_of(cell: str, values: set[str]) -> bool:
    """The cell is one of the mapping's values, as text or as a number (a Parquet float
    column gives "115.0" for the mapping's 115)."""
    text = cell.strip()
    if text in values:
        return True
    try:
        number = float(text)
    except ValueError:
        return False
    return any(_number(v) == number for v in values)


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def _float(text: str) -> float:
    text = text.strip()
    return math.nan if text.lower() in ("", "nan", "na", "null") else float(text)


def _time(text: str, unit: str | None, fmt: str | None) -> float:
    if fmt is not None:
        return datetime.strptime(text.strip(), fmt).replace(tzinfo=_utc()).timestamp()
    if unit is None:
        value = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
        if value.tzinfo is None:
            value = value.replace(tzinfo=_utc())
        return value.timestamp()
    return _float(text) * TIME_UNITS[unit]


def _utc():
    from datetime import timezone

    return timezone.utc
