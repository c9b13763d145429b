"""The house rules, checked from the source: imports run only downward through the layers (README's picture), no
two modules import each other (directly or around a loop), and every command-line option is documented."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from pidg.config_tools import unbounded_numeric_options, undocumented_options
from pidg.training.config import TrainConfig

PACKAGE = Path(__file__).resolve().parents[1] / "pidg"

#: Floors from the ground up; a room may import its own modules and any room on a lower floor, never a room on
#: its own floor or above.
FLOORS: list[set[str]] = [
    # settings that must precede torch (the package's face imports them first); errors; numba float32 helpers
    {"pidg._env", "pidg.errors", "pidg.kernel_math"},
    {"pidg", "pidg.config_tools", "pidg.checkpoint", "pidg.render", "pidg.metrics"},
    {"pidg.device"},  # what runs where: checks the render's backends against the device
    {"pidg.data"},
    {"pidg.models"},
    {"pidg.physics", "pidg.flow"},
    {"pidg.training", "pidg.evaluation", "pidg.export", "pidg.scenes"},
    {"pidg.pipeline"},
    {"pidg.bench"},
    {"pidg.report"},
    {"pidg.viewer"},
    {"pidg.cli"},
]


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _imports(path: Path, known: set[str]) -> set[str]:
    """The pidg modules a file imports anywhere in it (function-level imports too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{alias.name}" for alias in node.names] + [node.module]
            names = [n for n in names if n in known] or [node.module]
        for name in names:
            while name not in known and "." in name:
                name = name.rsplit(".", 1)[0]
            if name.startswith("pidg") and name in known:
                found.add(name)
    return found


def _room(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])


def _floor(room: str) -> int:
    for level, rooms in enumerate(FLOORS):
        if room in rooms:
            return level
    raise AssertionError(f"{room} is on no floor of the picture: add it to FLOORS (and to README's architecture)")


def test_imports_only_run_downward():
    modules = _modules()
    known = set(modules)
    upward = []
    for name, path in modules.items():
        here = _room(name)
        for target in _imports(path, known):
            there = _room(target)
            if there != here and _floor(there) >= _floor(here) and there != "pidg":
                upward.append(f"{name} -> {target}")
    assert not upward, "imports that run sideways or up a floor:\n" + "\n".join(sorted(upward))


def test_no_module_cycles():
    modules = _modules()
    known = set(modules)
    graph = {name: _imports(path, known) - {name} for name, path in modules.items()}
    # a package's face importing its own modules is not a cycle; a module importing its package's face is
    graph = {name: {t for t in targets if not (name == _room(name) and t.startswith(name + "."))} for name, targets in graph.items()}
    state: dict[str, int] = {}
    cycles = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in graph[node]:
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(path[path.index(nxt):] + [nxt]) if nxt in path else f"{node} -> {nxt}")
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in graph:
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


@pytest.mark.parametrize("room", sorted({_room(m) for m in _modules()}))
def test_every_room_is_on_a_floor(room):
    _floor(room)


def test_every_option_has_help_and_every_number_a_range():
    assert undocumented_options(TrainConfig) == []
    assert unbounded_numeric_options(TrainConfig) == []
