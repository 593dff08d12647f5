"""Slocum binary logs (``.dbd .sbd .tbd .ebd .mbd .nbd``, any case) through ``dbdreader``.

A Slocum file names its sensor list by a cache id; unless the file carries the list itself
(then it is copied into the cache once the file has been read whole), the list must be in
``--cache-dir`` as ``<id>.cac`` (copied from the glider's or the dockserver's
``state/cache``). The ASCII header is checked complete before dbdreader sees the file (it
reads a header cut short forever), and whatever dbdreader raises on a damaged file is an
error naming it: among several files the file is skipped and named
(``table.skip_unreadable``), alone it is the import's error. A file whose data part ends
partway through a record (cut short in transfer) is read up to its last whole record, with
a note naming it: dbdreader would read the cut record from stale bytes. Which sensor
becomes what (docs/field-data.md):

* time: the time base of ``m_depth`` (s since 1970); depth: ``m_depth`` m;
* pitch: ``m_pitch`` rad (+ nose up), interpolated by ``dbdreader.get_sync`` onto the
  depth's time base, as are the inputs;
* buoyancy input: ``m_de_oil_vol`` cc (deep glider), else ``m_ballast_pumped`` cc;
* pitch input: ``m_battpos`` in (the pitch battery position).

Each file is one dive number (the files in name order: a Slocum name sorts in time). The
glider is the name that leads the header's ``full_filename``; files of two are refused.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
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
    read_each,
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
#: Bytes of a file searched for its ASCII header (a real one is 14 short lines, < 1 kB).
HEADER_BYTES = 1 << 16
#: Oil/ballast ±500 cc and the pitch battery ±1.5 in are model units ±full scale.
SCALING = {"buoyancy": InputScaling(0.0, 500.0), "pitch_input": InputScaling(0.0, 1.5)}
#: The data part of a Slocum file opens with 16 known bytes ('s', a byte, 0x1234, 123.456 as
#: a float, 123456789.12345 as a double: the byte order); then come the records, each a tag
#: 'd', the state bytes (2 bits a sensor, 4 a byte: 2 = a new value follows) and the new
#: values in sensor order. The glider ends the file with a tag 'X'; a file sent compressed
#: ends after its last record without one.
KNOWN_BYTES = 16
RECORD_TAG = ord("d")
UPDATED = 2
#: The name the whole records of a cut file are read under, in the scratch directory.
WHOLE_RECORDS = "whole-records.dbd"


@dataclass(frozen=True)
class CutRecord:
    """Where a file's data part ends partway through: record ``number`` (from 1; 0 for the
    known bytes before the first) starts at byte ``at``, the bytes before it are whole
    records; ``missing`` of its ``length`` bytes are not in the file (None: its state bytes
    are cut, so its length is unknown)."""

    number: int
    at: int
    missing: int | None
    length: int | None

    def note(self, path: Path) -> str:
        """The import's note, naming the file."""
        return f"{path}: {self.text()}"

    def text(self) -> str:
        """Where the file ends, and what of it is read."""
        if self.number == 0:
            where = f"within the {KNOWN_BYTES} bytes that open it, before any record"
        elif self.missing is None:
            where = f"in the state bytes of record {self.number} (its length unknown)"
        else:
            where = f"in record {self.number}, {self.missing} of its {self.length} bytes missing"
        whole = self.number - 1
        read = (
            f"the {whole} whole record(s) before it are read, the cut one is left out"
            if whole > 0
            else "no whole record precedes it"
        )
        return (
            f"ends partway through its data, {where}; {read}; whatever followed is not in the "
            "file (cut short in transfer?)"
        )


def find_cut(raw: bytes, start: int, state_bytes: int, sizes: Sequence[int]) -> CutRecord | None:
    """Where the data part of a Slocum file (``raw``, its data from byte ``start``) ends
    partway through a record, walking it record by record as dbdreader reads it; None when
    it ends after a whole record (or at a tag other than 'd': the end tag 'X', or bytes this
    walk does not know)."""
    if len(raw) < start + KNOWN_BYTES:
        return CutRecord(0, start, start + KNOWN_BYTES - len(raw), KNOWN_BYTES)
    lengths = _new_value_bytes(state_bytes, sizes)
    rows = np.arange(state_bytes) * 256
    data = np.frombuffer(raw, dtype=np.uint8)
    at, number = start + KNOWN_BYTES, 0
    while at < len(raw) and raw[at] == RECORD_TAG:
        number += 1
        body = at + 1
        if body + state_bytes > len(raw):
            return CutRecord(number, at, None, None)
        length = 1 + state_bytes + int(lengths[rows + data[body : body + state_bytes]].sum())
        if at + length > len(raw):
            return CutRecord(number, at, at + length - len(raw), length)
        at += length
    return None


def _new_value_bytes(state_bytes: int, sizes: Sequence[int]) -> np.ndarray:
    """Entry 256·i + b: the bytes of new values that state byte i announces when it is b."""
    table = np.zeros((state_bytes, 256), dtype=np.int64)
    values = np.arange(256)
    for sensor, size in enumerate(sizes[: 4 * state_bytes]):
        byte, slot = divmod(sensor, 4)
        table[byte] += np.where((values >> (6 - 2 * slot)) & 3 == UPDATED, size, 0)
    return table.ravel()


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
    headers = dict(read_each(ordered, lambda path: _header(path, dbdreader), issues))
    vehicles: dict[str, Path] = {}
    for path, header in headers.items():
        # The glider's name leads the header's full_filename (an 8.3 name does not hold it).
        full = header.get("full_filename") or path.name
        vehicles.setdefault(full.split("-")[0], path)
    if len(vehicles) > 1:
        (first, one), (second, other) = list(vehicles.items())[:2]
        raise FieldError(
            f"files of two gliders: {one} is {first}, {other} is {second}; import one glider "
            "at a time"
        )
    # A file keeps its place in the order as its dive number, whether or not those before
    # it could be read.
    numbered = [(number, path) for number, path in enumerate(ordered) if path in headers]
    read = read_each(
        numbered,
        lambda dive: _read_file(
            dive[1], dive[0], headers[dive[1]], cache, dbdreader, columns, issues
        ),
        issues,
        files=len(ordered),
    )
    read_files = [str(path) for (_, path), _ in read]
    check_something_read(read_files, issues, len(ordered))
    return FieldData.from_columns(
        "slocum",
        read_files,
        columns,
        CONVERSIONS,
        SCALING,
        issues,
        vehicle=next(iter(vehicles), ""),
    )


def _read_file(
    path: Path,
    number: int,
    header: dict[str, str],
    cache: Path,
    dbdreader: Any,
    columns: Columns,
    issues: Issues,
) -> None:
    """One file's rows into ``columns`` as dive ``number``. UnreadableFile, before any row is
    added, when dbdreader cannot open the file (or its whole records, when it is cut)."""
    with tempfile.TemporaryDirectory(prefix="glider-hil-cac-") as scratch:
        # A file that carries its sensor list has dbdreader write it into the cache given;
        # a scratch directory keeps a list cut short out of the user's cache.
        carries = header.get("sensor_list_factored", "").strip() == "0"
        given = Path(scratch) if carries else cache
        dbd = _open(path, path, given, cache, dbdreader)
        try:
            cut = _whole_records(path, dbd, Path(scratch), dbdreader)
            if cut is not None:
                dbd.close()
                dbd = _open(Path(scratch) / WHOLE_RECORDS, path, given, cache, dbdreader)
                issues.notes.append(cut.note(path))
            _read(dbd, path, number, columns, issues, cut)
        finally:
            dbd.close()
        if carries:
            _keep_sensor_list(Path(scratch), cache, str(dbd.cacheID))


def _open(file: Path, path: Path, given: Path, cache: Path, dbdreader: Any) -> Any:
    """dbdreader's reader of ``file`` (``path`` or its whole records), its sensor list
    looked up in ``given``; what it raises is an error naming ``path``."""
    try:
        return dbdreader.DBD(str(file), cacheDir=str(given))
    except dbdreader.DbdError as error:
        raise _explain(path, cache, error, dbdreader) from error
    except Exception as error:  # KeyError, IndexError, ValueError, … on a damaged file
        raise UnreadableFile(
            path,
            f"{path}: not a readable Slocum file ({type(error).__name__}: {error}); a "
            "file cut short in transfer reads like this",
        ) from error


def _whole_records(path: Path, dbd: Any, scratch: Path, dbdreader: object) -> CutRecord | None:
    """Where ``path`` is cut partway through a record, with its whole records written to
    ``scratch / WHOLE_RECORDS`` (decompressed) for dbdreader to read instead: dbdreader
    would take the cut record's missing bytes from the record before it. None when the
    file ends after a whole record, or its bytes cannot be decompressed (dbdreader then
    says so)."""
    try:
        raw = _data_bytes(path, dbdreader)
    except Exception:  # lz4's errors on a damaged compressed file: dbdreader names them
        return None
    cut = find_cut(
        raw,
        int(dbd.fp_binary_start),
        int(dbd.n_state_bytes),
        tuple(dbd.byteSizes),
    )
    if cut is not None:
        (scratch / WHOLE_RECORDS).write_bytes(raw[: cut.at])
    return cut


def _data_bytes(path: Path, dbdreader: object) -> bytes:
    """The file's bytes, decompressed when it is a compressed one (``.dcd`` …)."""
    decompress = getattr(dbdreader, "decompress", None)
    if decompress is not None and decompress.is_compressed(str(path)):
        with decompress.Decompressor(str(path)) as packed:
            return bytes(packed.decompress())
    return path.read_bytes()


def _header(path: Path, dbdreader: object) -> dict[str, str]:
    """The file's ASCII header tags, checked complete as dbdreader reads it: a first line
    ``dbd_label``, then lines up to the ``num_ascii_tags``-th, each ended by a newline;
    else an error naming the file."""
    decompress = getattr(dbdreader, "decompress", None)
    try:
        if decompress is not None and decompress.is_compressed(str(path)):
            with decompress.Decompressor(str(path)) as packed:
                head = b"".join(packed.decompressed_blocks(2))[:HEADER_BYTES]
        else:
            with path.open("rb") as fp:
                head = fp.read(HEADER_BYTES)
    except Exception as error:  # OSError, lz4's errors on a damaged compressed file
        message = f"{path}: cannot be read ({type(error).__name__}: {error})"
        raise UnreadableFile(path, message) from error
    tags: dict[str, str] = {}
    complete = head.split(b"\n")[:-1]  # the piece after the last newline is cut short
    for number, line in enumerate(complete, start=1):
        key, _, value = line.decode("latin-1").partition(":")
        if number == 1 and key != "dbd_label":
            message = f"{path}: not a Slocum file (its first line is no dbd_label)"
            raise UnreadableFile(path, message)
        tags.setdefault(key, value.strip())
        count = tags.get("num_ascii_tags")
        if count is None:
            continue
        if not count.isdigit() or int(count) < number:
            raise UnreadableFile(
                path,
                f"{path}: not a readable Slocum file (num_ascii_tags {count!r} on line {number})",
            )
        if int(count) == number:
            return tags
    expected = tags.get("num_ascii_tags", "?")
    raise UnreadableFile(
        path,
        f"{path}: cut short in its ASCII header ({len(complete)} complete lines of "
        f"num_ascii_tags {expected}); a file cut short in transfer reads like this",
    )


def _keep_sensor_list(scratch: Path, cache: Path, cache_id: str) -> None:
    """The sensor list a file carried, from the scratch cache into ``cache`` (unless one
    is there already), after the file was read whole: written under a temporary name and
    renamed, so the cache never holds a partial list."""
    source = scratch / f"{cache_id.lower()}.cac"
    target = cache / source.name
    if target.exists() or not source.is_file():
        return
    part = cache / f".{source.name}.part"
    try:
        shutil.copyfile(source, part)
        os.replace(part, target)
    except OSError as error:
        with contextlib.suppress(OSError):
            part.unlink(missing_ok=True)
        raise FieldError(f"--cache-dir {cache}: cannot write {target.name} ({error})") from error


def _explain(path: Path, cache: Path, error: Exception, dbdreader: object) -> FieldError:
    """dbdreader's error as ours: a sensor list missing from the cache is the user's to
    supply (never skipped), anything else a damaged file."""
    value = getattr(error, "value", None)
    if value == getattr(dbdreader, "DBD_ERROR_CACHE_NOT_FOUND", -1):
        data = getattr(error, "data", None)
        files = getattr(data, "missing_cache_files", None) or {}
        names = ", ".join(f"{cid}.cac" for cid in files) or "its sensor-list (.cac) file"
        return FieldError(
            f"{path}: the sensor list {names} is not in --cache-dir {cache}; copy it from "
            "the glider's state/cache (or the dockserver's) into that directory"
        )
    return UnreadableFile(path, f"{path}: not a readable Slocum file ({str(error).strip()})")


def _read(
    dbd: object,
    path: Path,
    number: int,
    columns: Columns,
    issues: Issues,
    cut: CutRecord | None = None,
) -> None:
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
        why = f"; it {cut.text()}" if cut is not None else ""
        raise FieldError(f"{path}: sensors unreadable ({error}){why}") from error
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
