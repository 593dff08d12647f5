"""Parquet through a mapping file: the committed SeaExplorer slice written as Parquet."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest

from hil_service.offline.field import FieldError, read_field

pa = pytest.importorskip("pyarrow", reason="pyarrow comes with the [dev] and [field] extras")
pq = pytest.importorskip("pyarrow.parquet")

SEA = Path(__file__).parent / "data" / "field" / "seaexplorer-sea035"
SLICE = SEA / "sea035.12.gli.sub.37"
TIME_FORMAT = "%d/%m/%Y %H:%M:%S"

MAPPING = f"""\
[time]
column = "Timestamp"
format = "{TIME_FORMAT}"

[depth]
column = "Depth"
unit = "m"

[pitch]
column = "Pitch"
unit = "deg"

[buoyancy]
column = "BallastPos"
unit = "cc"
full_scale = 500

[pitch_input]
column = "LinPos"
unit = "mm"
centre = 60
full_scale = 50

[surface]
column = "NavState"
values = [105, 115, 116]
"""

NUMERIC = ("NavState", "Pitch", "Depth", "BallastPos", "LinPos")


def _slice_rows() -> list[dict[str, str]]:
    with SLICE.open(newline="") as handle:
        return list(csv.DictReader(handle, delimiter=";"))


def _write_parquet(path: Path, rows: list[dict[str, str | None]]) -> Path:
    """Typed columns as a logger writes them: the time as text, the rest as floats (None a
    null cell)."""
    columns: dict[str, list] = {"Timestamp": [r["Timestamp"] for r in rows]}
    for name in NUMERIC:
        columns[name] = [None if r.get(name) in (None, "") else float(r[name]) for r in rows]
    pq.write_table(pa.table(columns), path)
    return path


def _mapping(tmp_path: Path) -> Path:
    path = tmp_path / "sea035.toml"
    path.write_text(MAPPING)
    return path


def test_parquet_reads_as_the_native_seaexplorer_reader(tmp_path: Path) -> None:
    parquet = _write_parquet(tmp_path / "sea035-37.parquet", _slice_rows())
    mapped = read_field([parquet], "csv", _mapping(tmp_path))
    native = read_field([SLICE], "seaexplorer")
    assert mapped.t.size == native.t.size > 100
    np.testing.assert_allclose(mapped.t, native.t)
    np.testing.assert_allclose(mapped.depth, native.depth)
    np.testing.assert_allclose(mapped.pitch, native.pitch)
    np.testing.assert_array_equal(mapped.in_dive, native.in_dive)
    assert mapped.issues.surface_rows == native.issues.surface_rows > 0


def test_parquet_messy_rows_counted(tmp_path: Path) -> None:
    rows: list[dict[str, str | None]] = list(_slice_rows())
    clean = len(rows)
    rows.insert(50, dict(rows[49]))  # a repeated timestamp
    rows[80], rows[81] = rows[81], rows[80]  # out of order
    rows[120] = {**rows[120], "Depth": None, "Pitch": None}  # null cells: a NaN row
    rows[150] = {**rows[150], "Timestamp": "not a time"}  # unparsable
    rows[200] = {**rows[200], "BallastPos": None}  # an input missing: held
    parquet = _write_parquet(tmp_path / "messy.parquet", rows)
    data = read_field([parquet], "csv", _mapping(tmp_path))
    issues = data.issues
    assert issues.repeated_time == 1 and issues.out_of_order == 1
    assert issues.nan_rows == 1 and issues.unparsable_rows == 1
    assert issues.filled_inputs >= 1
    assert any("messy.parquet" in note and "unparsable" in note for note in issues.notes)
    assert data.t.size == clean - 2  # the NaN row and the unparsable one
    assert np.all(np.diff(data.t) > 0) and np.all(np.isfinite(data.depth))


def test_parquet_missing_a_column_names_the_file_and_the_mapping_line(tmp_path: Path) -> None:
    rows = [{k: v for k, v in r.items() if k != "Pitch"} for r in _slice_rows()]
    columns = {"Timestamp": [r["Timestamp"] for r in rows]}
    for name in ("NavState", "Depth", "BallastPos", "LinPos"):
        columns[name] = [float(r[name]) for r in rows]
    path = tmp_path / "nopitch.parquet"
    pq.write_table(pa.table(columns), path)
    expected = r"nopitch\.parquet:1: no column 'Pitch' .*sea035\.toml:10"
    with pytest.raises(FieldError, match=expected):
        read_field([path], "csv", _mapping(tmp_path))


def test_a_file_that_is_not_parquet_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.parquet"
    path.write_bytes(b"PAR1" + b"\0" * 64)
    with pytest.raises(FieldError, match=r"broken\.parquet: not a readable Parquet file"):
        read_field([path], "csv", _mapping(tmp_path))


def test_without_pyarrow_the_import_says_what_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    parquet = _write_parquet(tmp_path / "a.parquet", _slice_rows()[:20])
    # None in sys.modules makes the import raise ImportError, as an absent package does.
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(FieldError, match=r"a\.parquet: reading Parquet needs pyarrow.*\[field\]"):
        read_field([parquet], "csv", _mapping(tmp_path))
