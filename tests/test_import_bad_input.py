"""`glider-hil import` on bad input: a clear error (exit 2, no traceback) or counted and
skipped rows, never a crash, a hang or wrong data in the log."""

from __future__ import annotations

import json
import math
import re
import shutil
import struct
import warnings
from pathlib import Path

import pytest

from hil_service.cli import main
from hil_service.mcap.reader import LogReader
from hil_service.offline.field import read_field
from tests.test_field_import import MAPPING
from tests.test_tlog_import import T0, tlog_bytes

SEA = Path(__file__).parent / "data" / "field" / "seaexplorer-sea035"
DIVE = "sea035.12.gli.sub.37"


def _import(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """The CLI's exit code (argparse's too), stdout and stderr."""
    try:
        code = main(["import", *args])
    except SystemExit as stop:
        code = int(stop.code or 0)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


def _sea_copy(tmp_path: Path) -> Path:
    folder = tmp_path / "sx"
    folder.mkdir()
    for path in SEA.glob("sea035.*"):
        shutil.copy(path, folder)
    return folder


def _set_cell(path: Path, line: int, column: str, value: str) -> None:
    """Line ``line`` (1-based, the header is 1) of a SeaExplorer file gets ``value``."""
    lines = path.read_text(encoding="latin-1").split("\n")
    fields = lines[line - 1].split(";")
    fields[lines[0].split(";").index(column)] = value
    lines[line - 1] = ";".join(fields)
    path.write_text("\n".join(lines), encoding="latin-1")


def _telemetry(log: Path) -> list[dict]:
    return [m.json() for m in LogReader(log).messages() if m.topic == "glider/1/telemetry"]


@pytest.mark.parametrize(
    ("column", "value"),
    [
        ("Depth", "1e39"),  # beyond a 32-bit float
        ("Depth", "-1e308"),
        ("Depth", "-5000"),  # 5 km above the sea
        ("Depth", "12000"),  # below the deepest trench
        ("Pitch", "1e300"),
        ("Pitch", "120"),  # degrees: beyond an Euler pitch's ±90°
    ],
)
def test_an_absurd_field_value_is_counted_and_skipped(tmp_path, capsys, column, value):
    folder = _sea_copy(tmp_path)
    _set_cell(folder / DIVE, 100, column, value)
    log = tmp_path / "x.mcap"
    code, out, err = _import(capsys, str(folder), "-o", str(log), "--json")
    assert code == 0, err
    assert json.loads(out)["import"]["issues"]["out_of_range"] == 1
    samples = _telemetry(log)
    assert samples and all(-50 <= s["depth"] <= 11_000 for s in samples)
    assert all(abs(s["pitch"]) <= math.pi / 2 for s in samples)
    code, out, _ = _import(capsys, str(folder), "-o", str(log), "--force")
    assert "1 out of range (dropped)" in out


def _csv(tmp_path: Path, scale: float = 1.0, offset: float = 0.0) -> tuple[Path, Path]:
    """A two-dive CSV (its times × ``scale`` + ``offset``) and the mapping that reads it."""
    rows = ["time_s,p_dbar,pitch_deg,vbd,mass,dive"]
    for dive in (1, 2):
        for k in range(60):
            t = (1.6e9 + dive * 10_000 + 10 * k) * scale + offset
            depth = 2.0 * min(k, 60 - k)
            pitch, vbd = (-20, -200) if k < 30 else (20, 200)
            rows.append(f"{t!r},{depth},{pitch},{vbd},50,{dive}")
    data = tmp_path / "d.csv"
    data.write_text("\n".join(rows) + "\n")
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    return data, mapping


@pytest.mark.parametrize(
    ("scale", "offset"),
    [(1000.0, 0.0), (1e4, 0.0), (1.0, -2e9)],  # ms as s, ×1e4, before 1970
)
def test_csv_times_no_log_can_hold_are_an_error_naming_the_unit(tmp_path, capsys, scale, offset):
    data, mapping = _csv(tmp_path, scale, offset)
    log = tmp_path / "o.mcap"
    code, _, err = _import(capsys, str(data), "--mapping", str(mapping), "-o", str(log))
    assert code == 2
    assert "d.csv: no time between 1970-01-01 and 2554-07-21" in err
    assert "unit 's'" in err and "map.toml" in err
    assert not log.exists()


def test_csv_rows_with_a_time_no_log_can_hold_are_counted(tmp_path, capsys):
    data, mapping = _csv(tmp_path)
    lines = data.read_text().splitlines()
    lines[5] = "-3.5" + lines[5][lines[5].index(",") :]  # before 1970
    lines[70] = "1e12" + lines[70][lines[70].index(",") :]  # the year 33658
    data.write_text("\n".join(lines) + "\n")
    code, out, err = _import(
        capsys, str(data), "--mapping", str(mapping), "-o", str(tmp_path / "o.mcap"), "--json"
    )
    assert code == 0, err
    assert json.loads(out)["import"]["issues"]["out_of_range"] == 2


def _tlog(tmp_path: Path, data: bytes, name: str = "dive.tlog") -> Path:
    path = tmp_path / name
    path.write_bytes(data)
    return path


def _with_time(data: bytes, offsets: list[int], record: int, t_us: int) -> bytes:
    return data[: offsets[record]] + struct.pack(">Q", t_us) + data[offsets[record] + 8 :]


def test_tlog_records_with_an_absurd_time_are_counted_and_skipped(tmp_path, capsys):
    data, offsets = tlog_bytes()
    data = _with_time(data, offsets, 3, (1 << 64) - 1)
    log = tmp_path / "t.mcap"
    code, out, err = _import(capsys, str(_tlog(tmp_path, data)), "-o", str(log), "--json")
    assert code == 0, err
    report = json.loads(out)["import"]
    assert report["bad_times"] == 1 and report["records"] == 20
    times = [m.log_time_ns for m in LogReader(log).messages() if m.topic.startswith("mavlink/raw")]
    assert len(times) == 19 and max(times) < (T0 + 20 * 100_000) * 1000


def test_a_tlog_whose_every_time_is_absurd_is_an_error_naming_the_unit(tmp_path, capsys):
    data, offsets = tlog_bytes()
    for record in range(len(offsets)):
        data = _with_time(data, offsets, record, (1 << 64) - 1)
    log = tmp_path / "t.mcap"
    code, _, err = _import(capsys, str(_tlog(tmp_path, data)), "-o", str(log))
    assert code == 2
    assert "dive.tlog: no record has a time a log can hold" in err and "µs since 1970" in err
    assert not log.exists()


@pytest.mark.parametrize(
    "content",
    [b"", bytes(range(256)) * 4, b"hello, not a tlog\n" * 50],
    ids=["empty", "bytes", "text"],
)
def test_a_tlog_without_a_record_is_a_clear_error(tmp_path, capsys, content):
    log = tmp_path / "t.mcap"
    code, _, err = _import(capsys, str(_tlog(tmp_path, content, "zero.tlog")), "-o", str(log))
    assert code == 2
    assert "zero.tlog: no MAVLink record" in err
    assert not log.exists()


@pytest.mark.parametrize("given", ["0", "256", "300", "999", "-1", "one"])
def test_system_id_beyond_a_byte_is_refused(tmp_path, capsys, given):
    code, _, err = _import(capsys, str(SEA), "-o", str(tmp_path / "s.mcap"), "--system-id", given)
    assert code == 2 and "--system-id" in err
    assert "1..255" in err or "not an integer" in err


def test_system_id_255_is_the_vehicle_in_the_log(tmp_path, capsys):
    log = tmp_path / "s.mcap"
    code, _, err = _import(capsys, str(SEA), "-o", str(log), "--system-id", "255")
    assert code == 0, err
    assert any(m.topic == "glider/255/telemetry" for m in LogReader(log).messages())


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ('delimiter = ","', 'delimiter = ""', r"map\.toml:2: \[file\] delimiter must be one"),
        ('delimiter = ","', 'delimiter = ";;"', r"\[file\] delimiter must be one character"),
        ('delimiter = ","', 'kind = "xlsx"', r"map\.toml:2: \[file\] kind must be one of csv"),
        ('unit = "dbar"', 'unit = "dbar"\nwater_density = 0', r"\[pressure\] water_density must"),
        ('unit = "dbar"', 'unit = "dbar"\nsurface = nan', r"\[pressure\] surface must be a fin"),
        ("centre = 60", "centre = nan", r"map\.toml:\d+: \[pitch_input\] centre must be a finite"),
        ("full_scale = 500", "full_scale = inf", r"\[buoyancy\] full_scale must be a finite"),
        ('unit = "s"', 'unit = "s"\nformat = "%Y"', r"\[time\] format and unit both given"),
        ('[dive]\ncolumn = "dive"', '[surface]\ncolumn = "dive"\nvalues = 105', r"\[surface\] va"),
        ('unit = "deg"', "unit = []", r"\[pitch\] unit must be a string"),
        # Finite numbers beyond what any glider or tank holds (1e308 would overflow the
        # scaling), refused by their bounds.
        ("centre = 60", "centre = 1e308", r"\[pitch_input\] centre must be -1e\+12\.\.1e\+12"),
        ("centre = 60", "centre = -1e308", r"\[pitch_input\] centre must be -1e\+12\.\.1e\+12"),
        ("full_scale = 500", "full_scale = 1e308", r"\[buoyancy\] full_scale must be 1e-09\.\."),
        ("full_scale = 500", "full_scale = 1e-308", r"\[buoyancy\] full_scale must be 1e-09\.\."),
        (
            'unit = "dbar"',
            'unit = "dbar"\nwater_density = 1e308',
            r"\[pressure\] water_density must be 500\.\.2000",
        ),
        (
            'unit = "dbar"',
            'unit = "dbar"\nwater_density = 1.025',
            r"\[pressure\] water_density must be 500\.\.2000",
        ),
        (
            'unit = "dbar"',
            'unit = "dbar"\nsurface = 1e308',
            r"\[pressure\] surface must be within ±100 dbar",
        ),
        (
            'unit = "dbar"',
            'unit = "dbar"\nsurface = -1e308',
            r"\[pressure\] surface must be within ±100 dbar",
        ),
    ],
)  # fmt: skip
def test_a_mapping_value_that_makes_no_sense_names_file_table_and_key(
    tmp_path, capsys, old, new, message
):
    """One line naming the file, the line, the table and the key; no numpy warning on
    the way (an absurd number must not reach the arithmetic)."""
    data, mapping = _csv(tmp_path)
    assert old in MAPPING
    mapping.write_text(MAPPING.replace(old, new, 1))
    log = tmp_path / "o.mcap"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, _, err = _import(capsys, str(data), "--mapping", str(mapping), "-o", str(log))
    assert code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert re.match(rf"glider-hil import: {re.escape(str(mapping))}:\d+: ", err), err
    assert re.search(message, err), err
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)]
    assert not log.exists()


def test_a_seaexplorer_row_cut_short_is_unparsable(tmp_path):
    folder = _sea_copy(tmp_path)
    lines = (folder / DIVE).read_text(encoding="latin-1").split("\n")
    depth_at = lines[0].split(";").index("Depth")
    last = lines[250].split(";")
    assert float(last[depth_at]) > 500  # the glider is deep here
    cut = ";".join(last[:depth_at]) + ";" + last[depth_at][:2]  # 578.4 → 57
    (folder / DIVE).write_text("\n".join([*lines[:250], cut]), encoding="latin-1")
    data = read_field([folder])
    assert data.issues.unparsable_rows == 1
    dive = data.depth[data.dive == 37]
    assert dive[-1] > 500  # the last whole row, not the cut one


def test_a_csv_row_cut_short_is_unparsable(tmp_path):
    data, mapping = _csv(tmp_path)
    mapping.write_text(MAPPING.replace('[dive]\ncolumn = "dive"\n', ""))
    lines = data.read_text().splitlines()
    lines[40] = ",".join(lines[40].split(",")[:4])  # mass and dive cut off
    data.write_text("\n".join(lines) + "\n")
    fields = read_field([data], "csv", mapping)
    assert fields.issues.unparsable_rows == 1 and fields.issues.filled_inputs == 0


@pytest.mark.parametrize("period", ["1e-6", "0", "-1", "nan", "inf"])
def test_a_grid_period_below_a_millisecond_is_refused(tmp_path, capsys, period):
    code, _, err = _import(capsys, str(SEA), "-o", str(tmp_path / "g.mcap"), "--period", period)
    assert code == 2 and "--period" in err and "at least 0.001 s" in err


def test_a_grid_period_that_is_nearly_all_interpolation_is_refused(tmp_path, capsys):
    log = tmp_path / "g.mcap"
    code, _, err = _import(capsys, str(SEA), "-o", str(log), "--period", "0.01")
    assert code == 2 and "grid period 0.01 s would make" in err and "per raw sample" in err
    assert not log.exists()


@pytest.mark.parametrize("gap", ["0", "-5", "nan"])
def test_a_gap_that_is_no_duration_is_refused(tmp_path, capsys, gap):
    code, _, err = _import(capsys, str(SEA), "-o", str(tmp_path / "g.mcap"), "--gap", gap)
    assert code == 2 and "--gap" in err


@pytest.mark.parametrize("kind", ["field", "tlog"])
def test_an_output_that_is_a_directory_is_refused(tmp_path, capsys, kind):
    source = str(SEA) if kind == "field" else str(_tlog(tmp_path, tlog_bytes()[0]))
    out = tmp_path / "d2.mcap"
    out.mkdir()
    code, _, err = _import(capsys, source, "-o", str(out), "--force")
    assert code == 2 and f"-o {out} is a directory" in err
    assert not any(out.iterdir())


@pytest.mark.parametrize("kind", ["field", "tlog"])
def test_the_import_functions_refuse_a_directory_as_the_log(tmp_path, kind):
    """``import_tlog`` and ``write_field_log``, called from Python, refuse a directory at
    the log's path as the CLI does, and leave nothing in it."""
    from hil_service.offline.field.grid import resample
    from hil_service.offline.field.write import write_field_log
    from hil_service.offline.tlog_import import import_tlog
    from protocols.profiles import load_profile

    out = tmp_path / "logs"
    out.mkdir()
    with pytest.raises(IsADirectoryError, match=r"is a directory: give the path of the \.mcap"):
        if kind == "tlog":
            import_tlog(_tlog(tmp_path, tlog_bytes()[0]), out, load_profile("glider"))
        else:
            data = read_field([SEA])
            write_field_log(data, resample(data), out)
    assert not any(out.iterdir())


def test_a_vehicle_without_frames_is_an_error_listing_the_vehicles(tmp_path, capsys):
    log = tmp_path / "t.mcap"
    code, _, err = _import(
        capsys, str(_tlog(tmp_path, tlog_bytes()[0])), "-o", str(log), "--vehicle", "77"
    )
    assert code == 2
    assert "dive.tlog: no frame from vehicle 77 (the autopilots heard: 1;" in err
    assert not log.exists()


def test_two_tlogs_are_refused_as_one_file_at_a_time(tmp_path, capsys):
    data = tlog_bytes()[0]
    first, second = _tlog(tmp_path, data, "a.tlog"), _tlog(tmp_path, data, "b.tlog")
    code, _, err = _import(capsys, str(first), str(second), "-o", str(tmp_path / "t.mcap"))
    assert code == 2 and "a tlog import takes one file, got 2" in err


def test_a_pipe_given_as_field_data_is_named_for_what_it_is(tmp_path, capsys):
    """A named pipe (or `<(zcat …)`, a device) is not a file the import can read twice;
    the error says so instead of "no such file"."""
    import os

    pipe = tmp_path / "dives.csv"
    os.mkfifo(pipe)
    argv = ["import", str(pipe), "--mapping", str(MAPPING), "-o", str(tmp_path / "x.mcap")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{pipe}: not a regular file (a pipe or a device: save it to a file)" in err
    assert main(["import", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "y.mcap")]) == 2
    assert "missing.csv: no such file or directory" in capsys.readouterr().err


def test_a_mapping_given_for_a_glider_s_own_format_is_refused_not_ignored(tmp_path, capsys):
    """A ``--mapping`` names the columns of a CSV/Parquet file; a SeaExplorer's files are read
    through their own variables, so a mapping given with them would be silently unused."""
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    log = tmp_path / "o.mcap"
    code, _, err = _import(capsys, str(SEA / DIVE), "--mapping", str(mapping), "-o", str(log))
    assert code == 2
    assert "--mapping is for CSV/Parquet files; these are seaexplorer files" in err
    assert not log.exists()
