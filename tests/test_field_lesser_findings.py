"""Field import and report on lesser bad input: a Slocum file cut in its data is read up to
its last whole record and says so; a huge input value is clipped without a numpy warning,
and one that is no number is held; a report whose training dives validate no structure
says so instead of printing an empty list of fits (absurd mapping numbers:
``tests/test_import_bad_input.py``).

The Slocum inputs are cut copies of the sample file dbdreader's wheel ships.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from hil_service.cli import main
from hil_service.mcap.reader import LogReader
from hil_service.offline.field import FieldError, read_field
from tests.test_field_import import MAPPING

MBD = "ammonite-2008-028-01-000.mbd"
#: The sample .mbd's data part starts here (after its ASCII header and sensor list).
DATA_START = 59_858


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """The CLI's exit code, stdout and stderr, and no traceback."""
    try:
        code = main(list(args))
    except SystemExit as stop:
        code = int(stop.code or 0)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def _mbd(tmp_path: Path, size: int | None = None, name: str = "cut") -> Path:
    """The sample .mbd, its first ``size`` bytes (all of it: None), in its own folder."""
    dbdreader = pytest.importorskip("dbdreader")
    raw = (Path(dbdreader.__file__).parent / "data" / MBD).read_bytes()
    folder = tmp_path / name
    folder.mkdir()
    path = folder / MBD
    path.write_bytes(raw if size is None else raw[:size])
    return path


def _notes(log: Path) -> list[str]:
    reader = LogReader(log)
    for _ in reader.messages({"glider/1/telemetry"}):
        pass
    return reader.config()["field"]["issues"]["notes"]


# ---- a Slocum file cut partway through its data ------------------------------------------


@pytest.mark.parametrize(
    ("size", "where", "rows"),
    [
        (201_928, "in record 856, 99 of its 170 bytes missing; the 855 whole record(s)", 854),
        (200_000, "in the state bytes of record 845 (its length unknown); the 844 whole", 843),
    ],
)
def test_a_slocum_file_cut_in_its_data_says_so_and_keeps_its_whole_records(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], size: int, where: str, rows: int
) -> None:
    cut = _mbd(tmp_path, size)
    cache = tmp_path / "cache"
    cache.mkdir()
    log = tmp_path / "cut.mcap"
    code, out, err = _run(capsys, "import", str(cut), "--cache-dir", str(cache), "-o", str(log))
    assert code == 0, err
    note = f"{cut}: ends partway through its data, {where}"
    assert note in out
    assert any(n.startswith(note) for n in _notes(log))  # stored with the log's issues
    # The rows read are the whole file's first ones: the cut record is not read from
    # stale bytes (dbdreader alone gives a last depth of 60.5 m where the file has 604.3).
    data = read_field([cut], cache_dir=cache)
    whole = read_field([_mbd(tmp_path, name="whole")], cache_dir=cache)
    assert data.size == rows < whole.size
    for name in ("t", "depth", "pitch", "buoyancy", "pitch_input"):
        np.testing.assert_array_equal(getattr(data, name), getattr(whole, name)[:rows])


def test_a_slocum_file_ending_after_a_whole_record_has_no_cut_note(tmp_path: Path) -> None:
    """The whole file, and the file without its end tag 'X' (as a file sent compressed
    ends), read alike and without a note."""
    cache = tmp_path / "cache"
    cache.mkdir()
    whole = _mbd(tmp_path, name="whole")
    untagged = _mbd(tmp_path, whole.stat().st_size - 1, name="untagged")
    read = [read_field([path], cache_dir=cache) for path in (whole, untagged)]
    for data in read:
        assert not [n for n in data.issues.notes if "partway" in n]
    np.testing.assert_array_equal(read[0].depth, read[1].depth)


def test_a_slocum_file_cut_before_a_whole_record_is_an_error_naming_the_cut(
    tmp_path: Path,
) -> None:
    cut = _mbd(tmp_path, DATA_START + 300)
    cache = tmp_path / "cache"
    cache.mkdir()
    with pytest.raises(FieldError) as caught:
        read_field([cut], cache_dir=cache)
    message = str(caught.value)
    assert message.startswith(f"{cut}: sensors unreadable")
    assert "ends partway through its data, in record 1, 164 of its 448 bytes missing" in message


# ---- mapping numbers ---------------------------------------------------------------------


def _csv(tmp_path: Path, rows: list[str] | None = None) -> Path:
    """A one-dive CSV of the mapping's columns (``rows`` replaces the default body)."""
    body = rows or [
        f"{1.6e9 + 10 * k!r},{2.0 * k},-20,{100 + k},{55 + k % 10},1" for k in range(30)
    ]
    path = tmp_path / "d.csv"
    path.write_text("\n".join(["time_s,p_dbar,pitch_deg,vbd,mass,dive", *body]) + "\n")
    return path


def _import_with_buoyancy(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str
) -> tuple[str, list[float], list[warnings.WarningMessage]]:
    """Import a one-dive CSV whose buoyancy is 100 cc on every row but the 11th, which
    says ``text``: stdout, the logged u_depth per grid sample, and the warnings raised."""
    rows = [f"{1.6e9 + 10 * k!r},{2.0 * k},-20,100,60,1" for k in range(30)]
    rows[10] = f"{1.6e9 + 100!r},20,-20,{text},60,1"
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    log = tmp_path / "o.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, out, err = _run(
            capsys, "import", str(_csv(tmp_path, rows)), "--mapping", str(mapping), "-o", str(log)
        )
    assert code == 0, err
    u = [m.json()["u_depth"] for m in LogReader(log).messages({"glider/1/telemetry"})]
    return out, u, caught


def test_an_input_value_beyond_float_range_is_clipped_without_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # model value 2·1.7e308/500: beyond float range
    out, u, caught = _import_with_buoyancy(tmp_path, capsys, "1.7e308")
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]
    assert "clipped to full scale: {'buoyancy': 1, 'pitch_input': 0}" in out
    assert max(u) == 2.0 and all(np.isfinite(u))


@pytest.mark.parametrize("text", ["inf", "-inf", "nan"])
def test_an_input_that_is_not_a_finite_number_is_held_not_clipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str
) -> None:
    """A text ``inf`` is no reading: held from the sample before, like NaN, where a finite
    1.7e308 is a reading and is clipped (above)."""
    out, u, _ = _import_with_buoyancy(tmp_path, capsys, text)
    assert out.startswith("csv: 1 file(s)\n")  # a format without a vehicle name
    assert "clipped to full scale" not in out
    assert " 1 input values held from the previous sample" in out
    assert len(set(u)) == 1 and np.isfinite(u[0])  # every sample the held 100


# ---- the report when no training dive validates ------------------------------------------


def test_the_report_says_no_training_dive_validated_instead_of_empty_fits(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Three dives of 24 samples (10 s): none as long as the L + 1 + k (k = 300 s) samples
    the structure's validation needs."""
    rows = []
    for dive in (1, 2, 3):
        for k in range(24):
            t = 1.6e9 + dive * 10_000 + 10 * k
            down = k < 12
            rows.append(
                f"{t!r},{2.0 + 3.0 * min(k, 24 - k)},{-20 if down else 20},"
                f"{-200 if down else 200},{50 + k % 3},{dive}"
            )
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    log = tmp_path / "short.mcap"
    data = str(_csv(tmp_path, rows))
    code, _, err = _run(capsys, "import", data, "--mapping", str(mapping), "-o", str(log))
    assert code == 0, err
    code, _, err = _run(capsys, "report", str(log), "-o", str(tmp_path / "report"))
    assert code == 0, err
    text = (tmp_path / "report" / "report.md").read_text()
    assert (
        "Structure not validated: no training dive validated a candidate (0 training dive(s) "
        "long enough to validate on, 2 needed: the default steady-glide input, M=1); median "
        "free-run fit %: none." in text
    )
    assert not re.search(r"median free-run fit %: *\.", text)
