"""The shape of the Markdown tables the reports write: a table renders (GitHub, CommonMark's
table extension) only when its delimiter row has as many cells as its header, and a body
row with more cells loses the extra ones."""

from __future__ import annotations

import re

#: A cell boundary: a pipe not escaped as ``\|`` (a pipe inside a cell's text).
_BOUNDARY = re.compile(r"(?<!\\)\|")


def _cells(line: str) -> int:
    return len(_BOUNDARY.split(line.strip().strip("|")))


def misshapen_tables(text: str) -> list[str]:
    """Each table of ``text`` whose delimiter or body rows do not have its header's number
    of cells, as "line N: header H cells, row R cells"."""
    lines = text.splitlines()
    found: list[str] = []
    for i in range(len(lines) - 1):
        header, delimiter = lines[i], lines[i + 1]
        is_table = header.lstrip().startswith("|") and delimiter.lstrip().startswith("|---")
        if not is_table or (i > 0 and lines[i - 1].lstrip().startswith("|")):
            continue
        width = _cells(header)
        j = i + 1
        while j < len(lines) and lines[j].lstrip().startswith("|"):
            if _cells(lines[j]) != width:
                found.append(f"line {j + 1}: header {width} cells, row {_cells(lines[j])} cells")
            j += 1
    return found
