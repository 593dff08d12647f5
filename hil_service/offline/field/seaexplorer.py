"""SeaExplorer navigation files (``*.gli.sub.N``, ``*.gli.raw.N``; gzipped or not).

``;``-separated text, one header line, ``Timestamp`` as ``dd/mm/YYYY HH:MM:SS`` (UTC).
Which column becomes what (docs/field-data.md):

* depth: ``Depth`` m; pitch: ``Pitch`` ° (+ nose up) → rad;
* buoyancy input: ``BallastPos`` cc (the measured ballast volume; ``BallastCmd`` when the
  position is absent), pitch input: ``LinPos`` mm (the moving mass; ``LinCmd`` else);
* ``NavState``: 116 (at the surface) and 115 (surfacing: GPS, transmitting) and 105 (not
  navigating) are surface rows, kept in the log and not identified; a NaN ``NavState`` is
  a row without one (in-dive), a column all NaN a missing column.

Files are taken by their number N; each file is one dive number. Files of two gliders (the
name before the first dot) are refused. A file that cannot be read, or whose header lacks a
column every navigation file has (cut short in transfer), is skipped and named among
several files (``table.skip_unreadable``), and an error alone.
"""

from __future__ import annotations

import calendar
import gzip
import math
import re
import time
from pathlib import Path

from hil_service.offline.field.table import (
    DIVE_LIMIT,
    Columns,
    Conversion,
    FieldData,
    FieldError,
    InputScaling,
    Issues,
    UnreadableFile,
    check_something_read,
    read_each,
)

SURFACE_STATES = frozenset({105, 115, 116})
CONVERSIONS = [
    Conversion("t", "Timestamp", "dd/mm/YYYY HH:MM:SS UTC", "s since 1970-01-01"),
    Conversion("depth", "Depth", "m", "m"),
    Conversion("pitch", "Pitch", "deg", "rad", math.pi / 180.0),
    Conversion("buoyancy", "BallastPos", "cc", "cc"),
    Conversion("pitch_input", "LinPos", "mm", "mm"),
]
#: Ballast ±500 cc and moving mass 10–110 mm are model units ±full scale.
SCALING = {"buoyancy": InputScaling(0.0, 500.0), "pitch_input": InputScaling(60.0, 50.0)}
_NAME = re.compile(r"\.gli\.(sub|raw)\.(\d+)(\.gz)?$")
REQUIRED = ("Timestamp", "Depth", "Pitch")
INPUTS = {"buoyancy": ("BallastPos", "BallastCmd"), "pitch_input": ("LinPos", "LinCmd")}


def is_seaexplorer(path: Path) -> bool:
    return _NAME.search(path.name) is not None


def _number(path: Path) -> int:
    match = _NAME.search(path.name)
    if not match:
        return 0
    number = int(match.group(2))
    if number >= DIVE_LIMIT:
        raise FieldError(f"{path}: file number {number} beyond int64, as a dive number is stored")
    return number


def read_seaexplorer(paths: list[Path]) -> FieldData:
    issues = Issues()
    ordered = sorted(paths, key=lambda p: (_number(p), p.name))
    columns = Columns()
    vehicles: dict[str, Path] = {}
    for path in ordered:
        vehicles.setdefault(path.name.split(".")[0].upper(), path)
    if len(vehicles) > 1:
        (first, one), (second, other) = list(vehicles.items())[:2]
        raise FieldError(
            f"files of two gliders: {one} is {first}, {other} is {second}; import one glider "
            "at a time"
        )
    vehicle = next(iter(vehicles), "")
    read = read_each(ordered, lambda path: _read_file(path, columns, issues), issues)
    read_files = [str(path) for path, _ in read]
    check_something_read(read_files, issues, len(ordered))
    return FieldData.from_columns(
        "seaexplorer", read_files, columns, CONVERSIONS, SCALING, issues, vehicle
    )


def _text(path: Path) -> str:
    try:
        raw = path.read_bytes()
        if raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        return raw.decode("latin-1")
    except (OSError, EOFError, gzip.BadGzipFile) as error:
        message = f"{path}: cannot be read ({type(error).__name__}: {error})"
        raise UnreadableFile(path, message) from error


def _timestamp(text: str) -> float:
    return float(calendar.timegm(time.strptime(text.strip(), "%d/%m/%Y %H:%M:%S")))


def _read_file(path: Path, columns: Columns, issues: Issues) -> None:
    lines = _text(path).splitlines()
    if not lines:
        issues.notes.append(f"{path}: empty file")
        return
    header = [h.strip() for h in lines[0].split(";")]
    position = {name: i for i, name in enumerate(header) if name}
    absent = [name for name in REQUIRED if name not in position]
    if absent:
        raise UnreadableFile(
            path,
            f"{path}:1: header lacks {', '.join(absent)} (a SeaExplorer gli header names "
            f"{', '.join(REQUIRED)})",
        )
    chosen: dict[str, int | None] = {}
    missing = []
    for quantity, names in INPUTS.items():
        name = next((n for n in names if n in position), None)
        chosen[quantity] = None if name is None else position[name]
        if name is None:
            missing.append(names[0])
    if "NavState" not in position:
        missing.append("NavState")
    if missing:
        issues.missing_columns[str(path)] = missing
    number = _number(path)
    nav = position.get("NavState")
    first_row = len(columns.t)
    states = 0  # rows with a NavState value
    for line_no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split(";")
        try:
            if len(fields) != len(header):  # a row cut short (or run together): not a sample
                raise ValueError("not as many fields as the header")
            t = _timestamp(fields[position["Timestamp"]])
            depth = _float(fields[position["Depth"]])
            pitch = math.radians(_float(fields[position["Pitch"]]))
            inputs = {q: math.nan if i is None else _float(fields[i]) for q, i in chosen.items()}
            value = math.nan if nav is None else _float(fields[nav])
            state = None if math.isnan(value) else int(value)
        except (ValueError, IndexError, OverflowError):  # int(inf): OverflowError
            issues.unparsable_rows += 1
            if issues.unparsable_rows <= 5:
                issues.notes.append(f"{path}:{line_no}: unparsable row dropped")
            continue
        states += state is not None
        surface = state in SURFACE_STATES
        columns.t.append(t)
        columns.depth.append(depth)
        columns.pitch.append(pitch)
        columns.buoyancy.append(inputs["buoyancy"])
        columns.pitch_input.append(inputs["pitch_input"])
        columns.dive.append(number)
        columns.in_dive.append(not surface)
    if nav is not None and states == 0 and len(columns.t) > first_row:
        issues.missing_columns.setdefault(str(path), []).append("NavState (all NaN)")


def _float(text: str) -> float:
    text = text.strip()
    if text in ("", "NaN", "nan"):
        return math.nan
    return float(text)
