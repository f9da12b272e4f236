#!/usr/bin/env bash
# The demo: builds its environment, then runs headless on the ICT-FaceKit data.
# Writes out/demo/ (the .blend files, renders and figures); --refresh-docs also rewrites docs/images/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/env.sh"
cd "$ROOT"
exec python scripts/demo.py "$@"
