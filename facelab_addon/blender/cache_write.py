"""Writing a stored correction's point-cache file over an object's modifier stack.

A correction that does not fit FaceLab's key budget is written as a PC2 or MDD file
(:func:`write_correction_file`) and then played by a Mesh Cache modifier
(:func:`facelab_addon.blender.bakes.add_correction_cache`, at :func:`capture_index`). What the file
holds depends on the stack: over a captured Mesh Cache in Integrate mode, the rest mesh plus the
key offsets showing the correction (played under the capture, when that is exact), otherwise the
whole input of the modifier (what the stack below gives, plus the correction). The byte layout and
the block writing are :mod:`facelab_addon.core.capture.pointcache_writer`'s. Positions are
object-local scene units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.capture.integrate import integrate_matrices
from ..core.capture.pointcache_writer import CacheLayout, PointCacheWriter, write_offset_cache
from . import cache_integrate
from .caches import input_positions
from .capture_stream import CaptureReader
from .ownership import correction_cache, is_correction_cache
from .shapekeys import rest_vertices

__all__ = ["CAPTURE_CACHES", "WrittenCache", "capture_index", "write_correction_file"]

#: Modifier types that play a capture.
CAPTURE_CACHES = ("MESH_CACHE", "MESH_SEQUENCE_CACHE")


@dataclass
class WrittenCache:
    """What :func:`write_correction_file` wrote.

    Attributes
    ----------
    integrate : bool
        The file holds rest positions plus offsets (its Mesh Cache plays in Integrate mode, so shape keys
        still add on top); False: the whole corrected input (Overwrite).
    index : int or None
        Where its modifier goes: 0 (under the capture) or None (right after the capture, :func:`capture_index`).
    mode : str
        One phrase for the report: how the cache plays.
    """

    integrate: bool
    index: int | None
    mode: str


def capture_index(obj, prefix: str):
    """``(modifiers, index)``: where a correction cache of ``prefix`` goes, right after the last enabled capture
    cache (or first). FaceLab's correction caches are no capture."""
    mods = list(obj.modifiers)
    caps = [i for i, m in enumerate(mods) if m.show_viewport and m.type in CAPTURE_CACHES
            and not is_correction_cache(obj, m)]
    return mods, (caps[-1] + 1 if caps else 0)


def write_correction_file(obj, prefix: str, path, layout: CacheLayout, read, vertices, tol: float) -> WrittenCache:
    """Write the cache file of a correction of ``vertices`` (all when None) stored on ``layout``'s frames.

    Parameters
    ----------
    obj : bpy.types.Object
    prefix : str
        The correction's prefix: FaceLab's previous output of it is left out of the input read.
    path : str or os.PathLike
    layout : CacheLayout
    read : callable
        ``read(i, j)``: the correction's rows ``i:j`` (j - i, n, 3), object local, as shown on the evaluated mesh.
    vertices : (n,) int ndarray or None
    tol : float
        The storage tolerance, scene units (a correction a thousandth of it changes no Integrate map).

    Returns
    -------
    WrittenCache
    """
    mods, index = capture_index(obj, prefix)
    caps = index > 0
    # over a capture cache in Integrate mode the deltas are key offsets (``cache_integrate``)
    integrate = caps and mods[index - 1].type == "MESH_CACHE" and mods[index - 1].deform_mode == "INTEGRATE"
    rest = rest_vertices(obj).astype(np.float32)
    if integrate and _under_capture_exact(obj, prefix, mods, index, read, layout.frames, vertices, tol):
        write_offset_cache(path, layout, read, rest, vertices)
        return WrittenCache(True, 0, "Integrate, under the capture cache: it holds only the correction as offsets "
                                     "from the mesh, and shape keys still add on top")
    static = _write_whole(obj, prefix, index, path, layout, read, rest, vertices, integrate)
    return WrittenCache(static, None, "Integrate: shape keys still add on top" if static else
                        "Overwrite: it holds the whole corrected input; later shape-key edits show once the "
                        "modifier is off")


def _under_capture_exact(obj, prefix, mods, index, read, frames, vertices, tol) -> bool:
    """Whether key offsets played by an Integrate cache at the top of the stack, under the captured Integrate
    Mesh Cache ``mods[index - 1]``, show exactly what keys would.

    That cache outputs ``rest + offsets + M_C s`` (``s``: the shape-key mix, ``M_C`` its own Integrate map,
    the identity wherever it holds no correction), which the capture then carries like keys. So it is
    exact when nothing else is enabled before the capture and, on every frame with a correction, no shape
    key moves a vertex of the correction's polygon neighbourhood (FaceLab's spike keys of corrected frames
    are 0 elsewhere; their own frame keeps a zero correction).
    """
    own = correction_cache(obj, prefix)[0]
    if any(m.show_viewport and m != own for m in mods[: index - 1]):
        return False
    verts = np.arange(len(obj.data.vertices)) if vertices is None else vertices
    ring = cache_integrate.polygon_neighbourhood(cache_integrate.polygon_corners(obj.data), verts)
    moved = cache_integrate.keys_move_frames(obj, ring, frames, skip_prefixes=(prefix,))
    tiny = 1e-3 * tol  # a correction this small changes no Integrate map measurably
    return not any(np.abs(read(t, t + 1)).max() > tiny for t in np.flatnonzero(moved))


def _write_whole(obj, prefix, index, path, layout, read, rest, vertices, integrate) -> bool:
    """The file of a cache over the whole input (what the stack up to modifier ``index`` gives, plus the
    correction, mapped through the capture's surface over an Integrate capture); whether that input is the
    static mesh."""
    span = layout.span
    corners = cache_integrate.polygon_corners(obj.data) if integrate else None
    imap = cache_integrate.IntegrateMap(corners, vertices, rest) if integrate and vertices is not None else None
    static = True
    # the capture's own samples (what it carries keys by), not the evaluated mesh: other keys may be live
    cap = CaptureReader(obj, None if imap is None else imap.vertices, cache_samples=True) if integrate else None
    writer = PointCacheWriter(path, layout.format, len(rest), len(span), **layout.header)
    try:
        for i in range(0, len(span), 32):
            fr = span[i:i + 32]
            base = input_positions(obj, fr, upto=index, skip_prefixes=(prefix,))  # without our old output
            static = static and bool(np.all(base == rest[None]))
            raw = cap.read(fr) if integrate else None
            for k, f in enumerate(fr):
                t = layout.row(f)
                if t is not None:
                    d = np.asarray(read(t, t + 1)[0], dtype=np.float64)
                    if integrate:
                        if imap is not None:  # the corrected vertices' own maps, rest side inverted once
                            d = imap.to_shown(raw[k : k + 1], d[None])[0]
                        else:
                            M = integrate_matrices(rest, raw[k], *corners)
                            d = np.einsum("vij,vj->vi", M, d)
                    d = d.astype(np.float32)
                    if vertices is None:
                        base[k] += d
                    else:
                        base[k, vertices] += d
            writer.write(base)
        writer.close()
    except BaseException:
        writer.abort()
        raise
    return static
