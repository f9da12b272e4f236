"""Corrective shape keys on top of a captured cache (Mesh Cache in Integrate mode).

A Mesh Cache in ``'OVERWRITE'`` mode, and a Mesh Sequence Cache (Alembic) always, replace the
positions the shape keys produce. :func:`cache_to_shape_key_ready` makes the keys show: it
switches a Mesh Cache to ``'INTEGRATE'``, or bakes an Alembic capture to PC2 and plays it with
an Integrate Mesh Cache. In Integrate mode Blender carries a key's offset in the local frame of
the cache surface; :func:`correction_to_key_offsets` maps a wanted correction back through that
frame (:func:`facelab_addon.core.capture.integrate.integrate_matrices`).
"""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np

from ..core.capture import pointcache, pointcache_writer
from ..core.capture.integrate import corner_neighbours
from ..core.errors import FaceLabError, MeshError
from ..names import file_name_part
from ..core.geometry.inv3 import inv3
from .bakes import bake_steps, blend_relative, run_steps, uniform_step
from .caches import (
    alembic_still_error,
    check_capture_files,
    checked_frames,
    mesh_sequence_cache_modifier,
    mesh_cache_modifier,
    require_mesh_object,
    sequence_source,
)
from .objects import disabled_modifiers, modifier_enabled
from .ownership import key_matches, owned_key_names
from .shapekeys import key_values, values_from_action_only

__all__ = ["cache_to_shape_key_ready", "polygon_corners", "polygon_neighbourhood", "keys_move_frames",
           "correction_to_key_offsets", "IntegrateMap"]


def _unique_file(path: Path) -> Path:
    if not path.exists():
        return path
    i = 1
    while True:
        p = path.with_name(f"{path.stem}.{i:03d}{path.suffix}")
        if not p.exists():
            return p
        i += 1


def _unique_modifier_name(obj, base):
    from .shapekeys import unique_name

    return unique_name(base, (m.name for m in obj.modifiers))


def cache_to_shape_key_ready(obj, *, directory=None, scene_frames=None, progress=None) -> str:
    """Make shape keys (FaceLab's correctives) show on top of ``obj``'s captured cache.

    - Mesh Cache (PC2/MDD): sets its ``deform_mode`` to ``'INTEGRATE'``
      (in ``'OVERWRITE'`` the cache replaces the keyed positions).
    - Mesh Sequence Cache (Alembic), which always replaces the positions:
      bakes the captured sequence (the modifier's output, later modifiers
      off) to ``<object>_capture.pc2`` in ``directory`` (default: the
      .blend's folder; never overwriting a file), turns the Alembic modifier
      off in viewport and render (it is kept) and adds, right after it, a
      Mesh Cache playing that PC2 in ``'INTEGRATE'`` mode (sample 0 on
      ``scene_frames[0]``), so the mesh looks the same and keys add on top.
    - Shape-key animation or a static mesh: nothing to change.

    Nothing is deleted. Keys show *in the local frame* of the cache surface
    (``core.capture.integrate.integrate_matrices``).

    Parameters
    ----------
    obj : bpy.types.Object
    directory : str or os.PathLike, optional
        Where to write the PC2 for an Alembic cache.
    scene_frames : array_like of float, optional
        Frames to bake for an Alembic cache, evenly spaced. Default: the
        scene's frame range.
    progress : callable(i, T), optional

    Returns
    -------
    str
        What was changed, one sentence, for the operator's report.

    Raises
    ------
    MeshError
        The mesh has no faces (Integrate needs them) or the cache changes the
        vertex count.
    FaceLabError
        Unsaved .blend and no ``directory``.
    CacheFileError
        The cache file is missing or broken
        (:func:`~facelab_addon.blender.caches.check_capture_files`), or the
        Alembic capture does not move over ``scene_frames`` (the baked file is
        removed, the modifiers are left as they were).
    OutputError
        The PC2 cannot be written in ``directory``.
    """
    require_mesh_object(obj)
    src = sequence_source(obj)
    if src in ("mesh_cache", "mesh_sequence_cache") and len(obj.data.polygons) == 0:
        raise MeshError(f"'{obj.name}' has no faces; the Mesh Cache 'Integrate' mode needs faces to carry shape keys.")
    check_capture_files(obj)  # a broken file is refused before anything changes
    if src == "mesh_cache":
        md = mesh_cache_modifier(obj)
        if md.deform_mode == "INTEGRATE":
            return f"Mesh Cache '{md.name}' already integrates shape keys; nothing changed."
        md.deform_mode = "INTEGRATE"
        return f"Mesh Cache '{md.name}': deform mode Overwrite -> Integrate, so shape keys now add on top of the cache."
    if src == "shape_keys":
        return f"'{obj.name}' is animated by shape keys; corrective keys already add on top. Nothing changed."
    if src == "static":
        return f"'{obj.name}' has no captured cache; corrective keys already show. Nothing changed."

    # Alembic
    msc = mesh_sequence_cache_modifier(obj)
    scene = bpy.context.scene
    frames = checked_frames(range(scene.frame_start, scene.frame_end + 1) if scene_frames is None else scene_frames)
    step = uniform_step(frames, "Baking the Alembic cache")
    if directory is None:
        if not bpy.data.filepath:
            raise FaceLabError(
                "Save the .blend first (the capture is baked to a PC2 file next to it), or give a directory."
            )
        directory = os.path.dirname(bpy.data.filepath)
    directory = Path(bpy.path.abspath(os.fspath(directory)))
    base = file_name_part(obj.name)
    path = _unique_file(directory / f"{base}_capture.pc2")

    mods = list(obj.modifiers)
    k = mods.index(msc)
    later = [m for m in mods[k + 1 :] if modifier_enabled(m)]
    n = len(obj.data.vertices)
    with disabled_modifiers(later):
        run_steps(bake_steps(obj, frames, lambda: pointcache_writer.PointCacheWriter(
            path, "PC2", n, len(frames), start_frame=float(frames[0]), sample_rate=step), progress=progress))
    try:  # a capture that never moves is a file Blender could not read: keep the artist's modifier on
        baked = pointcache.read_pc2(path, mmap=True)[0]
        moved = len(frames) == 1 or any(np.any(baked[t] != baked[0]) for t in range(1, len(frames)))
        del baked
        if not moved:
            raise alembic_still_error(obj, frames)
    except FaceLabError:
        path.unlink(missing_ok=True)
        raise

    msc.show_viewport = False
    msc.show_render = False
    mc = obj.modifiers.new(_unique_modifier_name(obj, "FL Capture (PC2)"), "MESH_CACHE")
    mc.cache_format = "PC2"
    mc.filepath = blend_relative(path)
    mc.play_mode = "SCENE"
    mc.time_mode = "FRAME"
    mc.frame_scale = 1.0 / step
    mc.frame_start = float(frames[0]) / step  # sample = f/step - f0/step
    mc.interpolation = "LINEAR"
    mc.deform_mode = "INTEGRATE"
    mc.forward_axis, mc.up_axis = "POS_Y", "POS_Z"
    obj.modifiers.move(len(obj.modifiers) - 1, k + 1)
    return (
        f"Baked Alembic modifier '{msc.name}' ({len(frames)} frames, {frames[0]:g}-{frames[-1]:g}) to '{path}', "
        f"turned it off (kept) and added Mesh Cache '{mc.name}' (PC2, Integrate) after it, "
        "so shape keys now add on top of the capture."
    )


def polygon_corners(mesh):
    """``(face_offsets (P+1,), corner_verts (C,))`` int arrays of a Blender mesh's polygons."""
    offs = np.empty(len(mesh.polygons), np.int32)
    mesh.polygons.foreach_get("loop_start", offs)
    cv = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", cv)
    return np.r_[offs, len(cv)].astype(np.int64), cv.astype(np.int64)


def polygon_neighbourhood(corners, verts) -> np.ndarray:
    """Sorted vertices sharing a polygon edge with ``verts`` (``verts`` included): where an Integrate map
    whose cache moves only ``verts`` differs from the identity.

    Parameters
    ----------
    corners : tuple
        ``polygon_corners(mesh)``.
    verts : (n,) int array_like

    Returns
    -------
    (k,) int64 ndarray
    """
    offs, cv = corners
    prev, nxt = corner_neighbours(offs, cv)
    sel = np.isin(cv, np.asarray(verts, dtype=np.int64))
    return np.unique(np.r_[cv[sel], prev[sel], nxt[sel]]).astype(np.int64)


def keys_move_frames(obj, verts, frames, *, skip_prefixes=()) -> np.ndarray:
    """(T,) bool: the frames on which the shape-key mix may move any of ``verts`` away from the Basis.

    Keys muted, the Basis, and the keys ``skip_prefixes`` select (``shapekeys.key_matches``) are left
    out; so is a key whose offsets are zero on ``verts``. A key keyed (or set) to 0 on a frame does
    not move it. Conservative: when the key values cannot be read without evaluating the scene
    (drivers, NLA, a blended action, absolute keys) every frame counts as moved.

    Parameters
    ----------
    obj : bpy.types.Object
    verts : (n,) int array_like
    frames : (T,) array_like of float
        Scene frames.
    skip_prefixes : tuple of str

    Returns
    -------
    (T,) bool ndarray
    """
    frames = np.asarray(frames, dtype=np.float64).ravel()
    key = obj.data.shape_keys
    out = np.zeros(len(frames), bool)
    if key is None or len(key.key_blocks) < 2:
        return out
    if not key.use_relative:
        return ~out
    v = np.asarray(verts, dtype=np.int64)
    n = len(obj.data.vertices)
    owned = set(owned_key_names(key, create=False))
    blended = not values_from_action_only(key)

    def coords(data):
        c = np.empty(n * 3, np.float32)
        data.foreach_get("co", c)
        return c.reshape(n, 3)[v]

    for kb in key.key_blocks:
        if kb == key.reference_key or kb.mute or key_matches(key, kb.name, tuple(skip_prefixes), owned):
            continue
        if not np.any(coords(kb.data) != coords(kb.relative_key.data)):
            continue  # does not touch these vertices
        if blended:
            return ~out
        out |= key_values(key, kb, frames) != 0.0
    return out


def correction_to_key_offsets(obj, cache_positions, deltas, corners=None):
    """Shape-key offsets that show as ``deltas`` (V,3) on a frame whose cache output is ``cache_positions``.

    Without a cache (shape keys, static mesh) this is ``deltas`` itself. Over a
    Mesh Cache in ``'INTEGRATE'`` mode Blender carries key offsets in the
    local frame of the cache surface (``core.capture.integrate.integrate_matrices``),
    so the offsets are mapped back through those matrices.

    Parameters
    ----------
    obj : bpy.types.Object
    cache_positions : (V,3) float
        The captured positions on that frame (FaceLab keys muted), object-local.
    deltas : (V,3) float
        Wanted displacement of the evaluated mesh, object-local scene units.
    corners : tuple, optional
        Precomputed ``polygon_corners(obj.data)``.
    """
    if sequence_source(obj) not in ("mesh_cache", "mesh_sequence_cache"):
        return np.asarray(deltas, dtype=np.float64)
    from ..core.capture.integrate import integrate_matrices, integrate_offsets_to_key
    from .shapekeys import rest_vertices

    offs, cv = polygon_corners(obj.data) if corners is None else corners
    M = integrate_matrices(rest_vertices(obj), cache_positions, offs, cv)
    return integrate_offsets_to_key(M, deltas)


class IntegrateMap:
    """Key offsets that show wanted corrections of a few vertices over an Integrate Mesh Cache, many frames at once.

    The map of :func:`facelab_addon.core.capture.integrate.integrate_matrices` restricted to
    ``verts``: only their own polygon corners enter it (a vertex's map averages over its
    corners), and the rest side of every corner frame is inverted once here instead of on
    every frame. :meth:`to_key` maps a chunk of frames; equal to ``integrate_offsets_to_key``
    of ``integrate_matrices`` frame by frame.

    Parameters
    ----------
    corners : tuple
        ``polygon_corners(mesh)``.
    verts : (n,) int array_like
        The vertices corrected.
    rest : (V,3) array_like
        The mesh's own positions (the Basis), object local.

    Attributes
    ----------
    vertices : (k,) int64
        The vertices whose captured positions :meth:`to_key` needs (``verts`` and their polygon neighbours).
    """

    def __init__(self, corners, verts, rest):
        offs, cv = corners
        prev, nxt = corner_neighbours(offs, cv)
        verts = np.asarray(verts, dtype=np.int64)
        sel = np.isin(cv, verts)
        cur, prev, nxt = cv[sel], prev[sel], nxt[sel]
        self.vertices = np.unique(np.r_[cur, prev, nxt])
        self._c, self._p, self._n = (np.searchsorted(self.vertices, a) for a in (cur, prev, nxt))
        S = np.asarray(rest, dtype=np.float64)[self.vertices]
        e1, e2, nrm, area = self._frames(S[None])
        self._area = area[0]
        self._ok = self._area > 0
        Bs = np.stack([e1[0], e2[0], nrm[0]], axis=2)
        self._inv = np.zeros_like(Bs)
        self._inv[self._ok] = inv3(Bs[self._ok])
        rows = np.searchsorted(verts, cur)
        cnt = np.bincount(rows, minlength=len(verts)).astype(np.float64)
        import scipy.sparse as sp

        self._avg = sp.csr_matrix((1.0 / cnt[rows], (rows, np.arange(len(cur)))), shape=(len(verts), len(cur)))

    def _frames(self, P):
        c, p, n = P[:, self._c], P[:, self._p], P[:, self._n]
        e1, e2 = p - c, n - c
        nrm = np.cross(c - p, n - c)  # normal_tri_v3(prev, cur, next)
        area2 = np.linalg.norm(nrm, axis=-1)
        nrm /= np.where(area2 > 0, area2, 1.0)[..., None]
        return e1, e2, nrm, 0.5 * area2

    def to_key(self, captured, deltas, block: int = 32) -> np.ndarray:
        """Key offsets (t, n, 3) showing ``deltas`` (t, n, 3) of ``verts`` on frames whose cache output is ``captured``.

        ``captured`` (t, k, 3): positions of :attr:`vertices`, object local. Vertices whose map is
        singular get the least-squares offset.
        """
        out = np.empty(np.shape(deltas))
        for s in range(0, len(out), block):
            M = self._maps(captured[s : s + block])
            t = len(M)
            d = np.asarray(deltas[s : s + block], dtype=np.float64)
            good = np.abs(np.sum(M[..., 0, :] * np.cross(M[..., 1, :], M[..., 2, :]), axis=-1)) > 1e-12  # det
            res = np.zeros_like(d)
            res[good] = np.einsum("nij,nj->ni", inv3(M[good]), d[good])  # closed form: no LAPACK call per vertex
            for i, v in zip(*np.nonzero(~good)):
                res[i, v] = np.linalg.lstsq(M[i, v], d[i, v], rcond=None)[0]
            out[s : s + t] = res
        return out

    def to_shown(self, captured, key_offsets, block: int = 32) -> np.ndarray:
        """What key offsets (t, n, 3) of ``verts`` show over the cache: the inverse of :meth:`to_key`.

        ``captured`` (t, k, 3): positions of :attr:`vertices` on those frames, object local. Equal to
        ``integrate_matrices(...)[verts] @ offset`` frame by frame, at the cost of the corrected vertices only.
        """
        out = np.empty(np.shape(key_offsets))
        for s in range(0, len(out), block):
            M = self._maps(captured[s : s + block])
            out[s : s + len(M)] = np.einsum("tnij,tnj->tni", M, np.asarray(key_offsets[s : s + block], np.float64))
        return out

    def _maps(self, captured) -> np.ndarray:
        """(t, n, 3, 3) Integrate map of each corrected vertex on frames whose cache output is ``captured`` (t, k, 3)."""
        P = np.asarray(captured, dtype=np.float64)
        t = len(P)
        e1, e2, nrm, area = self._frames(P)
        k = np.sqrt(area / np.where(self._area > 0, self._area, 1.0))
        Bo = np.stack([e1, e2, nrm * k[..., None]], axis=3)  # (t, C, 3, 3) columns
        L = Bo @ self._inv  # zero where the rest corner is degenerate
        return (self._avg @ L.transpose(1, 0, 2, 3).reshape(L.shape[1], -1)).reshape(-1, t, 3, 3).transpose(1, 0, 2, 3)
