"""No import cycle among the project's own modules.

The graph is read from the sources with ``ast`` (nothing is imported): every ``import`` and
``from … import`` anywhere in a module, at its top, inside a function or under
``TYPE_CHECKING``, that names a module of ``hil_service``, ``protocols`` or
``plant_emulator``. ``from package import name`` is an edge to ``package.name`` when that
is a module, else to the package's ``__init__``. A package's ``__init__`` importing its own
modules is an edge like any other; a module is not taken to depend on the packages that
contain it (Python runs them first, but they are not what the module asked for).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("hil_service", "protocols", "plant_emulator")


def _modules(root: Path, packages: tuple[str, ...]) -> dict[str, tuple[Path, bool]]:
    """Dotted module name → (source file, whether it is a package's ``__init__``)."""
    found: dict[str, tuple[Path, bool]] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts.pop()
            found[".".join(parts)] = (path, is_package)
    return found


def _known(name: str, modules: dict[str, tuple[Path, bool]]) -> str | None:
    """``name`` or its closest enclosing module that is one of ours."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def import_graph(root: Path, packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """Each module of ``packages`` under ``root`` → the modules of ``packages`` it imports."""
    modules = _modules(root, packages)
    graph: dict[str, set[str]] = {}
    for name, (path, is_package) in modules.items():
        here = name.split(".") if is_package else name.split(".")[:-1]
        edges: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    target = _known(alias.name, modules)
                    if target:
                        edges.add(target)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here[: len(here) - (node.level - 1)]
                    source = ".".join([*base, *([node.module] if node.module else [])])
                else:
                    source = node.module or ""
                for alias in node.names:
                    submodule = f"{source}.{alias.name}"
                    target = submodule if submodule in modules else _known(source, modules)
                    if target:
                        edges.add(target)
        edges.discard(name)
        graph[name] = edges
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative),
    each sorted; every import cycle lies inside one of them."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            advanced = False
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = len(index)
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(sorted(graph.get(succ, ())))))
                    advanced = True
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            if advanced:
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _describe(graph: dict[str, set[str]], component: list[str]) -> str:
    inside = set(component)
    return "; ".join(f"{m} -> {sorted(graph[m] & inside)}" for m in component)


def test_no_import_cycle_in_the_project() -> None:
    graph = import_graph(ROOT)
    assert len(graph) > 100  # the walk found the packages
    assert "hil_service.umodel.estimate" in graph["hil_service.umodel.models"]
    found = cycles(graph)
    assert found == [], "import cycles: " + " | ".join(_describe(graph, c) for c in found)


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


@pytest.mark.parametrize(
    "b_text",
    [
        "from .a import X\n",  # at the top
        "def f():\n    from pkg.a import X\n",  # inside a function
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\n",
        "import pkg.sub.c\n",  # through a third module, below
    ],
)
def test_the_check_sees_cycles_of_every_form(tmp_path: Path, b_text: str) -> None:
    _write(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/a.py": "from pkg.b import Y\nX = 1\n",
            "pkg/b.py": b_text + "Y = 2\n",
            "pkg/sub/__init__.py": "",
            "pkg/sub/c.py": "from ..a import X\n",
        },
    )
    graph = import_graph(tmp_path, ("pkg",))
    found = cycles(graph)
    assert len(found) == 1
    assert {"pkg.a", "pkg.b"} <= set(found[0])


def test_the_check_passes_a_tree_without_cycles(tmp_path: Path) -> None:
    _write(
        tmp_path,
        {
            "pkg/__init__.py": "from .a import X\nfrom .b import Y\n",
            "pkg/a.py": "import os\nX = 1\n",
            "pkg/b.py": "from pkg.a import X\nfrom pkg import a\nY = X\n",
        },
    )
    graph = import_graph(tmp_path, ("pkg",))
    assert graph["pkg.b"] == {"pkg.a"}
    assert graph["pkg"] == {"pkg.a", "pkg.b"}
    assert cycles(graph) == []
