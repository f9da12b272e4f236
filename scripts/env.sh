#!/usr/bin/env bash
# Create (once) and activate a FaceLab virtual environment for one supported Blender version.
# Sourced by scripts/test.sh, scripts/demo.sh and scripts/build.sh; safe to run repeatedly.
#
#   FACELAB_BPY=4.5|5.0|5.3   which requirements/bpy-<version>.txt to install (default 5.0)
#   FACELAB_VENV=DIR          the venv directory (default .venv for 5.0, .venv-bpy45 / .venv-bpy53 otherwise)
#   FACELAB_PYTHON=EXE        the interpreter to build the venv with (default: found, see below)
#
# The Python version comes from the requirements file's "# python: X.Y" line (the bpy wheels of
# each Blender exist for one Python only). The interpreter is looked up the way a machine offers it:
# pythonX.Y on PATH, then pyenv's installed versions.
#
# Safe to source into an interactive shell: it sets no shell options, and a failure returns 1
# with a message instead of exiting the shell.
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BPY="${FACELAB_BPY:-5.0}"
REQ="$ROOT/requirements/bpy-$BPY.txt"
if [ ! -f "$REQ" ]; then
  echo "[facelab] no requirements/bpy-$BPY.txt; supported: $(cd "$ROOT/requirements" && ls bpy-*.txt | sed 's/bpy-//; s/\.txt//' | tr '\n' ' ')" >&2
  return 1 2>/dev/null || exit 1
fi
if [ "$BPY" = "5.0" ]; then VENV_DEFAULT="$ROOT/.venv"; else VENV_DEFAULT="$ROOT/.venv-bpy${BPY//./}"; fi
VENV="${FACELAB_VENV:-$VENV_DEFAULT}"
PYVER="$(sed -n 's/^# python: *\([0-9.]*\).*/\1/p' "$REQ" | head -1)"

facelab_find_python() {  # prints an interpreter running Python $1, or nothing
  local want="$1" cand v
  for cand in "python$want" python3; do
    if command -v "$cand" >/dev/null 2>&1 && \
       [ "$("$cand" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)" = "$want" ]; then
      command -v "$cand"; return 0
    fi
  done
  if command -v pyenv >/dev/null 2>&1; then
    for v in $(pyenv versions --bare 2>/dev/null | grep -E "^$want(\.[0-9]+)?$" | sort -t. -k3 -n -r); do
      cand="$(pyenv root)/versions/$v/bin/python$want"
      if [ -x "$cand" ]; then echo "$cand"; return 0; fi
    done
  fi
  return 1
}

# The venv is (re)made when missing or on another Python; pins that changed since the last install
# (the stamp holds the requirement lines installed, comments ignored) are installed into it.
STAMP="$VENV/.facelab-requirements"
pins() { grep -v '^[[:space:]]*#' "$1" 2>/dev/null | sed '/^[[:space:]]*$/d'; }
if [ ! -x "$VENV/bin/python" ] || \
   [ "$("$VENV/bin/python" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)" != "$PYVER" ]; then
  PY="${FACELAB_PYTHON:-}"
  if [ -z "$PY" ] && ! PY="$(facelab_find_python "$PYVER")"; then
    echo "[facelab] bpy $BPY needs Python $PYVER, which was not found (looked for python$PYVER and python3 on PATH," \
         "and in pyenv). Install Python $PYVER (e.g. 'pyenv install $PYVER'), or set FACELAB_PYTHON." >&2
    return 1 2>/dev/null || exit 1
  fi
  echo "[facelab] setting up $VENV for bpy $BPY with $PY (first run downloads bpy, ~400 MB)" >&2
  rm -rf "$VENV"
  if ! "$PY" -m venv "$VENV"; then
    echo "[facelab] could not create the venv $VENV with $PY" >&2
    return 1 2>/dev/null || exit 1
  fi
fi
if [ "$(pins "$REQ")" != "$(pins "$STAMP")" ]; then
  if ! "$VENV/bin/python" -m pip install -q --disable-pip-version-check -r "$REQ"; then
    echo "[facelab] installing requirements/bpy-$BPY.txt into $VENV failed (see pip's message above)" >&2
    return 1 2>/dev/null || exit 1
  fi
  cp "$REQ" "$STAMP"
fi
export PATH="$VENV/bin:$PATH"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
