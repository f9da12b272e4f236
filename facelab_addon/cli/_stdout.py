"""Keeping Blender's own output off the CLI's stdout, which carries only the JSON summary."""

from __future__ import annotations

import contextlib
import os
import sys

__all__ = ["quiet_stdout"]


@contextlib.contextmanager
def quiet_stdout():
    """Send everything written to stdout (Python and Blender's C code) to stderr meanwhile."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # no real stdout (some embeddings)
        yield
        return
    sys.stdout.flush()
    saved = os.dup(fd)
    try:
        os.dup2(sys.stderr.fileno(), fd)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, fd)
        os.close(saved)
