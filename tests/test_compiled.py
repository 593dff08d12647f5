"""The mypyc-compiled modules compute exactly what their Python sources compute.

The fixtures were recorded and are replayed (``test_replay``) by whatever this install runs;
here the same checks run with ``GLIDER_HIL_INTERPRETED=1`` in a child process, so both
builds are held to the same bits.
"""

from __future__ import annotations

import dataclasses
import importlib.machinery
import os
import subprocess
import sys

import pytest

from hil_service.pipeline import Decision
from hil_service.umodel.inverse import InverseResult, ShapedCommand
from protocols import compiled
from protocols.samples import BallastCommand
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


def _tree(root, modules: dict[str, float]) -> None:
    """Sources and compiled modules under ``root``: relative path → mtime."""
    for relative, mtime in modules.items():
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("")
        os.utime(path, (mtime, mtime))


def test_make_build_deletes_compiled_modules_that_are_not_on_the_list(tmp_path):
    """A compiled module whose source is gone, or that left HOT_PATH while its source stays
    (it would run in place of that source), is deleted; HOT_PATH's are kept, and a stale
    one is reported for compiling."""
    ext = importlib.machinery.EXTENSION_SUFFIXES[0]
    hot = compiled.HOT_PATH[0].replace(".", "/")
    _tree(tmp_path, {
        f"{hot}.py": 200.0, f"{hot}{ext}": 100.0,  # stale: older than its source
        f"hil_service/assembler{ext}": 100.0,  # its source is gone
        "hil_service/config.py": 100.0, f"hil_service/config{ext}": 200.0,  # not on the list
        f"plant_emulator/sub/x{ext}": 100.0,
    })  # fmt: skip
    orphans = {p.relative_to(tmp_path).as_posix() for p in compiled.orphan_binaries(tmp_path)}
    assert orphans == {
        f"hil_service/assembler{ext}",
        f"hil_service/config{ext}",
        f"plant_emulator/sub/x{ext}",
    }
    assert compiled.stale_modules(tmp_path) == [compiled.HOT_PATH[0]]
    out = run_child([str(ROOT / "protocols" / "compiled.py"), str(tmp_path)], interpreted=True)
    assert out.returncode == 1  # something to compile
    assert out.stdout.count("removed ") == 3
    assert compiled.orphan_binaries(tmp_path) == []
    assert (tmp_path / f"{hot}{ext}").is_file() and (tmp_path / "hil_service/config.py").is_file()


def test_a_checkout_built_from_its_sources_has_no_orphan():
    assert compiled.orphan_binaries(ROOT) == []


@pytest.mark.parametrize(
    "cls, args",
    [
        (Decision, (None, None, "blocked")),
        (BallastCommand, (0.25, -0.5)),
        (InverseResult, (0.5, "newton", 3, 1e-9, False)),
        (ShapedCommand, (0.5, True, False)),
    ],
)
def test_a_written_out_dataclass_init_sets_exactly_its_fields(cls, args):
    """The frozen dataclasses whose ``__init__`` is written out (docs/compiled.md) take
    their fields in declared order and set every one of them: a field added to the class
    and not to its ``__init__`` fails here, not in ``eq``, ``replace`` or a later read."""
    names = [f.name for f in dataclasses.fields(cls)]
    made = cls(*args)
    assert [getattr(made, name) for name in names] == list(args)
    assert made == cls(*args) and hash(made) == hash(cls(*args))
    assert dataclasses.replace(made) == made
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(made, names[0], args[0])
