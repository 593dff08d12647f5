"""Slocum binary logs (``.dbd .sbd .tbd .ebd .mbd .nbd``, any case) through ``dbdreader``.

A Slocum file names its sensor list by a cache id; unless the file carries the list itself
(then dbdreader writes it to the cache), the list must be in ``--cache-dir`` as
``<id>.cac`` (copied from the glider's or the dockserver's ``state/cache``). Which sensor
becomes what (docs/field-data.md):

* time: the time base of ``m_depth`` (s since 1970); depth: ``m_depth`` m;
* pitch: ``m_pitch`` rad (+ nose up), interpolated by ``dbdreader.get_sync`` onto the
  depth's time base, as are the inputs;
* buoyancy input: ``m_de_oil_vol`` cc (deep glider), else ``m_ballast_pumped`` cc;
* pitch input: ``m_battpos`` in (the pitch battery position).

Each file is one dive number (the files in name order: a Slocum name sorts in time).
"""

from __future__ import annotations

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

SUFFIXES = frozenset({".dbd", ".sbd", ".tbd", ".ebd", ".mbd", ".nbd"})
BUOYANCY = ("m_de_oil_vol", "m_ballast_pumped")
CONVERSIONS = [
    Conversion("t", "m_depth (time base)", "s since 1970-01-01", "s"),
    Conversion("depth", "m_depth", "m", "m"),
    Conversion("pitch", "m_pitch", "rad", "rad"),
    Conversion("buoyancy", "m_de_oil_vol | m_ballast_pumped", "cc", "cc"),
    Conversion("pitch_input", "m_battpos", "in", "in"),
]
#: Oil/ballast ±500 cc and the pitch battery ±1.5 in are model units ±full scale.
SCALING = {"buoyancy": InputScaling(0.0, 500.0), "pitch_input": InputScaling(0.0, 1.5)}


def is_slocum(path: Path) -> bool:
    return path.suffix.lower() in SUFFIXES


def read_slocum(paths: list[Path], cache_dir: str | Path | None) -> FieldData:
    try:
        import dbdreader
    except ImportError as error:  # a declared dependency; a broken install says so
        raise FieldError(f"reading Slocum files needs the dbdreader package: {error}") from error
    if cache_dir is None:
        raise FieldError(
            f"{paths[0]}: Slocum files need --cache-dir (the directory of the glider's "
            "sensor-list .cac files)"
        )
    cache = Path(cache_dir)
    if not cache.is_dir():
        raise FieldError(f"--cache-dir {cache}: not a directory")
    issues = Issues()
    columns = Columns()
    ordered = sorted(paths, key=lambda p: p.name.lower())
    for number, path in enumerate(ordered):
        try:
            dbd = dbdreader.DBD(str(path), cacheDir=str(cache))
        except dbdreader.DbdError as error:
            raise FieldError(_explain(path, cache, error, dbdreader)) from error
        try:
            _read(dbd, path, number, columns, issues)
        finally:
            dbd.close()
    return FieldData.from_columns(
        "slocum",
        [str(p) for p in ordered],
        columns,
        CONVERSIONS,
        SCALING,
        issues,
        vehicle=ordered[0].name.split("-")[0],
    )


def _explain(path: Path, cache: Path, error: Exception, dbdreader: object) -> str:
    value = getattr(error, "value", None)
    if value == getattr(dbdreader, "DBD_ERROR_CACHE_NOT_FOUND", -1):
        data = getattr(error, "data", None)
        files = getattr(data, "missing_cache_files", None) or {}
        names = ", ".join(f"{cid}.cac" for cid in files) or "its sensor-list (.cac) file"
        return (
            f"{path}: the sensor list {names} is not in --cache-dir {cache}; copy it from "
            "the glider's state/cache (or the dockserver's) into that directory"
        )
    return f"{path}: not a readable Slocum file ({str(error).strip()})"


def _read(dbd: object, path: Path, number: int, columns: Columns, issues: Issues) -> None:
    names = set(dbd.parameterNames)  # type: ignore[attr-defined]
    buoyancy = next((b for b in BUOYANCY if b in names), None)
    missing = [n for n in ("m_depth", "m_pitch", "m_battpos") if n not in names]
    if buoyancy is None:
        missing.append(" | ".join(BUOYANCY))
    if missing:
        issues.missing_columns[str(path)] = missing
    if "m_depth" not in names or "m_pitch" not in names:
        issues.notes.append(f"{path}: no m_depth/m_pitch: nothing to identify from")
        return
    wanted = ["m_depth", "m_pitch", *(n for n in (buoyancy, "m_battpos") if n is not None)]
    try:
        values = dbd.get_sync(*wanted)  # type: ignore[attr-defined]
    except Exception as error:  # dbdreader raises its own and numpy's errors on bad data
        raise FieldError(f"{path}: sensors unreadable ({error})") from error
    t, depth, pitch, *rest = (np.asarray(v, dtype=float) for v in values)
    given = dict(zip(wanted[2:], rest, strict=True))
    nan = np.full(t.size, np.nan)
    columns.extend(
        t=t.tolist(),
        depth=depth.tolist(),
        pitch=pitch.tolist(),
        buoyancy=given.get(buoyancy or "", nan).tolist(),
        pitch_input=given.get("m_battpos", nan).tolist(),
        dive=[number] * t.size,
        in_dive=(depth > 0.5).tolist(),
    )
    issues.notes.append(
        f"{path}: m_pitch and the inputs interpolated onto m_depth's {t.size} times "
        "(dbdreader.get_sync)"
    )
