"""The mypyc-compiled modules compute exactly what their Python sources compute.

The fixtures were recorded and are replayed (``test_replay``) by whatever this install runs;
here the same checks run with ``GLIDER_HIL_INTERPRETED=1`` in a child process, so both
builds are held to the same bits.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from protocols import compiled
from tests.conftest import DATA, ROOT


def run_child(args: list[str], interpreted: bool) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, *args], cwd=ROOT, env=compiled.child_environment(interpreted),
        capture_output=True, text=True, timeout=240,
    )  # fmt: skip


def run_verb(*args: str, interpreted: bool) -> subprocess.CompletedProcess[str]:
    return run_child(["-m", "hil_service.cli", *args], interpreted)


def kinds_in_child(interpreted: bool) -> set[str]:
    code = "from protocols import compiled; print(*compiled.module_kinds().values())"
    out = run_child(["-c", code], interpreted)
    assert out.returncode == 0, out.stderr
    return set(out.stdout.split())


def test_the_switch_runs_every_hot_path_module_from_its_source():
    assert kinds_in_child(interpreted=True) == {"interpreted"}
    # Without the switch: the compiled modules where this checkout has them built (a
    # compiled install), else every source (a pure install); never a mix.
    built = not compiled.unbuilt_modules(ROOT)
    assert kinds_in_child(interpreted=False) == ({"compiled"} if built else {"interpreted"})


@pytest.mark.parametrize("scenario", ["disturbed", "nonlinear"])
def test_interpreted_sources_replay_the_fixtures_bit_for_bit(scenario):
    result = run_verb(
        "replay", str(DATA / f"{scenario}.mcap"), "--fast", "--check", interpreted=True
    )
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.skipif(
    compiled.summary() != "compiled", reason="this install runs the Python sources only"
)
def test_compiled_and_interpreted_experiments_print_the_same_figures():
    args = ("experiment", "--scenario", "nonlinear", "--channel", "depth", "--samples", "1500",
            "--seed", "4", "--json")  # fmt: skip
    native, source = run_verb(*args, interpreted=False), run_verb(*args, interpreted=True)
    assert native.returncode == source.returncode == 0, native.stderr + source.stderr
    assert native.stdout == source.stdout
    assert '"dynamic"' in native.stdout
