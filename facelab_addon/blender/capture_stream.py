"""Reading a captured sequence a chunk of frames at a time, for only the vertices a step needs.

:func:`facelab_addon.blender.caches.read_captured_frames` returns whole (T,V,3) frames; a
10,000-frame shot of a 105k-vertex face is 12 GB that way. :class:`CaptureReader` prepares
once what every chunk needs and then returns (t, n, 3) float32 positions of ``vertices``
only, for any frames, by the same three paths and with the same result:

- a **Mesh Cache** (PC2/MDD) that can be read from its file
  (``caches.mesh_cache_direct_read_problem`` is None): the samples each frame needs
  are read straight from the memory-mapped file, for those vertices only;
- **shape-key animation** that the direct mix of ``shapekeys.shape_key_sequence`` handles:
  the key offsets are gathered once for the vertices, and a chunk costs the F-curve
  evaluation and one small product;
- anything else (Alembic, rigs, modifiers): frame by frame through the evaluated
  mesh (``caches.evaluate_frames``), keeping the vertices.

FaceLab's own keys are muted (left out of the mix) as in ``read_captured_frames``.
Positions are object-local, scene units, float32.
"""

from __future__ import annotations

import bpy
import numpy as np

from ..core.capture import meshcache, pointcache
from . import caches
from .ownership import as_prefixes, key_matches, owned_key_names
from .scene_time import require_scene_time
from .shapekeys import fcurve_for_key, finite_key_offsets, values_from_action_only

__all__ = ["CaptureReader"]


class CaptureReader:
    """Captured positions of ``vertices`` of ``obj`` on any frames, prepared once.

    Parameters
    ----------
    obj : bpy.types.Object
        The captured face mesh.
    vertices : (n,) int array_like, optional
        Vertex indices to read (default: all).
    mute_shape_keys_prefix : tuple of str
        Keys left out (FaceLab's recorded ``FL_*`` keys by default).
    cache_samples : bool
        With a Mesh Cache: its file's positions on those frames (what an Integrate cache carries
        keys by, ``cache_integrate``), whatever the shape keys and modifiers around it do.

    Attributes
    ----------
    path : {"mesh_cache", "shape_keys", "evaluate"}
        How the frames are read.

    Raises
    ------
    CacheFileError
        A cache file is missing or broken (``caches.check_capture_files``).
    """

    def __init__(self, obj, vertices=None, *, mute_shape_keys_prefix=caches.FACELAB_PREFIXES, cache_samples=False):
        caches.require_mesh_object(obj)
        require_scene_time(None, "Reading the capture", obj)  # the F-curves are read at the frames' own time
        self.obj, self.mute = obj, tuple(mute_shape_keys_prefix)
        n = len(obj.data.vertices)
        self.vertices = np.arange(n) if vertices is None else np.asarray(vertices, dtype=np.int64)
        caches.check_capture_files(obj)
        source = caches.sequence_source(obj, ignore_prefixes=self.mute)
        self.path = "evaluate"
        if source == "mesh_cache":
            md = caches.mesh_cache_modifier(obj)
            if cache_samples or caches.mesh_cache_direct_read_problem(obj, md, mute_prefixes=self.mute) is None:
                self._prepare_cache(md)
        elif source in ("shape_keys", "static") and self._prepare_keys():
            self.path = "shape_keys"

    # ------------------------------------------------------------------ preparation
    def _prepare_cache(self, md):
        self.path = "mesh_cache"
        self._md = md
        self._file = caches.cache_path(self.obj, md)
        self._info = pointcache.cache_info(self._file, md.cache_format)
        M = meshcache.axis_conversion_matrix(md.forward_axis, md.up_axis, tuple(md.flip_axis))
        self._axis = None if np.array_equal(M, np.eye(3)) else M.astype(np.float32)

    def _prepare_keys(self) -> bool:
        """Gather the key offsets of the vertices once; False when the direct mix does not apply."""
        obj, v = self.obj, self.vertices
        key = obj.data.shape_keys
        n = len(obj.data.vertices)
        if any(m.show_viewport for m in obj.modifiers):
            return False
        if key is not None:
            if not key.use_relative:
                return False
            if not values_from_action_only(key):
                return False

        def coords(data):
            c = np.empty(n * 3, np.float32)
            data.foreach_get("co", c)
            return c.reshape(n, 3)[v]

        if key is None:
            self._basis, self._curves, self._deltas = coords(obj.data.vertices), [], np.zeros((0, len(v) * 3),
                                                                                              np.float32)
            return True
        basis = key.reference_key
        skip, owned = as_prefixes(self.mute), set(owned_key_names(key, create=False))
        curves, deltas = [], []
        self._bad_keys = []
        for kb in key.key_blocks:
            if kb == basis or kb.mute or key_matches(key, kb.name, skip, owned):
                continue
            if kb.vertex_group:
                return False
            fc = fcurve_for_key(key, kb)
            curves.append((fc if fc is not None and not fc.mute else None, kb.value, kb.slider_min, kb.slider_max))
            deltas.append((coords(kb.data) - coords(kb.relative_key.data)).ravel())
            if not np.isfinite(deltas[-1]).all():  # checked against the values read (:meth:`_read_keys`)
                self._bad_keys.append((len(curves) - 1, kb, deltas[-1]))
                deltas[-1] = np.nan_to_num(deltas[-1], nan=0.0, posinf=0.0, neginf=0.0)
        self._basis = coords(basis.data)
        self._curves = curves
        self._deltas = np.stack(deltas) if deltas else np.zeros((0, len(v) * 3), np.float32)
        return True

    # ------------------------------------------------------------------ reading
    def read(self, scene_frames) -> np.ndarray:
        """(t, n, 3) float32 captured positions of :attr:`vertices` on ``scene_frames`` (subframes allowed)."""
        frames = np.asarray(scene_frames, dtype=np.float64).ravel()
        if self.path == "mesh_cache":
            return self._read_cache(frames)
        if self.path == "shape_keys":
            return self._read_keys(frames)
        out = np.empty((len(frames), len(self.vertices), 3), np.float32)
        for i, co in caches.iter_evaluated(self.obj, frames, mute_prefixes=self.mute):
            out[i] = co[self.vertices]
        return out

    def _read_keys(self, frames):
        t, n = len(frames), len(self.vertices)
        out = np.empty((t, n * 3), np.float32)
        if len(self._curves):
            W = np.empty((t, len(self._curves)), np.float32)
            for k, (fc, value, lo, hi) in enumerate(self._curves):
                w = np.array([fc.evaluate(f) for f in frames]) if fc is not None else np.full(t, value)
                W[:, k] = np.clip(w, lo, hi)
            for k, kb, offsets in getattr(self, "_bad_keys", ()):  # a key with NaN / inf: refused where it is on
                finite_key_offsets(self.obj, kb, offsets, frames, W[:, k], self.vertices)
            np.matmul(W, self._deltas, out=out)
            out += self._basis.ravel()
        else:
            out[:] = self._basis.ravel()
        return out.reshape(t, n, 3)

    def _samples(self, need):
        """(k, n, 3) float32 positions of the vertices in the file's samples ``need`` (memory-mapped)."""
        mm = pointcache.read_cache(self._file, fmt=self._md.cache_format, mmap=True)
        v = self.vertices
        need = np.asarray(need, dtype=np.int64)
        if len(need) and need[-1] - need[0] + 1 == len(need):  # consecutive samples (sorted, unique): one gather
            return np.take(mm[int(need[0]) : int(need[-1]) + 1], v, axis=1).astype(np.float32, copy=False)
        return np.stack([np.asarray(mm[int(s)][v], np.float32) for s in need])

    def _read_cache(self, frames):
        md, r = self._md, bpy.context.scene.render
        i0, i1, w = meshcache.mesh_cache_samples(
            frames, self._info, fps=caches.scene_fps(bpy.context.scene), time_mode=md.time_mode,
            play_mode=md.play_mode, frame_start=md.frame_start, frame_scale=md.frame_scale,
            interpolation=md.interpolation, eval_frame=md.eval_frame, eval_time=md.eval_time,
            eval_factor=md.eval_factor, frame_length=np.float32(r.frame_map_old) / np.float32(r.frame_map_new))
        out = meshcache.blend_samples(self._samples, i0, i1, w)
        if not np.isfinite(out).all():
            pointcache.check_finite_samples(self._info, out, i0)
        if self._axis is not None:
            out = out @ self._axis.T
        return out
