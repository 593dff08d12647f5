"""Where an imported log goes: one file, written whole or not at all."""

from __future__ import annotations

import os
from pathlib import Path


def refuse_directory(output: Path) -> None:
    """A directory at the log's path is refused before any work: moving the written file
    into it would leave the log where nobody looks for it."""
    if output.is_dir():
        raise IsADirectoryError(
            f"{output} is a directory: give the path of the .mcap file to write"
        )


def move_into_place(written: str | Path, output: Path) -> None:
    """The finished log to ``output`` in one rename (the scratch directory it was written
    in lies beside ``output``, on the same file system), replacing an older file there."""
    os.replace(written, output)
