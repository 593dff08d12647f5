"""Seaglider per-dive netCDF3 files (``pGGGDDDD.nc``, as the basestation writes them).

Read with ``scipy.io.netcdf_file`` (netCDF3 classic and 64-bit offset). Which variable
becomes what (docs/field-data.md):

* time: ``time`` s since 1970 (``eng_elaps_t`` + the ``start_time`` attribute when absent;
  neither: an error, no absolute time);
* depth: ``eng_depth`` cm → m (÷ 100), or m when its ``units`` attribute says so;
* pitch: ``eng_pitchAng`` ° (+ nose up) → rad, or rad when its ``units`` attribute says so
  (any other ``units`` of either is an error naming the file);
* buoyancy input: ``eng_vbdCC`` cc (the VBD's volume: + more buoyant);
* pitch input: ``eng_pitchCtl`` cm (the pitch mass position, + aft: nose up).

Each file is one dive, numbered by its ``dive_number`` attribute (else its name); the files
are taken in dive order and the surface intervals between dives are not sampled: gaps.
Files whose ``glider`` attributes differ are refused (one glider per import). A file that is
not readable netCDF3 (a dive cut short in transfer) is skipped and named among several files
(``table.skip_unreadable``), and an error alone.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

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
    read_each,
    whole_dive,
)

SUFFIXES = (".nc",)
TIME, ELAPSED, DEPTH, PITCH, VBD, PITCH_CTL = (
    "time",
    "eng_elaps_t",
    "eng_depth",
    "eng_pitchAng",
    "eng_vbdCC",
    "eng_pitchCtl",
)
#: The ``units`` attribute of depth and pitch (lower case) → (unit, factor to m or rad);
#: without the attribute depth is in cm and pitch in degrees, as the basestation writes.
UNITS = {
    DEPTH: {
        **dict.fromkeys(("cm", "centimeter", "centimeters", "centimetre"), ("cm", 0.01)),
        **dict.fromkeys(("m", "meter", "meters", "metre", "metres"), ("m", 1.0)),
    },
    PITCH: {
        **dict.fromkeys(("degrees", "degree", "deg"), ("deg", math.pi / 180.0)),
        **dict.fromkeys(("radians", "radian", "rad"), ("rad", 1.0)),
    },
}
DEFAULT_UNITS = {DEPTH: UNITS[DEPTH]["cm"], PITCH: UNITS[PITCH]["deg"]}
CONVERSIONS = [
    Conversion("t", TIME, "s since 1970-01-01", "s", 1.0),
    Conversion("depth", DEPTH, "cm", "m", 0.01),
    Conversion("pitch", PITCH, "deg", "rad", math.pi / 180.0),
    Conversion("buoyancy", VBD, "cc", "cc", 1.0),
    Conversion("pitch_input", PITCH_CTL, "cm", "cm", 1.0),
]
#: VBD ±600 cc and pitch mass ±10 cm are model units ±full scale (docs/field-data.md).
SCALING = {"buoyancy": InputScaling(0.0, 600.0), "pitch_input": InputScaling(0.0, 10.0)}
_DIVE_NAME = re.compile(r"p\d{3}(\d{4})\.nc$")


def is_seaglider(path: Path) -> bool:
    return path.suffix == ".nc"


def read_seaglider(paths: list[Path]) -> FieldData:
    issues = Issues()
    dives = sorted((_dive_number(p), p) for p in paths)
    columns = Columns()
    gliders: dict[str, Path] = {}
    conversions: list[Conversion] = []
    read_files: list[str] = []

    def take(dive: tuple[int, Path]) -> tuple[dict[str, tuple[str, float]], str]:
        read, units, glider = _read_dive(dive[1], dive[0], issues)
        columns.extend(**read)
        return units, glider

    for (_, path), (units, glider) in read_each(dives, take, issues):
        read_files.append(str(path))
        if glider:
            gliders.setdefault(glider, path)
        if len(gliders) > 1:
            (first, one), (second, other) = list(gliders.items())[:2]
            raise FieldError(
                f"files of two gliders: {one} is {first}, {other} is {second}; import one "
                "glider at a time"
            )
        if not conversions:
            conversions = _conversions(units)
        elif _conversions(units) != conversions:
            issues.notes.append(
                f"{path}: {DEPTH} in {units[DEPTH][0]}, {PITCH} in {units[PITCH][0]} "
                "(its units attributes), unlike the first file's"
            )
    check_something_read(read_files, issues, len(dives))
    return FieldData.from_columns(
        "seaglider",
        read_files,
        columns,
        conversions or CONVERSIONS,
        SCALING,
        issues,
        vehicle=next(iter(gliders), ""),
    )


def _conversions(units: dict[str, tuple[str, float]]) -> list[Conversion]:
    """``CONVERSIONS`` with the depth and pitch units a file's attributes gave."""
    depth, pitch = units[DEPTH], units[PITCH]
    return [
        CONVERSIONS[0],
        Conversion("depth", DEPTH, depth[0], "m", depth[1]),
        Conversion("pitch", PITCH, pitch[0], "rad", pitch[1]),
        *CONVERSIONS[3:],
    ]


def _open(path: Path):
    from scipy.io import netcdf_file

    try:
        return netcdf_file(path, "r", mmap=False)
    except (OSError, ValueError, TypeError, IndexError, EOFError) as error:
        size = path.stat().st_size if path.exists() else 0
        raise UnreadableFile(
            path,
            f"{path}: not a readable netCDF3 file ({size} bytes; {type(error).__name__}: "
            f"{error}); a file cut short in transfer reads like this",
        ) from error


def _dive_number(path: Path) -> int:
    match = _DIVE_NAME.search(path.name)
    try:
        with _open(path) as nc:
            value = nc._attributes.get("dive_number")
    except UnreadableFile:
        value = None  # named when the dive is read; reading it reports the damage
    if value is not None:
        number = _attribute(path, "dive_number", value)
        try:
            return whole_dive(number)
        except ValueError as error:
            raise FieldError(f"{path}: dive_number attribute: {error}") from error
    if match:
        return int(match.group(1))
    return 0


def _glider(path: Path, attributes: dict) -> str:
    """The glider's name from a file's ``glider`` attribute ("" without one)."""
    value = attributes.get("glider")
    if value is None:
        return ""
    number = _attribute(path, "glider", value)
    if not (math.isfinite(number) and number == int(number) and 0 <= number < 1e6):
        raise FieldError(f"{path}: glider attribute {number!r} is not a glider number")
    return f"SG{int(number):03d}"


def _attribute(path: Path, name: str, value: object) -> float:
    """A numeric global attribute's (first) value; a text or empty one is an error naming
    the file."""
    try:
        first = np.asarray(value).ravel()[0]
        if isinstance(first, bytes):
            first = first.decode("ascii")
        return float(first)
    except (ValueError, TypeError, IndexError, UnicodeDecodeError) as error:
        raise FieldError(f"{path}: {name} attribute {value!r} is not a number") from error


def _units(path: Path, variables: dict, name: str) -> tuple[str, float]:
    """(unit, factor to SI) of depth or pitch, by the variable's ``units`` attribute."""
    if name not in variables:
        return DEFAULT_UNITS[name]
    given = getattr(variables[name], "units", None)
    if given is None:
        return DEFAULT_UNITS[name]
    text = given.decode("latin-1") if isinstance(given, bytes) else str(given)
    unit = UNITS[name].get(text.strip().lower())
    if unit is None:
        known = sorted({u for u, _ in UNITS[name].values()})
        raise FieldError(
            f"{path}: {name} has units {text!r}; the import reads {' or '.join(known)}"
        )
    return unit


def _read_dive(
    path: Path, number: int, issues: Issues
) -> tuple[dict[str, list], dict[str, tuple[str, float]], str]:
    """The dive's rows, the (unit, factor) its depth and pitch were read in, and the
    glider's name."""
    with _open(path) as nc:
        glider = _glider(path, nc._attributes)
        variables = nc.variables
        units = {name: _units(path, variables, name) for name in (DEPTH, PITCH)}
        missing = [v for v in (DEPTH, PITCH, VBD, PITCH_CTL) if v not in variables]
        if TIME not in variables and ELAPSED not in variables:
            missing.insert(0, f"{TIME} (or {ELAPSED})")
        if missing:
            issues.missing_columns[str(path)] = missing

        def column(name: str, size: int | None = None) -> np.ndarray:
            if name not in variables:
                return np.full(size or 0, np.nan)
            try:
                return np.array(variables[name].data, dtype=float).ravel()
            except (ValueError, TypeError, OSError) as error:
                raise FieldError(f"{path}: variable {name} unreadable: {error}") from error

        if TIME in variables:
            t = column(TIME)
        elif ELAPSED in variables:
            start = nc._attributes.get("start_time")
            if start is None:
                raise FieldError(
                    f"{path}: no absolute time: no {TIME} variable and no start_time "
                    f"attribute ({ELAPSED} counts from the dive's start)"
                )
            t = column(ELAPSED) + _attribute(path, "start_time", start)
        else:
            size = next((variables[v].data.size for v in (DEPTH, PITCH) if v in variables), 0)
            t = np.full(size, np.nan)
        n = t.size
        values = {
            "depth": column(DEPTH, n) * units[DEPTH][1],
            "pitch": column(PITCH, n) * units[PITCH][1],
            "buoyancy": column(VBD, n),
            "pitch_input": column(PITCH_CTL, n),
        }
    sizes = {n, *(v.size for v in values.values())}
    if len(sizes) != 1:
        raise FieldError(f"{path}: the engineering variables differ in length {sorted(sizes)}")
    return (
        {
            "t": t.tolist(),
            **{k: v.tolist() for k, v in values.items()},
            "dive": [number] * n,
            "in_dive": [True] * n,
        },
        units,
        glider,
    )
