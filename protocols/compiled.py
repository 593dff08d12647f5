"""Which modules are compiled with mypyc, whether this process runs them compiled, and a
switch to run their Python sources instead.

``setup.py`` compiles ``HOT_PATH`` (the modules every MAVLink sample goes through) into one
native library. ``GLIDER_HIL_INTERPRETED=1`` in the environment makes this process import
the ``.py`` sources of all of them, even where compiled modules are installed: for
debugging with Python tracebacks, and for comparing the two (``tests/test_compiled.py``,
``benchmarks/bench_service.py``). All of them or none: compiled modules call each other's
native classes directly, so a mix would not work.

This module lives in ``protocols`` because every entry point imports that package first
(``protocols/__init__.py`` and ``hil_service/__init__.py`` both call ``apply_choice``).

``HOT_PATH`` names the ``hil_service`` modules by string, and must: ``setup.py`` reads the
list to hand mypyc its source paths without importing the package it is about to compile,
and the source finder has to recognise a module by name *before* it is imported (importing
it to ask would load the compiled one). ``tests/test_compiled.py`` imports every name (a
renamed module fails it).
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

ENV_INTERPRETED = "GLIDER_HIL_INTERPRETED"  # at run time: the Python sources
ENV_PURE_PYTHON = "GLIDER_HIL_PURE_PYTHON"  # at install time: compile nothing (setup.py)

#: Every module a MAVLink sample goes through whose own Python code is a noticeable share
#: of the time (the model's multi-step map, the predictive inverse and the root solver are
#: the control step; the RLS is the dynamic model's update).
HOT_PATH: tuple[str, ...] = (
    "hil_service.umodel.box_qp",
    "hil_service.umodel.dynamics",
    "hil_service.umodel.estimate",
    "hil_service.umodel.finite",
    "hil_service.umodel.dead_zone",
    "hil_service.umodel.guards",
    "hil_service.umodel.horizon",
    "hil_service.umodel.inverse",
    "hil_service.umodel.models",
    "hil_service.umodel.nlms",
    "hil_service.umodel.predictive",
    "hil_service.umodel.rbf",
    "hil_service.umodel.reproducible",
    "hil_service.umodel.residual_forecast",
    "hil_service.umodel.rls",
    "hil_service.sources.lockstep",
    "hil_service.sources.lockstep_assembler",
    "hil_service.sources.lockstep_responder",
    "hil_service.listeners.notifier",
    "hil_service.link_stats",
    "hil_service.mcap.writer",
    "hil_service.mcap.recorder",
    "hil_service.umodel.scoring",
    "hil_service.umodel.supervisor",
    "hil_service.service",
    "hil_service.pipeline",
    "protocols.frame_decoder",
    "protocols.frame_encoder",
    "protocols.mapping",
    "protocols.mavlink_io",
    "protocols.mavlink_json",
    "protocols.payload_json",
    "protocols.readings",
    "protocols.samples",
)


def _source(name: str) -> str:
    return name.replace(".", "/") + ".py"


def source_paths() -> list[str]:
    """HOT_PATH as the source files ``mypycify`` takes, relative to the project root."""
    return [_source(name) for name in HOT_PATH]


def flag(variable: str) -> bool:
    """An environment switch is on when set to anything but "" or "0"."""
    return os.environ.get(variable, "") not in ("", "0")


def child_environment(interpreted: bool) -> dict[str, str]:
    """This process's environment for a child that runs the compiled modules where they are
    built (``interpreted`` False) or their Python sources (True)."""
    env = {k: v for k, v in os.environ.items() if k != ENV_INTERPRETED}
    if interpreted:
        env[ENV_INTERPRETED] = "1"
    return env


class _SourceFinder:
    """Finds the ``.py`` source of a HOT_PATH module before the extension module is found."""

    def find_spec(
        self, name: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if name not in HOT_PATH or path is None:
            return None
        leaf = name.rpartition(".")[2] + ".py"
        for directory in path:
            candidate = Path(directory) / leaf
            if candidate.is_file():
                return importlib.util.spec_from_file_location(name, candidate)
        return None


def apply_choice() -> None:
    """Install the source finder when ``GLIDER_HIL_INTERPRETED`` asks for it (idempotent)."""
    if not flag(ENV_INTERPRETED):
        return
    if any(isinstance(finder, _SourceFinder) for finder in sys.meta_path):
        return
    sys.meta_path.insert(0, _SourceFinder())


def module_kinds() -> dict[str, str]:
    """Each HOT_PATH module as this process runs it: "compiled" or "interpreted"."""
    kinds = {}
    for name in HOT_PATH:
        module = importlib.import_module(name)
        origin = getattr(module, "__file__", "") or ""
        kinds[name] = "interpreted" if origin.endswith(".py") else "compiled"
    return kinds


def _build_state(root: Path, name: str) -> str:
    """ "missing", "stale" (a compiled module older than its source) or "built"."""
    source = root / _source(name)
    suffixes = importlib.machinery.EXTENSION_SUFFIXES
    binaries = [b for b in (source.with_suffix(s) for s in suffixes) if b.is_file()]
    if not binaries:
        return "missing"
    if any(b.stat().st_mtime < source.stat().st_mtime for b in binaries):
        return "stale"
    return "built"


def stale_modules(root: Path) -> list[str]:
    """Compiled modules under ``root`` older than their source (an editable install whose
    sources changed after the build: run ``make build``)."""
    return [name for name in HOT_PATH if _build_state(root, name) == "stale"]


def unbuilt_modules(root: Path) -> list[str]:
    """HOT_PATH modules under ``root`` with no compiled module, or a stale one."""
    return [name for name in HOT_PATH if _build_state(root, name) != "built"]


#: The packages whose modules may be compiled: where ``orphan_binaries`` looks.
PACKAGES: tuple[str, ...] = ("hil_service", "protocols", "plant_emulator")


def orphan_binaries(root: Path) -> list[Path]:
    """Compiled modules under ``root``'s packages that are not a HOT_PATH module: their
    source is gone, or the module left the list. Python imports an extension module before
    the ``.py`` beside it, and the stale check only looks at HOT_PATH, so such a file would
    silently run in place of an existing source; ``make build`` deletes them."""
    wanted = {root / _source(name) for name in HOT_PATH}
    suffixes = sorted(importlib.machinery.EXTENSION_SUFFIXES, key=len, reverse=True)
    found = []
    for package in PACKAGES:
        for binary in sorted((root / package).rglob("*.*")):
            suffix = next((s for s in suffixes if binary.name.endswith(s)), None)
            if suffix is None or not binary.is_file():
                continue
            if binary.with_name(binary.name[: -len(suffix)] + ".py") not in wanted:
                found.append(binary)
    return found


def summary() -> str:
    """ "compiled", "interpreted" or "mixed (…)", for reports and benchmark output."""
    kinds = module_kinds()
    values = set(kinds.values())
    if len(values) == 1:
        return values.pop()
    return "mixed (" + ", ".join(f"{k}: {v}" for k, v in kinds.items()) + ")"


if __name__ == "__main__":
    # `python protocols/compiled.py ROOT`: delete the orphan compiled modules under ROOT,
    # then exit 1 when a module needs compiling (``make build`` asks before compiling;
    # after an install that compiled them all there is nothing to do).
    root = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    for orphan in orphan_binaries(root):
        orphan.unlink()
        print(f"removed {orphan} (no HOT_PATH module of that name)")
    missing = [] if flag(ENV_PURE_PYTHON) else unbuilt_modules(root)
    if missing:
        print("to compile: " + ", ".join(missing))
    sys.exit(1 if missing else 0)
