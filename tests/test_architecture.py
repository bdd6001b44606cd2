"""The house's shape: imports run only downwards through the layers named in
``app/__init__.py``, and no module imports itself back through a cycle."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# layer of each top-level unit; a module may import its own layer and those below
LAYERS = {
    "app.config": 0, "app.errors": 0, "app.ratelimit": 0, "app.camera": 0,
    "app.perception": 1, "app.decision": 2, "app.flight": 3, "hardware": 4,
    "app.runtime": 5, "app.sim": 6, "app.tools": 7, "app.cli": 8,
}
ONLY_HERE = {"mavsdk": "hardware", "pyrealsense2": "hardware"}


def unit(module: str) -> str:
    """The layer unit a module belongs to: its package under app, or a base module."""
    parts = module.split(".")
    if parts[0] == "hardware":
        return "hardware"
    return ".".join(parts[:2])


def modules() -> dict[str, Path]:
    found = {}
    for base in ("app", "hardware"):
        for path in (ROOT / base).rglob("*.py"):
            rel = path.relative_to(ROOT).with_suffix("")
            name = ".".join(p for p in rel.parts if p != "__init__")
            found[name] = path
    return found


def imports(path: Path) -> list[tuple[str, int]]:
    """Every module imported, at module level or inside functions (lazy imports count)."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, node.lineno))
            out += [(f"{node.module}.{a.name}", node.lineno) for a in node.names]
    return out


def project_graph() -> dict[str, set[str]]:
    mods = modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        for imported, _ in imports(path):
            if imported in mods and imported != name:
                graph[name].add(imported)
    return graph


def upward_imports() -> list[str]:
    wrong = []
    for name, path in modules().items():
        if name == "app":
            continue  # the package's own __init__ (a docstring and the version)
        own = unit(name)
        assert own in LAYERS, f"{name}: in no layer (add its package to app/__init__.py and LAYERS)"
        for imported, line in imports(path):
            top = imported.split(".")[0]
            if top in ONLY_HERE and own != ONLY_HERE[top]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {top} (only {ONLY_HERE[top]} may)")
            if top not in ("app", "hardware") or imported in ("app", "hardware"):
                continue
            other = unit(imported)
            if other in LAYERS and LAYERS[other] > LAYERS[own]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {imported} "
                             f"(layer {LAYERS[other]} above {own}'s {LAYERS[own]})")
    return wrong


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    found: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                found.append(stack[stack.index(m):] + [m])
            elif m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)
    return found


def test_imports_run_only_downwards() -> None:
    assert upward_imports() == []


def test_no_import_cycles() -> None:
    assert cycles(project_graph()) == []


def test_the_check_catches_an_upward_import_and_a_cycle(tmp_path: Path) -> None:
    """The checks themselves can fail: a stage importing the runtime, and two modules
    importing each other."""
    assert unit("app.perception.detection") == "app.perception" and unit("hardware.px4") == "hardware"
    assert LAYERS[unit("app.runtime.process")] > LAYERS[unit("app.perception.detection")]
    assert cycles({"a": {"b"}, "b": {"a"}}) == [["a", "b", "a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    bad = tmp_path / "stage.py"
    bad.write_text("import numpy\n\ndef f():\n    from app.runtime.process import fly\n")
    assert ("app.runtime.process.fly", 4) in imports(bad)
