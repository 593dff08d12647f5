"""The notes of a field import (a row dropped, times before 1980, a file cut short) reach
the user after the import too: ``report`` lists them under "Import notes" in report.md (the
first ``MAX_NOTES``, then how many more), ``info`` prints them with the stored
configuration; an import without notes gets no list.

The input is a small CSV built from the rows of tests/test_field_messy_input.py.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from hil_service.cli import main
from hil_service.offline.field.report import MAX_NOTES, field_section
from hil_service.offline.field.table import EARLY_TIME_NOTE
from tests.test_field_import import MAPPING
from tests.test_field_messy_input import HEADER, _csv_rows

HEADING = "Import notes:"


def _import(tmp_path: Path, rows: list[str]) -> Path:
    """``glider-hil import`` of ``rows`` as a CSV with the test mapping: the log."""
    mapping = tmp_path / "map.toml"
    mapping.write_text(MAPPING)
    data = tmp_path / "a.csv"
    data.write_text("\n".join([HEADER, *rows]) + "\n")
    log = tmp_path / "a.mcap"
    argv = ["import", str(data), "--format", "csv", "--mapping", str(mapping), "-o", str(log)]
    assert main(argv) == 0
    return log


def _report(tmp_path: Path, log: Path) -> str:
    """``glider-hil report LOG``: its report.md."""
    out = tmp_path / "report"
    assert main(["report", str(log), "-o", str(out)]) == 0
    return (out / "report.md").read_text(encoding="utf-8")


def _in_seconds_read_as_ms(rows: list[str]) -> list[str]:
    """The rows with their times a thousandth of what they were: all in January 1970."""
    return [f"{float(r.split(',', 1)[0]) / 1000:.6f},{r.split(',', 1)[1]}" for r in rows]


@pytest.mark.timeout(60)
def test_report_and_info_show_the_notes_of_a_field_import(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rows = _in_seconds_read_as_ms(_csv_rows())
    rows[7] = rows[7].replace(",0,", ",x,", 1)  # line 9 of the file: no number
    log = _import(tmp_path, rows)
    dropped = f"{tmp_path / 'a.csv'}:9: unparsable row dropped"
    text = _report(tmp_path, log)
    section = text[text.index("## Field identification") :]
    listed = section[section.index(HEADING) :].split("\n\n")[1].splitlines()
    assert listed == [f"- {dropped}", f"- {EARLY_TIME_NOTE}"], section
    capsys.readouterr()
    assert main(["info", str(log)]) == 0
    out = capsys.readouterr().out
    assert dropped in out and EARLY_TIME_NOTE in out


@pytest.mark.timeout(60)
def test_a_field_import_without_notes_has_no_notes_list(tmp_path: Path) -> None:
    text = _report(tmp_path, _import(tmp_path, _csv_rows()))
    assert "## Field identification" in text and HEADING not in text


def test_the_report_lists_the_first_notes_and_counts_the_rest(tmp_path: Path) -> None:
    """An import notes each row it drops: the report lists ``MAX_NOTES`` and says how many
    more the log holds (a log imported as recorded: the section ends before identifying)."""
    notes = [f"a.csv:{k}: unparsable row dropped" for k in range(MAX_NOTES + 5)]
    field = {"format": "csv", "issues": {"notes": notes}, "grid": {"period_s": 0}}
    lines, _, _ = field_section("x.mcap", {"field": field}, tmp_path)
    at = lines.index(HEADING)
    listed = lines[at + 2 : at + 2 + MAX_NOTES + 1]
    assert listed[:-1] == [f"- {note}" for note in notes[:MAX_NOTES]]
    assert listed[-1] == "- ... and 5 more (all in `glider-hil info x.mcap`, field.issues.notes)"


def test_the_section_names_a_vehicleless_import_and_counts_rows_out_of_range(
    tmp_path: Path,
) -> None:
    """A CSV import stores no vehicle name: the heading is its format alone; and the rows
    dropped as out of range are counted beside the other dropped rows."""
    field = {"format": "csv", "issues": {"rows": 9, "out_of_range": 3}, "grid": {"period_s": 0}}
    lines, _, _ = field_section("x.mcap", {"field": field}, tmp_path)
    assert "## Field identification (csv)" in lines
    assert any("3 out of range" in line for line in lines), lines
