"""The package's import graph: no circle, no import that climbs a layer (every import is read,
those inside functions and under ``TYPE_CHECKING`` included)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mfp_mapper"

LAYERS = {
    "config": 0,
    "core": 1,
    "mapio": 2,
    "sensing": 2,
    "sources": 3,
    "mapping": 4,
    "outputs": 5,
    "ros": 6,
    "cli": 7,
}
"""Rank of each subpackage: a module may import its own subpackage and lower ranks only
(two subpackages of one rank do not import each other). The package's ``__init__`` and the
``mfp_mapper.node`` entry point stand above them all."""

FORBIDDEN = {"sensing": {"mfp_mapper.core.mapper"}}
"""Imports a subpackage may not make although their rank allows them (sensing turns clouds
into placed rays; only the mapping loop puts them into a Mapper)."""


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The modules of mfp_mapper that ``path`` imports (a name imported from a package is the
    submodule when there is one)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("mfp_mapper"))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if not node.module.startswith("mfp_mapper"):
                continue
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.add(sub if sub in modules else node.module)
    return found & modules


def _graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    modules = set(paths)
    return {name: _imports(path, modules) - {name} for name, path in paths.items()}


def _layer(module: str) -> tuple[str, int]:
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in LAYERS:
        return parts[1] if len(parts) > 1 else "", len(LAYERS) + 1
    return parts[1], LAYERS[parts[1]]


def test_every_module_has_a_layer() -> None:
    loose = sorted(m for m in _graph() if _layer(m)[1] > len(LAYERS) and m.count(".") > 1)
    assert not loose, f"modules outside the layers: {loose}"


def test_no_import_climbs_a_layer() -> None:
    upward = []
    for module, imported in sorted(_graph().items()):
        package, rank = _layer(module)
        for target in sorted(imported):
            target_package, target_rank = _layer(target)
            if target_package == package:
                continue
            if target_rank >= rank or target in FORBIDDEN.get(package, set()):
                upward.append(f"{module} -> {target}")
    assert not upward, "imports that climb or cross a layer:\n" + "\n".join(upward)


def test_no_import_circle() -> None:
    graph = _graph()
    state: dict[str, int] = {}
    circles: list[list[str]] = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                circles.append([*stack[stack.index(nxt) :], nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    assert not circles, "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_each_layer_is_a_package(package: str) -> None:
    assert (PACKAGE / package / "__init__.py").is_file()


STAGES = ("parse_scan", "add_no_return_rays", "pose_deadline", "place_scan")
"""The scan pipeline's stages (``sensing.pipeline``): only the one loop chains them."""


def test_only_the_loop_runs_the_pipeline_stages() -> None:
    callers = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "pipeline.py" or path == PACKAGE / "mapping" / "loop.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            called = node.func if isinstance(node, ast.Call) else None
            name = (
                called.attr
                if isinstance(called, ast.Attribute)
                else called.id
                if isinstance(called, ast.Name)
                else None
            )
            if name in STAGES:
                callers.append(f"{_module_name(path)}: {name}")
    assert not callers, "pipeline stages called outside mapping.loop:\n" + "\n".join(callers)


READERS = {"mfp_mapper.sources.pose_files", "mfp_mapper.sources.scan_files"}
"""Modules that parse recordings' files: ``sources`` opens recordings, no one above it."""


def test_recordings_are_read_in_sources_only() -> None:
    """mapping/ takes opened recordings (``sources.opener``): it imports no bag reader
    (rosbags) and no pose- or scan-file parser."""
    found = []
    for path in sorted((PACKAGE / "mapping").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            found += [
                f"{_module_name(path)} -> {n}"
                for n in names
                if n.split(".")[0] == "rosbags" or n in READERS
            ]
    found += [f"{m} -> {t}" for m, ts in _graph().items() if ".mapping." in m for t in ts & READERS]
    assert not found, "recording readers imported in mapping/:\n" + "\n".join(sorted(set(found)))
