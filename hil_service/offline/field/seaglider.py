"""Seaglider per-dive netCDF3 files (``pGGGDDDD.nc``, as the basestation writes them).

Read with ``scipy.io.netcdf_file`` (netCDF3 classic and 64-bit offset). Which variable
becomes what (docs/field-data.md):

* time: ``time`` s since 1970 (``eng_elaps_t`` + the ``start_time`` attribute when absent);
* depth: ``eng_depth`` cm → m (÷ 100);
* pitch: ``eng_pitchAng`` ° (+ nose up) → rad;
* buoyancy input: ``eng_vbdCC`` cc (the VBD's volume: + more buoyant);
* pitch input: ``eng_pitchCtl`` cm (the pitch mass position, + aft: nose up).

Each file is one dive, numbered by its ``dive_number`` attribute (else its name); the files
are taken in dive order and the surface intervals between dives are not sampled: gaps.
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
    glider = ""
    for number, path in dives:
        read = _read_dive(path, number, issues)
        columns.extend(**read)
        glider = glider or _glider(path)
    return FieldData.from_columns(
        "seaglider",
        [str(p) for _, p in dives],
        columns,
        CONVERSIONS,
        SCALING,
        issues,
        vehicle=glider,
    )


def _open(path: Path):
    from scipy.io import netcdf_file

    try:
        return netcdf_file(path, "r", mmap=False)
    except (OSError, ValueError, TypeError, IndexError, EOFError) as error:
        size = path.stat().st_size if path.exists() else 0
        raise FieldError(
            f"{path}: not a readable netCDF3 file ({size} bytes; {type(error).__name__}: "
            f"{error}); a file cut short in transfer reads like this"
        ) from error


def _dive_number(path: Path) -> int:
    match = _DIVE_NAME.search(path.name)
    try:
        with _open(path) as nc:
            value = nc._attributes.get("dive_number")
            if value is not None:
                return int(np.asarray(value).ravel()[0])
    except FieldError:
        pass  # named below; reading it reports the damage
    if match:
        return int(match.group(1))
    return 0


def _glider(path: Path) -> str:
    with _open(path) as nc:
        value = nc._attributes.get("glider")
    return "" if value is None else f"SG{int(np.asarray(value).ravel()[0]):03d}"


def _read_dive(path: Path, number: int, issues: Issues) -> dict[str, list]:
    with _open(path) as nc:
        variables = nc.variables
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
            base = float(np.asarray(start).ravel()[0]) if start is not None else 0.0
            t = column(ELAPSED) + base
        else:
            size = next((variables[v].data.size for v in (DEPTH, PITCH) if v in variables), 0)
            t = np.full(size, np.nan)
        n = t.size
        values = {
            "depth": column(DEPTH, n) * 0.01,
            "pitch": np.radians(column(PITCH, n)),
            "buoyancy": column(VBD, n),
            "pitch_input": column(PITCH_CTL, n),
        }
    sizes = {n, *(v.size for v in values.values())}
    if len(sizes) != 1:
        raise FieldError(f"{path}: the engineering variables differ in length {sorted(sizes)}")
    return {
        "t": t.tolist(),
        **{k: v.tolist() for k, v in values.items()},
        "dive": [number] * n,
        "in_dive": [True] * n,
    }
