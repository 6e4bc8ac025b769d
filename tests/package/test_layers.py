"""The layers, read from the code's own import statements: dependencies point one way (service ->
inference runtime -> network; training and evaluation -> network), and no files import each other,
directly or in a loop."""

from __future__ import annotations

import ast
import tomllib
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# subpackage -> the subpackages it may import (everything else is a higher or a side layer)
MAY_IMPORT: dict[str, set[str]] = {
    "model": set(),
    "stereo_data": set(),
    "client": {"stereo_data"},  # the file formats (a point cloud's PLY)
    "inference": {"model", "stereo_data"},
    "evaluation": {"inference", "model", "stereo_data"},
    "training": {"evaluation", "inference", "model", "stereo_data"},
    "service": {"inference", "model", "stereo_data"},
    "cli": {"service", "training", "evaluation", "inference", "model", "stereo_data", "client"},
    "": {"inference", "model", "client"},  # crestereo_pp/__init__.py, the public API
}


def modules() -> dict[str, Path]:
    """Every module of the installed package, by its dotted name, from pyproject.toml's package-dir."""
    package_dir = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    found = {"crestereo_pp": REPO / package_dir["crestereo_pp"] / "__init__.py"}
    for name, folder in package_dir.items():
        if name == "crestereo_pp":
            continue
        for path in (REPO / folder).rglob("*.py"):
            parts = path.relative_to(REPO / folder).with_suffix("").parts
            found[".".join([name, *parts[: -1 if parts[-1] == "__init__" else None]])] = path
    return found


def imported(name: str, path: Path, known: dict[str, Path]) -> Iterator[str]:
    """The project modules that module `name` (at `path`) names in its import statements."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, *([node.module] if node.module else [])])
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        yield from (target for target in targets if target in known and target != name)


def import_graph() -> dict[str, set[str]]:
    known = modules()
    return {name: set(imported(name, path, known)) for name, path in known.items()}


def layer(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


def test_no_module_imports_one_from_a_higher_or_side_layer():
    wrong = sorted(
        f"{name} -> {target}"
        for name, targets in import_graph().items()
        for target in targets
        if layer(target) != layer(name) and layer(target) not in MAY_IMPORT[layer(name)]
    )
    assert wrong == []


def test_no_files_import_each_other_directly_or_in_a_loop():
    graph = import_graph()
    # Tarjan's strongly connected components: a component of two or more modules is a loop.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    loops: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in graph[module]:
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            component = []
            while (member := stack.pop()) != module:
                component.append(member)
            if component:
                loops.append(sorted([module, *component]))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    assert loops == []


def test_every_subpackage_has_its_layer():
    assert {layer(name) for name in modules()} <= set(MAY_IMPORT)
