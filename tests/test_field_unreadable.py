"""A field import of several files with one that cannot be read (a dive cut short in
transfer): that file is skipped and named, every other file's samples are imported as if it
were not there, and the import fails only when no file can be read. Errors of meaning (a
unit the import cannot read, a sensor list missing from the cache) still refuse.
"""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from hil_service.cli.processes import run_verb
from hil_service.offline.field import FieldError, read_field
from hil_service.offline.field.table import FieldData
from tests.test_field_import import MAPPING
from tests.test_field_messy_input import MBD, _dbdreader_data, _mbd_bytes, _seaglider

DATA = Path(__file__).parent / "data" / "field"
SG = DATA / "seaglider-sg542"
SEA = DATA / "seaexplorer-sea035"
CUT_DIVE = "p5420305.nc"


def _same_samples(a: FieldData, b: FieldData) -> None:
    assert a.size == b.size > 0
    for name in ("t", "depth", "pitch", "buoyancy", "pitch_input", "dive", "in_dive"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _seaglider_dives(folder: Path, cut: int | None) -> Path:
    """The three SG542 slices in ``folder``, dive 305 cut to ``cut`` bytes (None: left out)."""
    folder.mkdir()
    for source in sorted(SG.glob("*.nc")):
        if source.name != CUT_DIVE:
            shutil.copy(source, folder / source.name)
        elif cut is not None:
            (folder / source.name).write_bytes(source.read_bytes()[:cut])
    return folder


@pytest.mark.parametrize("cut", [0, 3000, 20_000])
def test_a_seaglider_dive_cut_short_is_skipped_and_named(tmp_path: Path, cut: int) -> None:
    data = read_field([_seaglider_dives(tmp_path / "with", cut)])
    without = read_field([_seaglider_dives(tmp_path / "without", None)])
    _same_samples(data, without)
    cut_path = str(tmp_path / "with" / CUT_DIVE)
    assert list(data.issues.unreadable_files) == [cut_path]
    assert "not a readable netCDF3 file" in data.issues.unreadable_files[cut_path]
    assert any(n.startswith(cut_path) and n.endswith(": skipped") for n in data.issues.notes)
    assert cut_path not in data.files and len(data.files) == 2
    assert data.issues.as_dict()["unreadable_files"] == data.issues.unreadable_files
    assert "1 file(s) that could not be read skipped" in data.issues.describe()[0]


def test_an_import_none_of_whose_files_can_be_read_is_an_error(tmp_path: Path) -> None:
    for name in ("p5420304.nc", "p5420305.nc"):
        (tmp_path / name).write_bytes((SG / name).read_bytes()[:3000])
    with pytest.raises(
        FieldError, match=r"none of the 2 files could be read; the first: .*p5420304"
    ):
        read_field([tmp_path])


def test_a_seaglider_unit_the_import_cannot_read_still_refuses_the_import(tmp_path: Path) -> None:
    folder = _seaglider_dives(tmp_path / "dives", None)
    _seaglider(folder / "p5420399.nc", {"dive_number": 399}, units={"eng_depth": "fathoms"})
    with pytest.raises(FieldError, match=r"p5420399\.nc: eng_depth has units 'fathoms'"):
        read_field([folder])


@pytest.mark.timeout(60)
def test_a_damaged_slocum_file_among_others_is_skipped(tmp_path: Path) -> None:
    raw = _mbd_bytes()
    cache, folder = tmp_path / "cache", tmp_path / "files"
    cache.mkdir()
    folder.mkdir()
    (folder / MBD).write_bytes(raw)
    damaged = folder / "ammonite-2008-028-01-001.mbd"
    damaged.write_bytes(raw[:600])  # inside its sensor list
    data = read_field([folder], cache_dir=cache)
    alone = read_field([_dbdreader_data() / MBD], cache_dir=tmp_path / "cache")
    _same_samples(data, alone)
    assert list(data.issues.unreadable_files) == [str(damaged)]
    assert "not a readable Slocum file" in data.issues.unreadable_files[str(damaged)]


def test_a_slocum_sensor_list_missing_from_the_cache_still_refuses(tmp_path: Path) -> None:
    files = [_dbdreader_data() / f"amadeus-2014-204-05-00{n}.sbd" for n in (0, 1)]
    with pytest.raises(FieldError, match=r"sensor list 093bd5ed\.cac is not in --cache-dir"):
        read_field(files, cache_dir=tmp_path)


def test_a_seaexplorer_file_cut_short_in_its_gzip_is_skipped(tmp_path: Path) -> None:
    names = sorted(p.name for p in SEA.glob("*.gli.sub.*"))
    for name in names:
        shutil.copy(SEA / name, tmp_path / name)
    without = read_field([tmp_path])
    packed = gzip.compress((SEA / names[1]).read_bytes())
    cut = tmp_path / f"{names[1]}.gz"
    (tmp_path / names[1]).unlink()
    cut.write_bytes(packed[: len(packed) // 2])
    data = read_field([tmp_path])
    assert list(data.issues.unreadable_files) == [str(cut)]
    assert "cannot be read" in data.issues.unreadable_files[str(cut)]
    assert data.size < without.size
    kept = np.isin(without.dive, data.dive)
    np.testing.assert_array_equal(data.t, without.t[kept])


def test_an_empty_csv_among_others_is_skipped(tmp_path: Path) -> None:
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    good = tmp_path / "a.csv"
    good.write_text(
        "time_s,p_dbar,pitch_deg,vbd,mass,dive\n"
        + "\n".join(f"{1.7e9 + i},{10 + 0.1 * i},-20,{-100 + i},{5},1" for i in range(50))
        + "\n"
    )
    empty = tmp_path / "b.csv"
    empty.write_text("")
    data = read_field([good, empty], mapping=mapping)
    _same_samples(data, read_field([good], mapping=mapping))
    assert list(data.issues.unreadable_files) == [str(empty)]
    with pytest.raises(FieldError, match=r"b\.csv:1: empty file"):
        read_field([empty], mapping=mapping)


def test_the_import_and_its_report_name_the_skipped_dive(tmp_path: Path) -> None:
    folder = _seaglider_dives(tmp_path / "dives", 3000)
    out = tmp_path / "sg.mcap"
    result = run_verb("import", str(folder), "-o", str(out), timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"{folder / CUT_DIVE}: not a readable netCDF3 file" in result.stdout
    report_dir = tmp_path / "report"
    result = run_verb("report", str(out), "-o", str(report_dir), timeout=300)
    assert result.returncode == 0, result.stderr
    text = (report_dir / "report.md").read_text()
    assert "2 file(s) read, 1 that could not be read skipped" in text
    assert f"{folder / CUT_DIVE}: not a readable netCDF3 file" in text


def test_one_unreadable_file_given_twice_is_still_nothing_read(tmp_path: Path) -> None:
    cut = tmp_path / "p5420304.nc"
    cut.write_bytes((SG / "p5420304.nc").read_bytes()[:3000])
    with pytest.raises(FieldError, match=r"none of the 2 files could be read"):
        read_field([cut, cut])
