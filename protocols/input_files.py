"""What is wrong with a file a flag names (a key, a configuration, a mapping, a log), said
before the file is opened.

A named pipe given for one (``<(...)``, a FIFO) would block the open until a writer came,
and Zenoh's reader holds the interpreter while it waits, so not even SIGTERM ends the
process; a directory would reach the reader as an error with a source path in it.
"""

from __future__ import annotations

import stat
from pathlib import Path

__all__ = ["not_a_file"]


def not_a_file(path: str | Path, what: str, directory_hint: str = "") -> str:
    """Why ``path`` cannot be read as ``what`` ("log", "signing key", …), or '' when it is a
    regular file (whether it can be read, and what it holds, is the reader's to say);
    ``directory_hint``: what to give instead of a directory."""
    try:
        mode = Path(path).stat().st_mode
    except FileNotFoundError:
        return f"{path}: no such {what}"
    except OSError as error:
        return f"{path}: {error.strerror or error}"
    if stat.S_ISDIR(mode):
        hint = f" ({directory_hint})" if directory_hint else ""
        return f"{path}: a directory, not a {what}{hint}"
    if not stat.S_ISREG(mode):
        return f"{path}: not a regular file (a pipe or a device: save it to a file)"
    return ""
