"""Whether the files of FaceLab's correction caches are where the .blend says.

A correction cache (``//<blend>_<object>_<prefix>.pc2``, :func:`.bakes.correction_cache_path`) is
found by the path stored in its Mesh Cache modifier. A .blend moved or copied without it plays
nothing there: Blender shows (and would bake) the uncorrected capture and says so only on its
console. These functions name each such cache, where Blender looked, where FaceLab wrote it and
the fix, for the steps that must refuse meanwhile (Bake, the heat map), the sidebar and the CLI.
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy

from ..names import PROPAGATE_PREFIX, RECONSTRUCT_PREFIX, RETARGET_PREFIX, SOLVE_PREFIX
from .ownership import correction_cache, correction_cache_record

__all__ = ["correction_cache_players", "missing_correction_files", "correction_cache_problems",
           "require_correction_caches"]

#: The step that writes each prefix's correction cache (named in the fix of a missing one).
_STEP_OF_PREFIX = {PROPAGATE_PREFIX: "Propagate", SOLVE_PREFIX: "Solve Performance",
                   RECONSTRUCT_PREFIX: "Reconstruct", RETARGET_PREFIX: "Retarget"}


def correction_cache_players(obj) -> list:
    """``[(prefix, modifier, owner, mesh_cache)]``: each FaceLab correction cache of ``obj`` with a file, the
    modifier recorded for it on ``obj``, and the object and Mesh Cache modifier that play the file (``obj``
    itself, or the hidden patch object of a patch cache)."""
    out = []
    if getattr(obj, "type", None) != "MESH":
        return out
    for prefix, entry in correction_cache_record(obj).items():
        md = correction_cache(obj, prefix)[0]
        if md is None:
            continue
        owner = obj
        if md.type == "NODES":  # a patch cache: the hidden patch object plays the file
            owner = bpy.data.objects.get(entry.get("patch", "")) if entry.get("patch") else None
            if owner is None:
                continue
        mc = md if md.type == "MESH_CACHE" else next((m for m in owner.modifiers if m.type == "MESH_CACHE"), None)
        if mc is not None and mc.filepath:
            out.append((prefix, md, owner, mc))
    return out


def missing_correction_files(obj) -> list:
    """``[(prefix, stored path)]`` of ``obj``'s correction caches whose file is not there (a panel's check)."""
    return [(prefix, mc.filepath) for prefix, _, owner, mc in correction_cache_players(obj)
            if not os.path.isfile(bpy.path.abspath(mc.filepath, library=owner.library))]


def correction_cache_problems(obj, *, read_headers: bool = True) -> list:
    """What is wrong with the files of ``obj``'s FaceLab correction caches: one sentence per cache.

    A correction cache is a file beside the .blend (``//<blend>_<object>_<prefix>.pc2``), found by
    the path stored in its Mesh Cache modifier. When the .blend is moved or copied without it,
    Blender plays nothing there and shows (and bakes) the uncorrected capture without a word; this
    names each such cache, where Blender looked, where FaceLab wrote it, and the fix.

    Parameters
    ----------
    obj : bpy.types.Object
    read_headers : bool
        Also read each file's header (a truncated file, another vertex count); False: only whether it
        exists (cheap enough for a panel redraw).

    Returns
    -------
    list of str
        Empty when every cache plays.
    """
    from ..core.capture import pointcache
    from ..core.errors import CacheFileError

    out = []
    for prefix, md, owner, mc in correction_cache_players(obj):
        files = correction_cache(obj, prefix)[1]
        path = bpy.path.abspath(mc.filepath, library=owner.library)
        step = _STEP_OF_PREFIX.get(prefix, "the step that wrote it")
        what = f"The correction cache of '{obj.name}' ({prefix}*, modifier '{md.name}')"
        if not os.path.isfile(path):
            written = files[-1] if files else ""
            if written and os.path.normpath(written) != os.path.normpath(path) and os.path.isfile(written):
                where = f"it is still at '{written}': copy it to '{path}'"
            else:
                where = f"copy '{Path(written or path).name}' back beside the .blend ('{path}')"
            out.append(f"{what} plays '{mc.filepath}', but there is no such file ('{path}'; the .blend was moved or "
                       f"copied without it), so '{obj.name}' shows the uncorrected capture. Fix: {where}, or run "
                       f"{step} again to write it anew.")
            continue
        if read_headers:
            try:
                info = pointcache.cache_info(path, mc.cache_format)
                n = len(owner.data.vertices)
                pointcache.check_vertex_count(info, n, name=f"'{owner.name}'")
            except CacheFileError as e:
                out.append(f"{what}: {e} Run {step} again to write it anew.")
    return out


def require_correction_caches(obj, what: str) -> None:
    """Refuse ``what`` while a FaceLab correction cache of ``obj`` is missing or broken.

    Raises
    ------
    CacheFileError
        :func:`correction_cache_problems`, after ``what`` and why it cannot run.
    """
    from ..core.errors import CacheFileError

    problems = correction_cache_problems(obj)
    if problems:
        raise CacheFileError(f"{what} would use '{obj.name}' without FaceLab's correction: " + " ".join(problems))
