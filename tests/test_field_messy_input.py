"""Messy field files: a clear error naming the file, or counted rows, never a hang, a
traceback, a damaged sensor-list cache or data read in the wrong unit or from two gliders.

The inputs are built here from the slices in tests/data/field/ and dbdreader's sample files.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.io import netcdf_file

from hil_service.offline.field import FieldError, read_field
from hil_service.offline.field.grid import resample
from hil_service.offline.field.mapped import load_mapping
from hil_service.offline.field.table import EARLY_TIME_NOTE
from tests.test_field_import import MAPPING

DATA = Path(__file__).parent / "data" / "field"
SG = DATA / "seaglider-sg542" / "p5420304.nc"
SEA = DATA / "seaexplorer-sea035"
MBD = "ammonite-2008-028-01-000.mbd"
HEADER = "time_s,p_dbar,pitch_deg,vbd,mass,dive"


# ---- Slocum ------------------------------------------------------------------------------


def _dbdreader_data() -> Path:
    dbdreader = pytest.importorskip("dbdreader")
    return Path(dbdreader.__file__).parent / "data"


def _mbd_bytes() -> bytes:
    return (_dbdreader_data() / MBD).read_bytes()


def _factored(raw: bytes) -> bytes:
    """The sample .mbd as a file that names its sensor list (in the cache) instead of
    carrying it: ``sensor_list_factored: 1`` and the sensor lines left out."""
    lines = raw.split(b"\n")
    tags = int(lines[2].split(b":")[1])
    sensors = int(next(x for x in lines if x.startswith(b"total_num_sensors")).split(b":")[1])
    header = [
        b"sensor_list_factored:    1" if x.startswith(b"sensor_list_factored") else x
        for x in lines[:tags]
    ]
    return b"\n".join([*header, *lines[tags + sensors :]])


@pytest.mark.timeout(30)
@pytest.mark.parametrize("size", [0, 50, 100, 400])
def test_a_slocum_file_cut_in_its_ascii_header_is_refused(tmp_path: Path, size: int) -> None:
    path = tmp_path / MBD
    path.write_bytes(_mbd_bytes()[:size])
    with pytest.raises(FieldError, match=rf"{MBD}: cut short in its ASCII header"):
        read_field([path], cache_dir=tmp_path)


@pytest.mark.timeout(30)
def test_a_slocum_header_whose_tag_count_is_never_reached_is_refused(tmp_path: Path) -> None:
    path = tmp_path / MBD
    path.write_bytes(_mbd_bytes().replace(b"num_ascii_tags:    14", b"num_ascii_tags:    2", 1))
    with pytest.raises(FieldError, match=rf"{MBD}: not a readable Slocum file"):
        read_field([path], cache_dir=tmp_path)


@pytest.mark.parametrize(
    "damage",
    [
        lambda raw: raw[:600],  # inside the sensor list: IndexError in dbdreader
        lambda raw: raw[:20_000],
        lambda raw: raw.replace(b"sensor_list_crc:", b"sensor_list_crx:", 1),  # KeyError
        lambda raw: raw.replace(b"total_num_sensors:    1385", b"total_num_sensors:    x", 1),
    ],
)
def test_a_damaged_slocum_file_is_an_error_naming_it(tmp_path: Path, damage: Any) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    path = tmp_path / MBD
    path.write_bytes(damage(_mbd_bytes()))
    with pytest.raises(FieldError, match=rf"{MBD}: not a readable Slocum file"):
        read_field([path], cache_dir=cache)


def test_a_sensor_list_cut_short_stays_out_of_the_cache(tmp_path: Path) -> None:
    raw = _mbd_bytes()
    cache, cut, whole = tmp_path / "cache", tmp_path / "cut", tmp_path / "whole"
    for folder in (cache, cut, whole):
        folder.mkdir()
    (cut / MBD).write_bytes(raw[:5000])  # the header whole, the sensor list cut
    with pytest.raises(FieldError, match=MBD):
        read_field([cut / MBD], cache_dir=cache)
    assert list(cache.iterdir()) == []
    later = whole / "ammonite-2008-028-01-001.mbd"
    later.write_bytes(_factored(raw))
    with pytest.raises(FieldError, match=r"sensor list 813b137d\.cac is not in --cache-dir"):
        read_field([later], cache_dir=cache)
    (whole / MBD).write_bytes(raw)
    data = read_field([whole / MBD, later], cache_dir=cache)
    assert 1 in set(data.dive.tolist()) and data.vehicle == "ammonite"
    assert [p.name for p in cache.iterdir()] == ["813b137d.cac"]
    assert read_field([later], cache_dir=cache).size > 100  # the copied list reads


def test_slocum_files_of_two_gliders_are_refused(tmp_path: Path) -> None:
    data_dir = _dbdreader_data()
    files = [data_dir / MBD, data_dir / "amadeus-2014-204-05-000.sbd"]
    with pytest.raises(FieldError, match=r"two gliders: .*amadeus.*ammonite"):
        read_field(files, cache_dir=tmp_path)


# ---- Seaglider ---------------------------------------------------------------------------


def _seaglider(
    path: Path,
    attributes: dict[str, Any] | None = None,
    units: dict[str, str] | None = None,
    scale: dict[str, float] | None = None,
    drop: tuple[str, ...] = (),
) -> Path:
    """A copy of the SG542 dive 304 slice with global attributes set (None: removed),
    variables' units set, values scaled, and variables left out."""
    with netcdf_file(SG, "r", mmap=False) as src:
        given = dict(src._attributes)
        variables = {
            name: (np.array(var.data, dtype=float), dict(var._attributes))
            for name, var in src.variables.items()
            if name not in drop
        }
        size = src.dimensions["sg_data_point"]
    for key, value in (attributes or {}).items():
        if value is None:
            given.pop(key, None)
        else:
            given[key] = value
    path.parent.mkdir(parents=True, exist_ok=True)
    with netcdf_file(path, "w") as dst:
        for key, value in given.items():
            setattr(dst, key, value)
        dst.createDimension("sg_data_point", size)
        for name, (values, attrs) in variables.items():
            out = dst.createVariable(name, "f8", ("sg_data_point",))
            out[:] = values * (scale or {}).get(name, 1.0)
            if units and name in units:
                attrs["units"] = units[name]
            for key, value in attrs.items():
                setattr(out, key, value)
    return path


def test_seaglider_dive_numbers_beyond_int64_are_refused_naming_the_file(tmp_path: Path) -> None:
    for value in (1e30, math.inf):
        path = _seaglider(tmp_path / f"{value}" / "p5420304.nc", {"dive_number": value})
        with pytest.raises(FieldError, match=r"p5420304\.nc: dive_number attribute"):
            read_field([path])


@pytest.mark.parametrize(
    ("attribute", "value"),
    [
        ("dive_number", "abc"),
        ("dive_number", math.nan),
        ("glider", "sg542"),
        ("glider", ""),
        ("glider", math.nan),
    ],
)
def test_a_seaglider_attribute_that_is_no_number_names_the_file(
    tmp_path: Path, attribute: str, value: Any
) -> None:
    path = _seaglider(tmp_path / "p5420304.nc", {attribute: value})
    with pytest.raises(FieldError, match=rf"p5420304\.nc: {attribute} attribute"):
        read_field([path])


def test_a_seaglider_start_time_as_a_date_names_the_file(tmp_path: Path) -> None:
    path = _seaglider(tmp_path / "p5420304.nc", {"start_time": "2016-01-31"}, drop=("time",))
    with pytest.raises(FieldError, match=r"p5420304\.nc: start_time attribute"):
        read_field([path])


def test_a_seaglider_dive_without_an_absolute_time_is_refused(tmp_path: Path) -> None:
    path = _seaglider(tmp_path / "p5420304.nc", {"start_time": None}, drop=("time",))
    with pytest.raises(FieldError, match=r"p5420304\.nc: no absolute time"):
        read_field([path])


def test_seaglider_units_attributes_are_honoured(tmp_path: Path) -> None:
    original = read_field([SG])
    path = _seaglider(
        tmp_path / "p5420304.nc",
        units={"eng_depth": "m", "eng_pitchAng": "radians"},
        scale={"eng_depth": 0.01, "eng_pitchAng": math.pi / 180.0},
    )
    data = read_field([path])
    np.testing.assert_allclose(data.depth, original.depth, rtol=1e-12)
    np.testing.assert_allclose(data.pitch, original.pitch, rtol=1e-12)
    conversions = {c.quantity: c for c in data.conversions}
    assert (conversions["depth"].unit, conversions["depth"].scale) == ("m", 1.0)
    assert (conversions["pitch"].unit, conversions["pitch"].scale) == ("rad", 1.0)


@pytest.mark.parametrize(("variable", "unit"), [("eng_depth", "ft"), ("eng_pitchAng", "grad")])
def test_a_seaglider_unit_the_import_cannot_read_is_refused(
    tmp_path: Path, variable: str, unit: str
) -> None:
    path = _seaglider(tmp_path / "p5420304.nc", units={variable: unit})
    with pytest.raises(FieldError, match=rf"p5420304\.nc: {variable} has units '{unit}'"):
        read_field([path])


def test_seaglider_files_of_two_gliders_are_refused(tmp_path: Path) -> None:
    shutil.copy(SG, tmp_path)
    _seaglider(tmp_path / "p6010305.nc", {"glider": 601, "dive_number": 305})
    with pytest.raises(FieldError, match=r"two gliders: .*p5420304\.nc is SG542, .*SG601"):
        read_field([tmp_path])


# ---- SeaExplorer -------------------------------------------------------------------------


def _sea_rows(name: str = "sea035.12.gli.sub.37") -> list[list[str]]:
    return [line.split(";") for line in (SEA / name).read_text().splitlines()]


def _write_rows(path: Path, rows: list[list[str]]) -> Path:
    path.write_text("\n".join(";".join(r) for r in rows) + "\n")
    return path


def test_a_seaexplorer_file_number_beyond_int64_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "sea035.12.gli.sub.99999999999999999999999"
    shutil.copy(SEA / "sea035.12.gli.sub.37", path)
    with pytest.raises(FieldError, match=r"gli\.sub\.99999999999999999999999: file number"):
        read_field([path])


def test_seaexplorer_files_of_two_gliders_are_refused(tmp_path: Path) -> None:
    shutil.copy(SEA / "sea035.12.gli.sub.37", tmp_path)
    shutil.copy(SEA / "sea035.12.gli.sub.38", tmp_path / "sea099.3.gli.sub.38")
    with pytest.raises(FieldError, match=r"two gliders: .* is SEA035, .* is SEA099"):
        read_field([tmp_path])


def test_a_nan_navstate_is_a_row_without_one(tmp_path: Path) -> None:
    rows = _sea_rows()
    nav = rows[0].index("NavState")
    rows[100][nav] = "NaN"
    data = read_field([_write_rows(tmp_path / "sea035.12.gli.sub.37", rows)])
    assert data.issues.unparsable_rows == 0 and data.issues.rows == len(rows) - 1
    for row in rows[1:]:
        row[nav] = "NaN"
    path = _write_rows(tmp_path / "sea035.12.gli.sub.37", rows)
    data = read_field([path])
    assert data.issues.unparsable_rows == 0 and data.in_dive.all()
    assert data.issues.missing_columns == {str(path): ["NavState (all NaN)"]}


# ---- CSV ---------------------------------------------------------------------------------


def _csv_rows(step: float = 10.0, count: int = 60) -> list[str]:
    rows = []
    for k in range(count):
        depth = 0.2 * min(k, count - k) * 10
        rows.append(f"{1e9 + step * k:.3f},{depth:.2f},{-20 if k < count // 2 else 20},0,50,1")
    return rows


def _mapped(tmp_path: Path, rows: list[str], header: str = HEADER) -> tuple[Path, Path]:
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    path = tmp_path / "a.csv"
    path.write_text("\n".join([header, *rows]) + "\n")
    return path, mapping


def test_a_csv_dive_number_beyond_int64_is_an_unparsable_row(tmp_path: Path) -> None:
    rows = _csv_rows()
    rows[5] = rows[5].rsplit(",", 1)[0] + ",1e30"
    rows[6] = rows[6].rsplit(",", 1)[0] + ",-1e19"
    path, mapping = _mapped(tmp_path, rows)
    data = read_field([path], "csv", mapping)
    assert data.issues.unparsable_rows == 2 and data.size == len(rows) - 2
    assert f"{path}:7: unparsable row dropped" in data.issues.notes
    path.write_text("\n".join([HEADER, *(r.rsplit(",", 1)[0] + ",1e30" for r in rows)]) + "\n")
    with pytest.raises(FieldError, match=r"a\.csv: every row unparsable \(60"):
        read_field([path], "csv", mapping)


def test_a_csv_field_over_the_parser_s_limit_is_an_unparsable_row(tmp_path: Path) -> None:
    rows = _csv_rows()
    rows[10] = rows[10] + "," + "x" * 200_000 + '"'
    rows[11] = rows[11].replace(",0,", ',"' + "1" * 140_000 + '",', 1)
    path, mapping = _mapped(tmp_path, rows)
    data = read_field([path], "csv", mapping)
    assert data.issues.unparsable_rows == 2
    assert f"{path}:13: unparsable row dropped" in data.issues.notes


def test_a_csv_header_naming_a_used_column_twice_is_refused(tmp_path: Path) -> None:
    path, mapping = _mapped(tmp_path, [r + ",3" for r in _csv_rows()], HEADER + ",pitch_deg")
    with pytest.raises(FieldError, match=r"a\.csv:1: the header names column\(s\) 'pitch_deg'"):
        read_field([path], "csv", mapping)


def test_the_default_grid_period_is_the_median_step_below_a_tenth_of_a_second(
    tmp_path: Path,
) -> None:
    path, mapping = _mapped(tmp_path, _csv_rows(step=0.05, count=400))
    data = read_field([path], "csv", mapping)
    grid = resample(data)
    assert grid.period == 0.05
    assert grid.size == data.size == 400 and grid.interpolated == 0


def test_a_mapping_that_is_not_utf8_names_the_file(tmp_path: Path) -> None:
    mapping = tmp_path / "map.toml"
    mapping.write_bytes(MAPPING.replace('"vbd"', '"v\xe9b"').encode("latin-1"))
    with pytest.raises(FieldError, match=r"map\.toml: not UTF-8"):
        load_mapping(mapping)


def test_times_that_all_fall_before_1980_are_noted(tmp_path: Path) -> None:
    """Seconds read as milliseconds put a 2001 record in January 1970, 1,000-fold
    compressed: the import goes on (relative times are data too) but says so."""
    path, mapping = _mapped(tmp_path, _csv_rows())
    assert EARLY_TIME_NOTE not in read_field([path], "csv", mapping).issues.notes
    shrunk = [f"{float(r.split(',', 1)[0]) / 1000:.6f},{r.split(',', 1)[1]}" for r in _csv_rows()]
    path, mapping = _mapped(tmp_path, shrunk)
    assert EARLY_TIME_NOTE in read_field([path], "csv", mapping).issues.notes
