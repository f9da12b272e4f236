"""The shell scripts behave in a user's interactive shell: sourcing ``scripts/env.sh`` sets no shell
options and a failure returns instead of closing the terminal."""

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_sourcing_env_sh_leaves_the_shell_options_alone_and_returns_on_failure():
    script = (
        f"cd {ROOT}; FACELAB_BPY=0.0 source scripts/env.sh; echo \"rc=$?\"; "
        "set -o | grep -E '^(errexit|nounset|pipefail)'; false; echo alive"
    )
    r = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "no requirements/bpy-0.0.txt; supported:" in r.stderr
    lines = r.stdout.split("\n")
    assert "rc=1" in lines and "alive" in lines
    assert all(line.split()[-1] == "off" for line in lines if line.startswith(("errexit", "nounset", "pipefail")))


def test_the_demo_shows_progress_lines_and_logs_everything_else(tmp_path):
    """The demo runs in a child process whose output goes to OUT/demo.log; the terminal gets only its
    progress lines, the final table and usage errors (here: a bad --only, before any work)."""
    import sys

    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "demo.py"), "--out", str(out), "--only", "refine,x"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "unknown part(s) ['x'] in --only; choose from refine,propagate,solve,reconstruct" in r.stdout
    assert "Traceback" not in r.stdout + r.stderr
    assert sorted(p.name for p in out.iterdir()) == ["demo.log"]  # nothing else written
    assert "unknown part(s)" in (out / "demo.log").read_text()


def test_the_demo_table_has_one_row_per_step(capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("facelab_demo", ROOT / "scripts" / "demo.py")
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    refine = dict(lip_rms_mm_before=0.51, lip_rms_mm_after=0.2, contour_px_before=5.2, contour_px_after=0.8)
    prop = dict(frames=48, held_out_lip_rms_mm_before=0.31, held_out_lip_rms_mm_after=0.05,
                training_frames=[1, 2, 3], corrective_shapes=6)
    rows = [("refine", demo._row("refine", refine)), ("propagate", demo._row("propagate", prop))]
    demo._table(rows, {"refine": 12.0, "propagate": 80.4}, None)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 4 and all(ln.startswith("[table] ") for ln in lines)
    assert "0.51 mm" in lines[2] and "0.20 mm" in lines[2] and "12 s" in lines[2]
    assert "0.310 mm" in lines[3] and "0.050 mm" in lines[3] and "3 sketched frames" in lines[3]


def test_every_facelab_name_the_scripts_and_benchmarks_import_exists():
    """The demo, the benchmarks and the helper scripts import from the add-on inside functions, where only a
    full run would find a name that moved (the demo's propagation step once imported ``_y_at`` from a module
    it had left). Every ``from facelab_addon... import name`` in them must resolve."""
    import ast
    import importlib

    missing = []
    for path in sorted([*(ROOT / "scripts").glob("*.py"), *(ROOT / "benchmarks").glob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("facelab_addon"):
                try:
                    mod = importlib.import_module(node.module)
                except ImportError as e:
                    missing.append(f"{path.name}:{node.lineno}: {node.module} ({e})")
                    continue
                for alias in node.names:
                    if not hasattr(mod, alias.name):
                        try:  # a submodule imported by name
                            importlib.import_module(f"{node.module}.{alias.name}")
                        except ImportError:
                            missing.append(f"{path.name}:{node.lineno}: {node.module}.{alias.name}")
    assert not missing, "names the scripts import that do not exist:\n" + "\n".join(missing)
