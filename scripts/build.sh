#!/usr/bin/env bash
# Build the Blender extension zips (one per platform, with their wheels) into dist/.
# Arguments go to scripts/build_extension.py, e.g. `bash scripts/build.sh --platform linux-x64`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/env.sh"
cd "$ROOT"
exec python scripts/build_extension.py "$@"
