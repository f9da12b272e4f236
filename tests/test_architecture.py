"""The layer rules of the package, checked on the source (no imports, no Blender).

core: NumPy/SciPy only, never bpy, never a layer above it; blender: adapters over core;
pipeline: orchestrates blender + core; ui and cli sit on top, and cli never imports ui;
testing is never imported by shipped code. No import cycles between modules (imports inside
function bodies count), no module takes an underscore name from another module, and no module
grows into a giant file.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "facelab_addon"
# a guard against giant files, not a split rule: split a module by concept, never to fit a count
MAX_LINES = 900

LAYER_OF = {"core": 0, "blender": 1, "pipeline": 2, "ui": 3, "cli": 3}


def _modules():
    for p in sorted(PKG.rglob("*.py")):
        rel = p.relative_to(ROOT).with_suffix("")
        parts = list(rel.parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        yield ".".join(parts), p, is_pkg


def _source_module(name, is_pkg, node):
    """The absolute module an ``ImportFrom`` node reads from (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    stem = base[: len(base) - (node.level - 1)]
    return ".".join(stem + ([node.module] if node.module else []))


def _imports(name, path, is_pkg):
    """Absolute module names imported anywhere in one file, function bodies included
    (``from x import y`` counts x and x.y; ``from pkg import submodule`` counts the submodule only)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            mod = _source_module(name, is_pkg, node)
            subs = {f"{mod}.{a.name}" for a in node.names}
            if not subs <= set(MODULES):
                out.add(mod)
            out.update(subs)
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


@pytest.mark.parametrize("name", sorted(m for m in MODULES if _layer(m) == "cli"))
def test_cli_never_imports_ui(name):
    """The CLI and the UI are siblings: what both need (the scene-to-settings readers) lives below."""
    path, is_pkg = MODULES[name]
    bad = sorted(i for i in _imports(name, path, is_pkg) if _layer(i) == "ui")
    assert not bad, f"{name} imports the UI {bad}"


def _private(name):
    return name.startswith("_") and not name.startswith("__")


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_private_names_across_modules(name):
    """A name another module needs is public in its owner (documented); an underscore name
    is the module's own business. Checks ``from x import _y`` and ``x._y`` on an imported
    package module."""
    path, is_pkg = MODULES[name]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    modules_bound, bad = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            mod = _source_module(name, is_pkg, node)
            for a in node.names:
                if f"{mod}.{a.name}" in MODULES:
                    modules_bound[a.asname or a.name] = f"{mod}.{a.name}"
                elif _layer(mod) and _private(a.name):
                    bad.append(f"from {mod} import {a.name}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name in MODULES and a.asname:
                    modules_bound[a.asname] = a.name
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in modules_bound and _private(node.attr)):
            bad.append(f"{modules_bound[node.value.id]}.{node.attr} (line {node.lineno})")
    assert not bad, f"{name} reaches into another module's private names: {sorted(set(bad))}"


def test_no_import_cycles():
    """No circle of modules, counting imports inside function bodies: a deferred import that
    closes a circle still ties the two modules together; move what both need to one owner."""
    graph = {}
    for name, (path, is_pkg) in MODULES.items():
        graph[name] = sorted(i for i in _imports(name, path, is_pkg) if i in MODULES and i != name)
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
    assert n <= MAX_LINES, f"{path.relative_to(ROOT)} has {n} lines; split it by concept"


#: Re-exports left in modules other work is changing; each entry goes when its callers import from the owner.
REEXPORTS_KNOWN: dict = {}


def _reexports(name, path, is_pkg):
    """Names ``name`` takes from another package module (top-level ``from x import y``, submodules left out)
    and hands on: listed in its ``__all__``, or never used in it. A package's ``__init__`` may present the
    public names of its own submodules (``core.lips.regressor.LipRegressor``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    listed = set()
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            listed = set(ast.literal_eval(node.value))
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    out = set()
    for node in tree.body:
        if not isinstance(node, ast.ImportFrom):
            continue
        mod = _source_module(name, is_pkg, node)
        if _layer(mod) is None and mod != "facelab_addon":
            continue
        if is_pkg and mod.startswith(name + "."):  # a package presents its own submodules' public names
            continue
        for a in node.names:
            bound = a.asname or a.name
            if f"{mod}.{a.name}" not in MODULES and (bound in listed or bound not in used):
                out.add(bound)
    return out


@pytest.mark.parametrize("name", sorted(MODULES))
def test_names_are_imported_from_their_owner(name):
    """A module does not pass on names it imports (in its ``__all__``, or imported and never used): callers
    import a name from the module that defines it, so moving code leaves no shim behind to maintain."""
    path, is_pkg = MODULES[name]
    found = _reexports(name, path, is_pkg)
    known = REEXPORTS_KNOWN.get(name, set())
    assert not found - known, f"{name} re-exports {sorted(found - known)}: import them from their owner instead"
    assert not known - found, f"{name} no longer re-exports {sorted(known - found)}: drop them from REEXPORTS_KNOWN"
