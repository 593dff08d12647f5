"""Shared by the tests of flags refused before a verb runs: argparse's exit, and a stand-in
for the verb's run function that fails the test if a bad flag got through."""

from __future__ import annotations

from typing import Any

import pytest

from hil_service.cli import main


def must_not_run(*_: Any, **__: Any) -> Any:
    raise AssertionError("ran although a flag is bad")


def refused_by_argparse(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """``glider-hil ARGV`` exits 2 from argparse, without a traceback; its stderr."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, err
    assert "Traceback" not in err
    return err


def refused_line(capsys: pytest.CaptureFixture[str], verb: str, *argv: str) -> str:
    """``glider-hil VERB ARGV`` in this process exits 2 with one line on stderr; the line."""
    code = main([verb, *argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    assert line.startswith(f"glider-hil {verb}: ")
    return line
