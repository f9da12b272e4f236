"""``benchmarks/_harness.py``, the set-up the Blender benchmarks share: stdout carries only the JSON whatever
else prints (Python or C level), Blender's user resources go to a temporary folder, and the add-on is
unregistered when the benchmark ends, also when it fails (bpy 4.5 hangs at exit otherwise). Each case
runs a small script in a child process, as a benchmark runs."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(body, tmp_path, **env):
    """Run ``body`` after the harness's import; the environment without BLENDER_USER_RESOURCES, plus ``env``."""
    script = tmp_path / "bench.py"
    script.write_text(textwrap.dedent(f"""
        import os, sys
        sys.path[:0] = [{str(ROOT)!r}, {str(ROOT / "benchmarks")!r}]
        from _harness import blender_session, json_stdout, log, since, user_resources
    """) + textwrap.dedent(body))
    env = {k: v for k, v in os.environ.items() if k != "BLENDER_USER_RESOURCES"} | env
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, env=env)


def test_stdout_carries_only_the_json(tmp_path):
    r = _run("""
        import time
        out_json = json_stdout()
        print("python noise")
        os.write(1, b"C-level noise\\n")
        log("progress")
        t0 = time.perf_counter()
        out_json.emit({"a": 1, "name": "café", "s": since(t0)}, ensure_ascii=False)
        print("after")
    """, tmp_path)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert r.stdout == json.dumps(d, indent=1, ensure_ascii=False) + "\n"
    assert d["a"] == 1 and d["name"] == "café" and 0 <= d["s"] < 1
    for line in ("python noise", "C-level noise", "progress", "after"):
        assert line in r.stderr.splitlines()


def test_user_resources_go_to_a_temporary_folder_unless_set(tmp_path):
    r = _run("print(user_resources('facelab-test-'))", tmp_path)
    assert r.returncode == 0, r.stderr
    made = Path(r.stdout.strip())
    assert made.is_dir() and made.name.startswith("facelab-test-") and made.parent != ROOT
    made.rmdir()
    given = tmp_path / "mine"
    r = _run("print(user_resources())", tmp_path, BLENDER_USER_RESOURCES=str(given))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(given)


@pytest.mark.blender
def test_blender_session_registers_and_unregisters_even_when_the_benchmark_fails(tmp_path):
    r = _run("""
        out_json = json_stdout()
        state = {}
        try:
            with blender_session() as bpy:
                state["inside"] = hasattr(bpy.types.Scene, "facelab_store")
                state["user"] = os.environ["BLENDER_USER_RESOURCES"]
                raise RuntimeError("benchmark failed")
        except RuntimeError as e:
            state["error"] = str(e)
        import bpy
        state["after"] = hasattr(bpy.types.Scene, "facelab_store")
        out_json.emit(state)
    """, tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    d = json.loads(r.stdout)
    assert d["inside"] is True and d["after"] is False and d["error"] == "benchmark failed"
    assert Path(d["user"]).name.startswith("facelab-bl-user-")
