"""Field data into our MCAP layout: real Seaglider and SeaExplorer slices, bad files, CSV."""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hil_service.cli.processes import run_verb
from hil_service.mcap.reader import LogReader
from hil_service.offline.field import FieldError, read_field
from hil_service.offline.field.grid import resample
from hil_service.offline.field.mapped import load_mapping
from hil_service.offline.field.write import write_field_log
from tests.markdown_tables import misshapen_tables

DATA = Path(__file__).parent / "data" / "field"
SG = DATA / "seaglider-sg542"
SEA = DATA / "seaexplorer-sea035"

MAPPING = """\
[file]
delimiter = ","

[time]
column = "time_s"
unit = "s"

[pressure]
column = "p_dbar"
unit = "dbar"

[pitch]
column = "pitch_deg"
unit = "deg"

[buoyancy]
column = "vbd"
unit = "cc"
full_scale = 500

[pitch_input]
column = "mass"
unit = "mm"
centre = 60
full_scale = 50

[dive]
column = "dive"
"""


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return run_verb(*args, timeout=120)


def test_seaglider_dives_read_in_order_with_si_units() -> None:
    data = read_field([SG])
    assert data.format == "seaglider" and data.vehicle == "SG542"
    assert sorted(set(data.dive.tolist())) == [304, 305, 306]
    assert np.all(np.diff(data.t) > 0)
    assert 900 < data.depth.max() < 1100  # m, from eng_depth in cm
    assert np.abs(data.pitch).max() < np.pi / 2  # rad
    assert data.issues.nan_rows == 0 and data.issues.out_of_order == 0


def test_seaglider_grid_keeps_surface_intervals_as_gaps() -> None:
    data = read_field(sorted(SG.glob("*.nc"), reverse=True))  # given out of order
    grid = resample(data, 10.0)
    assert [s.dive for s in grid.segments] == [304, 305, 306]
    assert grid.used_fraction >= 0.95
    assert grid.raw_used == grid.raw_in_dive == data.size
    for a, b in zip(grid.segments, grid.segments[1:], strict=False):
        last = grid.t[a.stop - 1]
        assert grid.t[b.start] - last > 60.0  # the surface interval is not filled in


def test_seaexplorer_surface_rows_counted_not_identified(tmp_path: Path) -> None:
    # One file gzipped, as a .gli.raw.N may be sent
    shutil.copy(SEA / "sea035.12.gli.sub.36", tmp_path)
    shutil.copy(SEA / "sea035.12.gli.sub.37", tmp_path)
    raw = (SEA / "sea035.12.gli.sub.38").read_bytes()
    (tmp_path / "sea035.12.gli.sub.38.gz").write_bytes(gzip.compress(raw))
    data = read_field([tmp_path])
    assert data.format == "seaexplorer" and data.vehicle == "SEA035"
    assert sorted(set(data.dive.tolist())) == [36, 37, 38]
    assert data.issues.surface_rows == int(np.count_nonzero(~data.in_dive)) > 0
    plain = read_field([SEA])
    assert plain.size == data.size


def test_import_writes_the_project_layout_and_replays(tmp_path: Path) -> None:
    out = tmp_path / "sg.mcap"
    result = _cli("import", str(SG), "-o", str(out), "--period", "10", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)["import"]
    assert report["grid"]["used_fraction"] >= 0.95
    reader = LogReader(out)
    topics = {m.topic for m in reader.messages()}
    assert {"mavlink/raw/in", "glider/1/telemetry", "mavlink/json/in/ATTITUDE"} <= topics
    config = reader.config()
    assert config["source"]["kind"] == "field import"
    conversions = {c["quantity"]: c for c in config["field"]["conversions"]}
    assert conversions["depth"]["unit"] == "cm" and conversions["depth"]["scale"] == 0.01
    assert reader.report.channels["glider/1/telemetry"]["schema"] == "glider-hil.telemetry"
    replay = _cli("replay", "--fast", "--json", str(out))
    assert replay.returncode == 0, replay.stderr
    identifier = json.loads(replay.stdout)["identifier"]["1"]["depth"]
    grid_samples = report["grid"]["grid_samples"]
    # Only each segment's history refill is skipped: no period change taken for a gap.
    assert identifier["samples"] >= 0.95 * grid_samples


def test_report_on_a_field_import_scores_held_out_dives(tmp_path: Path) -> None:
    out = tmp_path / "sg.mcap"
    assert _cli("import", str(SG), "-o", str(out), "--period", "10").returncode == 0
    result = _cli("report", str(out), "-o", str(tmp_path / "report"))
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "report" / "report.md").read_text()
    assert "## Field identification (seaglider SG542)" in text
    assert "steady-glide" in text and "rls-arx" in text and "persistence" in text
    assert "| glide-u |" in text and "glide-u (buoyancy input and measured pitch)" in text
    assert misshapen_tables(text) == []
    assert "fit % dive 306" in text and "excited" in text
    assert (tmp_path / "report" / "field_depth_steady-glide.png").stat().st_size > 10_000


def test_truncated_netcdf_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "p5420399.nc"
    bad.write_bytes((SG / "p5420304.nc").read_bytes()[:3000])
    with pytest.raises(FieldError, match=r"p5420399\.nc: not a readable netCDF3 file"):
        read_field([bad])
    result = _cli("import", str(bad), "-o", str(tmp_path / "x.mcap"))
    assert result.returncode == 2 and "p5420399.nc" in result.stderr


def _csv(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def _rows() -> list[str]:
    rows = []
    for dive in (1, 2):
        for k in range(60):
            t = dive * 10_000 + 10 * k
            depth = 0.2 * min(k, 60 - k) * 10  # down then up
            rows.append(
                f"{t},{depth:.2f},{-20 if k < 30 else 20},{-200 if k < 30 else 200},50,{dive}"
            )
    return rows


def test_csv_with_a_mapping_messy_rows_counted(tmp_path: Path) -> None:
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    rows = _rows()
    rows.insert(10, rows[9])  # a repeated timestamp
    rows[20], rows[21] = rows[21], rows[20]  # out of order
    rows.insert(30, "10295,nan,nan,nan,50,1")  # a NaN row
    rows.insert(40, "10395,abc,1,1,50,1")  # unparsable
    header = "time_s,p_dbar,pitch_deg,vbd,mass,dive"
    first = _csv(tmp_path / "a.csv", header, rows[:61])
    second = _csv(
        tmp_path / "b.csv",
        "time_s,p_dbar,pitch_deg,mass,dive",
        [",".join(r.split(",")[:3] + r.split(",")[4:]) for r in rows[61:]],
    )  # b.csv lacks the buoyancy column
    data = read_field([first, second], "csv", mapping)
    issues = data.issues
    assert issues.repeated_time == 1 and issues.out_of_order == 1
    assert issues.nan_rows == 1 and issues.unparsable_rows == 1
    assert issues.missing_columns == {str(second): ["vbd"]}
    assert np.all(np.diff(data.t) > 0)
    assert data.depth.max() == pytest.approx(60 * 1e4 / (1025 * 9.80665), rel=1e-3)


def test_csv_missing_required_column_names_file_and_line(tmp_path: Path) -> None:
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    bad = _csv(tmp_path / "bad.csv", "time_s,pressure,pitch_deg,vbd,mass", ["1,2,3,4,5"])
    with pytest.raises(FieldError, match=r"bad\.csv:1: no column 'p_dbar' .*map\.toml:9"):
        read_field([bad], "csv", mapping)


def test_mapping_typo_names_the_line(tmp_path: Path) -> None:
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING.replace('unit = "deg"', 'unti = "deg"'))
    with pytest.raises(FieldError, match=r"map\.toml:14: unknown key 'unti' in \[pitch\]"):
        load_mapping(mapping)
    mapping.write_text(MAPPING.replace('unit = "dbar"', 'unit = "psi"'))
    with pytest.raises(FieldError, match=r"map\.toml:10: unit 'psi' of \[pressure\]"):
        load_mapping(mapping)


def _dbdreader_data() -> Path:
    dbdreader = pytest.importorskip("dbdreader")
    return Path(dbdreader.__file__).parent / "data"


def test_slocum_file_with_its_own_sensor_list(tmp_path: Path) -> None:
    data_dir = _dbdreader_data()
    mbd = data_dir / "ammonite-2008-028-01-000.mbd"
    data = read_field([mbd], cache_dir=tmp_path)
    assert data.format == "slocum" and data.size > 100
    assert data.depth.max() > 5.0
    assert any("get_sync" in note for note in data.issues.notes)
    grid = resample(data)
    out = write_field_log(data, grid, tmp_path / "slocum.mcap")
    assert out.samples == grid.size > 0


def test_slocum_missing_cache_names_the_file_it_needs(tmp_path: Path) -> None:
    data_dir = _dbdreader_data()
    sbd = data_dir / "amadeus-2014-204-05-000.sbd"
    with pytest.raises(FieldError, match=r"sensor list 093bd5ed\.cac is not in --cache-dir"):
        read_field([sbd], cache_dir=tmp_path)
    with pytest.raises(FieldError, match="need --cache-dir"):
        read_field([sbd])


def test_docs_list_every_field_key_an_import_stores(tmp_path: Path) -> None:
    import re

    data = read_field([SEA])
    out = tmp_path / "sea.mcap"
    write_field_log(data, resample(data), out)
    reader = LogReader(out)
    for _ in reader.messages():
        pass
    stored = reader.config()
    text = (Path(__file__).parent.parent / "docs" / "mcap.md").read_text()
    rows = {
        line.split("|")[1].strip().strip("`"): line
        for line in text.splitlines()
        if line.startswith("| `") and "imported" not in line
    }
    assert {"source", "profile", "field"} <= set(rows) and set(stored) == {
        "source",
        "profile",
        "field",
    }
    documented = set(re.findall(r"`([a-z_0-9]+)`", rows["field"]))
    nested = {"issues", "lost", "scaling", "clipped", "inputs"}

    def keys(value: object) -> set[str]:
        found: set[str] = set()
        if isinstance(value, dict):
            for k, v in value.items():
                found.add(k)
                if k not in nested:
                    found |= keys(v)
        elif isinstance(value, list):
            for item in value:
                found |= keys(item)
        return found

    assert keys(stored["field"]) <= documented


def test_an_imported_tlog_report_gives_the_fit_it_replayed_with(tmp_path: Path, capsys) -> None:
    from hil_service.cli import main
    from tests.test_tlog_import import ardusub_dive_tlog

    tlog, log, out = tmp_path / "dive.tlog", tmp_path / "dive.mcap", tmp_path / "report"
    ardusub_dive_tlog(tlog, 1500)
    assert main(["import", str(tlog), "-o", str(log), "--profile", "ardusub"]) == 0
    assert main(["report", str(log), "-o", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "ran with the default pipeline settings" in text
    rows = [
        [c.strip() for c in line.strip("|").split("|")]
        for line in text.splitlines()
        if line.startswith("| 1 |")
    ]
    assert rows and all(float(cells[6]) == float(cells[6]) for cells in rows), text  # fit %


def test_samples_as_recorded_reach_the_identifier_through_period_changes(
    tmp_path: Path,
) -> None:
    """The service's step continuity learns a Seaglider's changes of sample period (a few
    samples skipped at each, not every sample after a change), so the samples as recorded
    reach the identifier; on the grid only each dive's history refill is skipped."""
    learnt = {}
    for name, extra in (("raw", ["--as-recorded"]), ("grid", ["--period", "10"])):
        out = tmp_path / f"{name}.mcap"
        assert _cli("import", str(SG), "-o", str(out), *extra).returncode == 0
        replay = _cli("replay", "--fast", "--json", str(out))
        identifier = json.loads(replay.stdout)["identifier"]["1"]["depth"]
        learnt[name] = identifier["samples"] / (identifier["samples"] + identifier["skipped"])
    assert learnt["raw"] > 0.9 and learnt["grid"] > 0.95, learnt


def test_csv_errors_name_the_file_s_own_line_past_comments(tmp_path: Path) -> None:
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    header = "time_s,p_dbar,pitch_deg,vbd,mass,dive"
    path = tmp_path / "c.csv"
    path.write_text(f"# logged by a shore station\n\n{header}\n1,2,3,4,5,1\n2,x,3,4,5,1\n")
    data = read_field([path], "csv", mapping)
    assert data.issues.unparsable_rows == 1
    assert f"{path}:5: unparsable row dropped" in data.issues.notes


def test_seaexplorer_file_missing_an_input_column_is_counted(tmp_path: Path) -> None:
    lines = (SEA / "sea035.12.gli.sub.37").read_text().splitlines()
    header = lines[0].split(";")
    drop = [header.index("BallastPos"), header.index("BallastCmd")]
    cut = [";".join(c for i, c in enumerate(line.split(";")) if i not in drop) for line in lines]
    (tmp_path / "sea035.12.gli.sub.37").write_text("\n".join(cut) + "\n")
    shutil.copy(SEA / "sea035.12.gli.sub.38", tmp_path)
    data = read_field([tmp_path])
    assert data.issues.missing_columns == {str(tmp_path / "sea035.12.gli.sub.37"): ["BallastPos"]}
    assert np.isnan(data.buoyancy[data.dive == 37]).all()
    grid = resample(data)
    assert grid.lost["no input value yet"] == int(
        np.count_nonzero(data.in_dive & (data.dive == 37))
    )
    assert {s.dive for s in grid.segments} == {38}
