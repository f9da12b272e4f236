"""The layer rules of the package, checked on the source (no imports, no Blender).

core: NumPy/SciPy only, never bpy, never a layer above it; blender: adapters over core;
pipeline: orchestrates blender + core; ui and cli sit on top; testing is never imported by
shipped code. No import cycles between modules, and no module grows past the size a reader
can hold.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "facelab_addon"
MAX_LINES = 650

LAYER_OF = {"core": 0, "blender": 1, "pipeline": 2, "ui": 3, "cli": 3}


def _modules():
    for p in sorted(PKG.rglob("*.py")):
        rel = p.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        yield ".".join(parts), p, is_pkg


def _imports(name, path, is_pkg, top_level_only=False):
    """Absolute module names imported by one file (``from x import y`` counts x and x.y)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else ast.walk(tree)
    out = set()
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    for node in nodes:
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                stem = base[: len(base) - (node.level - 1)]
                mod = ".".join(stem + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
            out.update(f"{mod}.{a.name}" for a in node.names)
    return out


MODULES = {name: (path, is_pkg) for name, path, is_pkg in _modules()}


def _layer(module: str):
    parts = module.split(".")
    if len(parts) < 2 or parts[0] != "facelab_addon":
        return None
    return parts[1]


@pytest.mark.parametrize("name", sorted(m for m in MODULES if _layer(m) == "core"))
def test_core_imports_no_bpy_and_nothing_above_it(name):
    path, is_pkg = MODULES[name]
    bad = sorted(
        i for i in _imports(name, path, is_pkg)
        if i.split(".")[0] in ("bpy", "bmesh", "mathutils", "bpy_extras")
        or _layer(i) in ("blender", "pipeline", "ui", "cli", "testing")
    )
    assert not bad, f"{name} imports {bad}"


@pytest.mark.parametrize("name", sorted(m for m in MODULES if _layer(m) not in (None, "testing")))
def test_shipped_code_never_imports_testing(name):
    path, is_pkg = MODULES[name]
    bad = sorted(i for i in _imports(name, path, is_pkg) if _layer(i) == "testing")
    assert not bad, f"{name} imports test support {bad}"


@pytest.mark.parametrize("name", sorted(m for m in MODULES if _layer(m) in LAYER_OF))
def test_dependencies_point_down(name):
    path, is_pkg = MODULES[name]
    own = LAYER_OF[_layer(name)]
    bad = sorted(
        i for i in _imports(name, path, is_pkg)
        if _layer(i) in LAYER_OF and LAYER_OF[_layer(i)] > own
        and not (_layer(name) == "ui" and _layer(i) == "ui")
    )
    assert not bad, f"{name} (layer {_layer(name)}) imports a layer above it: {bad}"


@pytest.mark.parametrize("name", sorted(m for m in MODULES if _layer(m) == "ui"))
def test_ui_reaches_core_only_for_errors_and_pure_types(name):
    """Operators gather settings, call a pipeline and report; the math lives below them."""
    path, is_pkg = MODULES[name]
    allowed = ("facelab_addon.core.errors",)
    bad = sorted(
        i for i in _imports(name, path, is_pkg)
        if _layer(i) == "core" and not i.startswith(allowed) and i != "facelab_addon.core"
    )
    assert not bad, f"{name} imports core directly: {bad}"


def test_no_import_cycles():
    graph = {}
    for name, (path, is_pkg) in MODULES.items():
        graph[name] = sorted(i for i in _imports(name, path, is_pkg, top_level_only=True) if i in MODULES and i != name)
    state, stack = {}, []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in graph[n]:
            if state.get(m) == 1:
                cycle = stack[stack.index(m):] + [m]
                # a package importing its own submodule is not a cycle of concerns
                if not all(c.startswith(n + ".") or n.startswith(c + ".") for c in cycle if c != n):
                    raise AssertionError("import cycle: " + " -> ".join(cycle))
            elif m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in graph:
        if n not in state:
            visit(n)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_modules_stay_readable(name):
    path, _ = MODULES[name]
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_LINES, f"{path.relative_to(ROOT)} has {n} lines; split it by concern"
