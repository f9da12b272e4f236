"""The docs follow the code: docs/api.md is what scripts/api_docs.py generates now, every link in the
Markdown stays inside the repository and resolves, every `facelab_addon` path the Markdown names
(`facelab_addon.core.lips.sketch.refine_lips`, `core.capture.camera.Camera`, `from ... import ...`)
exists in the code, and every figure of docs/benchmarks.md is a value of benchmarks/results/*.json."""

import ast
import json
import importlib.util
import re
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MARKDOWN = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
# docs whose Python paths are checked against the code (api.md is generated from it)
PATH_CHECKED = [p for p in MARKDOWN if p.name != "api.md"]

LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def load_api_docs():
    spec = importlib.util.spec_from_file_location("api_docs", ROOT / "scripts" / "api_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_api_md_is_up_to_date(tmp_path):
    out = tmp_path / "api.md"
    with out.open("w") as f:
        r = subprocess.run([sys.executable, str(ROOT / "scripts" / "api_docs.py"), "--stdout"], cwd=ROOT,
                           stdout=f, stderr=subprocess.PIPE, text=True)
    assert r.returncode == 0, r.stderr
    assert out.read_text() == (ROOT / "docs" / "api.md").read_text(), \
        "docs/api.md is out of date: run python scripts/api_docs.py"


def test_api_docs_covers_the_shipped_modules_without_importing_them():
    api = load_api_docs()
    names = [m for m, _ in api.modules()]
    assert names == sorted(names, key=lambda m: m.split("."))
    assert "facelab_addon.core.lips.sketch" in names and "facelab_addon.blender.strokes" in names
    assert not [m for m in names if m.startswith(("facelab_addon.ui", "facelab_addon.testing"))]
    assert not [m for m in names if "._" in m]
    summary, entries = api.describe("facelab_addon.core.lips.sketch",
                                    ROOT / "facelab_addon" / "core" / "lips" / "sketch.py")
    assert summary.startswith("Sketch-based lip refinement")
    assert ("refine_lips", "function") in [(n, k) for n, k, _ in entries]
    text = (ROOT / "docs" / "api.md").read_text()
    assert "## `facelab_addon.blender.strokes`" in text  # imports bpy: parsed, not imported


def links(path):
    text = FENCE.sub("", path.read_text())
    text = re.sub(r"`[^`\n]*`", "", text)
    return LINK.findall(text)


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda p: str(p.relative_to(ROOT)))
def test_links_stay_inside_the_repository(path):
    bad = []
    for target in links(path):
        if target.startswith("#"):
            continue
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):
            bad.append(f"{target}: points outside the repository")
            continue
        dest = (path.parent / target.split("#")[0]).resolve()
        if not dest.is_relative_to(ROOT):
            bad.append(f"{target}: leaves the repository")
        elif not dest.exists():
            bad.append(f"{target}: does not exist")
    assert not bad, bad


def test_readme_links_the_docs():
    found = {t for t in links(ROOT / "README.md")}
    for doc in ("docs/conventions.md", "docs/benchmarks.md", "docs/api.md", "docs/install.md", "docs/cli.md"):
        assert doc in found, doc
    readme = (ROOT / "README.md").read_text()
    assert "| case |" not in readme and "## Benchmarks" not in readme  # the numbers live in docs/benchmarks.md
    assert "DESIGN.md" not in readme


@cache
def module_names(dotted):
    """Top-level names a module defines, or None if there is no such module."""
    base = ROOT.joinpath(*dotted.split("."))
    path = base / "__init__.py" if base.is_dir() else base.with_suffix(".py")
    if not path.exists():
        return None
    names = {p.stem for p in base.glob("*.py")} | {p.name for p in base.iterdir() if p.is_dir()} \
        if base.is_dir() else set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names}
    return names


def check_path(dotted):
    """Why a dotted ``facelab_addon`` path does not exist ('' if it does)."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        if module_names(".".join(parts[:i])) is not None:
            rest = parts[i:]
            if not rest or rest[0] in module_names(".".join(parts[:i])):
                return ""
            return f"{dotted}: {'.'.join(parts[:i])} has no {rest[0]}"
    return f"{dotted}: no such module"


LAYERS = r"(?:core|blender|pipeline|ui|cli|testing|names|assets)"
DOTTED = re.compile(rf"\b(?:facelab_addon\.)?{LAYERS}(?:\.[A-Za-z_]\w*)+")


@pytest.mark.parametrize("path", PATH_CHECKED, ids=lambda p: str(p.relative_to(ROOT)))
def test_python_paths_in_the_docs_exist(path):
    text = path.read_text()
    refs = set()
    for code in re.findall(r"`([^`\n]+)`", FENCE.sub("", text)) + FENCE.findall(text):
        for m in DOTTED.findall(code):
            if re.search(r"\.(py|md|json|obj|toml|png|blend|pc2|mdd|zip|txt)$", m):
                continue
            refs.add(m if m.startswith("facelab_addon.") else "facelab_addon." + m)
    for block in FENCE.findall(text):
        for mod, names in re.findall(r"^\s*from (facelab_addon[\w.]*) import ([\w, ]+)", block, re.M):
            refs |= {f"{mod}.{n.split()[0]}" for n in names.split(",") if n.strip()}  # "a as b" -> a
    if path.name in ("README.md", "conventions.md"):
        assert refs, f"{path.name} names no facelab_addon path"
    bad = [why for why in map(check_path, sorted(refs)) if why]
    assert not bad, bad


def test_path_check_catches_stale_paths():
    assert check_path("facelab_addon.core.lips.sketch.refine_lips") == ""
    assert check_path("facelab_addon.core.capture.camera.Camera") == ""
    assert "has no sketch" in check_path("facelab_addon.core.sketch.refine_lips")  # the pre-regroup path
    assert "has no refine" in check_path("facelab_addon.core.lips.sketch.refine")


# --------------------------------------------------------------------------- written for artists
GUIDES = [p for p in MARKDOWN if p.parent.name == "docs" and p.name != "api.md"]
#: Phrases of a lab notebook, not of a guide: history stays in git.
HISTORY = re.compile(r"(?i)\bthis session\b|\b(?:last|previous) session\b|\bused to\b|\(issue \d+|\bissue \d+'s\b"
                     r"|\bsince then\b|\brerun after\b|\buntil now\b")
MAX_CELL = 300  # characters of one table cell
README_LINES = 150


def table_cells(text):
    """``(line number, cell)`` of every Markdown table row's cells outside code fences."""
    out = []
    fenced = False
    for n, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        if fenced or not line.lstrip().startswith("|"):
            continue
        cells = re.split(r"(?<!\\)\|", line.strip().strip("|"))
        out += [(n, c.strip()) for c in cells]
    return out


@pytest.mark.parametrize("path", GUIDES, ids=lambda p: str(p.relative_to(ROOT)))
def test_guides_carry_no_history(path):
    hits = [f"{path.name}:{n}: {m.group(0)!r}" for n, line in enumerate(path.read_text().splitlines(), 1)
            for m in HISTORY.finditer(line)]
    assert not hits, hits


@pytest.mark.parametrize("path", [p for p in MARKDOWN if p.name != "README.md"],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_table_cells_are_short(path):
    long = [f"{path.name}:{n}: {len(c)} characters: {c[:60]}..." for n, c in table_cells(path.read_text())
            if len(c) > MAX_CELL]
    assert not long, long


def test_doc_checks_catch_what_they_should():
    assert HISTORY.search("rows are from a rerun after this session's change")
    assert HISTORY.search("Damp Uncertain Frames (issue 11)") and HISTORY.search("what used to read -1")
    assert not HISTORY.search("the issue is the lips; 11 frames") and not HISTORY.search("a used tool")
    cells = table_cells("| a | b |\n|---|---|\n| x | " + "y" * 400 + " |\n```\n| in | code |\n```\n")
    assert [len(c) for _, c in cells] == [1, 1, 3, 3, 1, 400]


def test_readme_is_short_and_table_cells_short():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_LINES
    assert not [c for _, c in table_cells(text) if len(c) > MAX_CELL]


def test_every_readme_figure_links_to_benchmarks():
    """Every line of the README giving a measured figure (a percentage, mm, ms, a ratio) links to
    docs/benchmarks.md, where the figure and the command that made it live."""
    text = FENCE.sub("", (ROOT / "README.md").read_text())
    figure = re.compile(r"\d+(?:\.\d+)?\s?(?:%|mm\b|ms\b|×)")
    bare = [line[:80] for line in text.splitlines() if figure.search(line) and "docs/benchmarks.md" not in line]
    assert not bare, bare


#: Figures of docs/benchmarks.md measured outside the benchmarks' JSON (the text says where).
NOT_IN_RESULTS = {"0.000023"}  # the posed head and jaw of tests/blender/test_rest_space.py


def _result_values():
    vals = []

    def walk(o):
        if isinstance(o, dict):
            for v in o.values():
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)
        elif isinstance(o, (int, float)) and not isinstance(o, bool):
            vals.append(float(o))

    for f in sorted((ROOT / "benchmarks" / "results").glob("*.json")):
        walk(json.loads(f.read_text()))
    return vals


def test_benchmark_figures_are_in_the_results():
    """Every figure with two or more decimals in docs/benchmarks.md is some value of the results JSON
    (as stored, or as a percentage / per mille / x10), rounded as the text shows it: a figure typed by
    hand, or left behind when a benchmark was re-run, fails."""
    vals = _result_values()
    text = FENCE.sub("", (ROOT / "docs" / "benchmarks.md").read_text())
    figures = set(re.findall(r"(?<![\w.])(\d+\.\d{2,})(?![\w.])", text)) - NOT_IN_RESULTS
    missing = sorted(
        n for n in figures
        if not any(abs(round(v * s, len(n.split(".")[1])) - float(n)) < 1e-9 for v in vals for s in (1, 10, 100, 1000))
    )
    assert not missing, f"docs/benchmarks.md figures in no benchmarks/results/*.json: {missing}"

