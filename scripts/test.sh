#!/usr/bin/env bash
# The test suite: pure-core tests and headless Blender tests (bpy wheel).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/env.sh"
cd "$ROOT"
exec python -m pytest -q tests "$@"
