#!/usr/bin/env bash
# The test suite (pure-core tests and headless Blender tests through the bpy module) on the oldest
# and the newest supported Blender, each in its own venv made on first use from
# requirements/bpy-<version>.txt (see scripts/env.sh):
#
#   bash scripts/test.sh                  # oldest and newest (4.5 LTS on Python 3.11, 5.3 on Python 3.13)
#   bash scripts/test.sh --only 5.3       # one of them (any requirements/bpy-*.txt version, e.g. 5.0)
#   bash scripts/test.sh --fast           # while working: one Blender (5.0, else the newest), tests marked
#                                         # slow left out (pytest -m "not slow"); the full suite stays the check
#   bash scripts/test.sh -- -k lips -x    # arguments after -- go to pytest
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
ALL="$(ls requirements/bpy-*.txt | sed 's|.*/bpy-||; s|\.txt$||' | sort -V)"
VERSIONS="$(printf '%s\n' "$ALL" | head -1) $(printf '%s\n' "$ALL" | tail -1)"
MARK=()
while [ $# -gt 0 ]; do
  case "$1" in
    --only) VERSIONS="${2:?--only needs a version: $(echo $ALL)}"; shift 2 ;;
    --only=*) VERSIONS="${1#--only=}"; shift ;;
    --fast)
      if printf '%s\n' $ALL | grep -qx "5.0"; then VERSIONS="5.0"; else VERSIONS="$(printf '%s\n' "$ALL" | tail -1)"; fi
      MARK=(-m "not slow"); shift ;;
    --) shift; break ;;
    *) break ;;
  esac
done
VERSIONS="$(printf '%s\n' $VERSIONS | awk '!seen[$0]++')"
failed=()
for v in $VERSIONS; do
  echo "[facelab] === bpy $v ===" >&2
  if ( export FACELAB_BPY="$v"; source "$ROOT/scripts/env.sh" &&
       python -c 'import bpy, numpy, sys; print("[facelab] bpy %s, Python %d.%d, numpy %s" % (
           bpy.app.version_string, *sys.version_info[:2], numpy.__version__), file=sys.stderr)' &&
       python -m pytest -q tests ${MARK[@]+"${MARK[@]}"} "$@" ); then
    echo "[facelab] bpy $v: passed" >&2
  else
    failed+=("$v")
  fi
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "[facelab] FAILED on bpy ${failed[*]} (of: $(echo $VERSIONS))" >&2
  exit 1
fi
echo "[facelab] passed on bpy $(echo $VERSIONS)" >&2
