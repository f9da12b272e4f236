#!/usr/bin/env bash
# The demo: builds its environment, then runs headless on the ICT-FaceKit data.
# Writes out/demo/ (a .blend and renders) and refreshes docs/images/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/env.sh"
cd "$ROOT"
exec python scripts/demo.py "$@"
