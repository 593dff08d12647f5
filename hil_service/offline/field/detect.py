"""Which format a set of paths is, and reading it: ``read_field``."""

from __future__ import annotations

from pathlib import Path

from hil_service.offline.field.mapped import read_mapped
from hil_service.offline.field.seaexplorer import is_seaexplorer, read_seaexplorer
from hil_service.offline.field.seaglider import is_seaglider, read_seaglider
from hil_service.offline.field.slocum import is_slocum, read_slocum
from hil_service.offline.field.table import FieldData, FieldError
from protocols.input_files import not_a_file

FORMATS = ("seaglider", "seaexplorer", "slocum", "csv")


def expand(paths: list[str | Path]) -> list[Path]:
    """Files given, a directory standing for the field files in it (sorted)."""
    files: list[Path] = []
    for given in paths:
        path = Path(given)
        if path.is_dir():
            inside = sorted(p for p in path.iterdir() if p.is_file() and guess(p) is not None)
            if not inside:
                raise FieldError(f"{path}: a directory without any field data file")
            files += inside
        else:
            problem = not_a_file(path, "file or directory")
            if problem:
                raise FieldError(problem)
            files.append(path)
    return files


def guess(path: Path) -> str | None:
    if is_seaglider(path):
        return "seaglider"
    if is_seaexplorer(path):
        return "seaexplorer"
    if is_slocum(path):
        return "slocum"
    if path.suffix.lower() in (".csv", ".parquet", ".txt"):
        return "csv"
    return None


def read_field(
    paths: list[str | Path],
    fmt: str | None = None,
    mapping: str | Path | None = None,
    cache_dir: str | Path | None = None,
) -> FieldData:
    files = expand(paths)
    if fmt is None:
        kinds = {guess(p) for p in files}
        if None in kinds:
            unknown = next(p for p in files if guess(p) is None)
            raise FieldError(f"{unknown}: not a known field format (give --format)")
        if len(kinds) != 1:
            raise FieldError(
                f"files of several formats given: {', '.join(sorted(map(str, kinds)))}"
            )
        fmt = str(next(iter(kinds)))
    if mapping is not None and fmt != "csv":
        raise FieldError(
            f"--mapping is for CSV/Parquet files; these are {fmt} files, read through their "
            "format's own variables (docs/field-data.md): leave it out, or give --format csv"
        )
    if fmt == "seaglider":
        return read_seaglider(files)
    if fmt == "seaexplorer":
        return read_seaexplorer(files)
    if fmt == "slocum":
        return read_slocum(files, cache_dir)
    if fmt == "csv":
        if mapping is None:
            raise FieldError(
                f"{files[0]}: a CSV/Parquet import needs --mapping (docs/field-data.md)"
            )
        return read_mapped(files, mapping)
    raise FieldError(f"unknown format {fmt!r} (one of {', '.join(FORMATS)})")
