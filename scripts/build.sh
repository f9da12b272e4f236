#!/usr/bin/env bash
# Build the Blender extension zips into dist/: one per platform and Blender Python (Blender 4.5-5.0:
# Python 3.11; 5.1-5.3: Python 3.13), each with only its own wheels; the last lines list the zips.
# Needs the development environment (scripts/env.sh makes the venv with the bpy module the first time).
# Arguments go to scripts/build_extension.py, e.g. `bash scripts/build.sh --platform linux-x64 --python 3.13`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/env.sh"
cd "$ROOT"
exec python scripts/build_extension.py "$@"
