"""Output files, checked before a pipeline starts: the destination must be an absolute path (or a
``//`` path of a saved .blend) whose folder can be written.

Relative paths are refused rather than resolved against the working directory (a ``//`` path in an
unsaved .blend, or ``out.pc2``, would otherwise land wherever Blender was started from).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import bpy

from ..core.errors import FaceLabError

__all__ = ["OutputPathError", "check_output"]


class OutputPathError(FaceLabError):
    """A destination file cannot be written: relative without a saved .blend, a folder that is a
    file, a read-only folder, or an existing folder in the file's place."""


def check_output(path, what: str = "Bake") -> Path | None:
    """The absolute destination of ``path``, if a file can be written there; None for an empty path.

    Parameters
    ----------
    path : str or os.PathLike
        Absolute, or ``//``-relative to the saved .blend.
    what : str
        The step asking, for the message.

    Raises
    ------
    OutputPathError
        Relative path (``//`` in an unsaved .blend, or no ``//``), a folder on the way that is a
        file, a folder that cannot be written, or a folder where the file should be.
    """
    if not path:
        return None
    text = os.fspath(path)
    if text.startswith("//"):
        if not bpy.data.filepath:
            raise OutputPathError(f"{what}: '{text}' is relative to the .blend, which is not saved yet, so it would "
                                  "be written to Blender's working directory; save the .blend first or choose an "
                                  "absolute path.")
        text = bpy.path.abspath(text)
    p = Path(text)
    if not p.is_absolute():
        raise OutputPathError(f"{what}: '{text}' is a relative path (it would be written to the working directory "
                              f"{os.getcwd()}); choose an absolute path, or '//{text}' beside the saved .blend.")
    if p.is_dir():
        raise OutputPathError(f"{what}: {p} is a folder; choose a file name inside it (e.g. {p / 'face.pc2'}).")
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputPathError(f"{what}: {parent} is a file, not a folder, so {p.name} cannot be written under it; "
                              "choose another folder.")
    try:
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".facelab_probe_"):
            pass
    except OSError as e:
        raise OutputPathError(f"{what}: cannot write in the folder {parent} ({e.strerror or e}); choose a folder "
                              "you can write to, or change its permissions.") from None
    if p.exists() and not os.access(p, os.W_OK):
        raise OutputPathError(f"{what}: {p} exists and is read-only; choose another file or make it writable.")
    return p
