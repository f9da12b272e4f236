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
