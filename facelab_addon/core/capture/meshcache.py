"""Blender's Mesh Cache modifier in NumPy: which cache samples it shows on a scene frame, and its axes.

Reproduces, in float32 as Blender computes it, how the *Mesh Cache* modifier
(Blender 5.0, ``MOD_meshcache.cc``) turns a scene frame into cache samples of
a PC2/MDD file (:mod:`.pointcache`), so the captured sequence ``(T,V,3)`` the
modifier shows can be read straight from the file. ``mesh_cache_samples``
maps scene frames to (sample, sample, weight) triples, ``blend_samples``
blends them, and ``axis_conversion_matrix`` gives the modifier's axis matrix;
they are checked against the evaluated modifier in
``tests/blender/test_caches.py``. Notable behaviour (all replicated here):

- ``time_mode='FRAME'``: sample index = ``frame_scale * ctime - frame_start``
  where ``ctime`` is the scene frame. The PC2 header's start frame and sample
  rate and the MDD times are *ignored*; sample 0 plays on scene frame
  ``frame_start`` (the default ``frame_start=0`` plays sample 1 on frame 1).
- ``time_mode='TIME'``: ``t = frame_scale * ctime / fps - frame_start``
  (``frame_start`` is then in seconds). MDD: the sample is found by searching
  the ``times`` array (linear between neighbours). PC2: Blender divides by
  the frame rate a second time, ``sample = (t / fps - startFrame) / sampleRate``
  (a long-standing quirk); it is reproduced, not fixed.
- ``time_mode='FACTOR'``: ``sample = clamp(t, 0, 1) * numSamples`` with ``t``
  as for ``'TIME'``.
- ``interpolation='LINEAR'`` blends the two neighbouring samples (snapped when
  the fraction is <= 1e-4), ``'NONE'`` rounds half up; out-of-range samples
  are clamped to the first / last one.
- Axes: the modifier sends the cache's +Y to ``forward_axis`` and +Z to
  ``up_axis``, then flips; the defaults (forward ``POS_Y``, up ``POS_Z``, no
  flip) are the identity. This is the inverse of what Blender's importers
  do with the same labels (see ``axis_conversion_matrix``).

Positions are object-local, scene units. No bpy in this module.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError
from .pointcache import CacheInfo, gather_f32

__all__ = ["mesh_cache_samples", "blend_samples", "axis_conversion_matrix"]

_FRAME_SNAP_EPS = np.float32(0.0001)  # MOD_meshcache_util.hh

_AXES = {"POS_X": 0, "POS_Y": 1, "POS_Z": 2, "NEG_X": 3, "NEG_Y": 4, "NEG_Z": 5}


def _axis_vector(name):
    k = _AXES[name]
    v = np.zeros(3)
    v[k % 3] = 1.0 if k < 3 else -1.0
    return v


def axis_conversion_matrix(forward_axis: str = "POS_Y", up_axis: str = "POS_Z", flip_axis=()) -> np.ndarray:
    """The 3x3 matrix the Mesh Cache modifier applies to the cache positions.

    Measured on Blender 5.0.1: the modifier sends the cache's +Y axis to
    ``forward_axis`` and its +Z axis to ``up_axis`` (and +X to forward x up),
    then negates the output components named in ``flip_axis``. Beware: this
    is the *inverse* (transpose) of ``bpy_extras.io_utils.axis_conversion(
    from_forward, from_up)``, the matrix Blender's importers build from the
    same labels. The defaults (forward ``POS_Y``, up ``POS_Z``, no flip) are
    the identity; a forward and up on the same axis (``POS_Z``/``NEG_Z``, ...)
    is ignored by Blender (identity too).

    Parameters
    ----------
    forward_axis, up_axis : {"POS_X", "POS_Y", "POS_Z", "NEG_X", "NEG_Y", "NEG_Z"}
    flip_axis : iterable of {"X", "Y", "Z"} or (3,) bools
        The modifier's ``flip_axis`` (a bool per axis, as bpy returns it, or axis names).

    Returns
    -------
    (3,3) float64 ndarray
        ``p_evaluated = M @ p_cache`` (dimensionless, orthogonal).
    """
    if forward_axis not in _AXES or up_axis not in _AXES:
        raise FaceLabError(f"Unknown axis '{forward_axis}'/'{up_axis}'; use one of {sorted(_AXES)}.")
    C = np.eye(3)
    if _AXES[forward_axis] % 3 != _AXES[up_axis] % 3:
        f, u = _axis_vector(forward_axis), _axis_vector(up_axis)
        C = np.stack([np.cross(f, u), f, u], axis=1)  # columns: images of +X, +Y, +Z
    flips = list(flip_axis)
    if len(flips) == 3 and all(isinstance(b, (bool, np.bool_)) for b in flips):
        flips = [a for a, b in zip("XYZ", flips) if b]
    D = np.diag([-1.0 if a in flips else 1.0 for a in "XYZ"])
    return D @ C


def mesh_cache_samples(
    scene_frames,
    info: CacheInfo,
    *,
    fps: float,
    time_mode: str = "FRAME",
    play_mode: str = "SCENE",
    frame_start: float = 0.0,
    frame_scale: float = 1.0,
    interpolation: str = "LINEAR",
    eval_frame: float = 0.0,
    eval_time: float = 0.0,
    eval_factor: float = 0.0,
    frame_length: float = 1.0,
):
    """Which cache samples a Mesh Cache modifier blends on each scene frame.

    Reproduces ``MOD_meshcache.cc`` (time interpretation), the PC2/MDD
    ``*_read_*_times`` readers and ``MOD_meshcache_calc_range`` in float32,
    as Blender computes them.

    Parameters
    ----------
    scene_frames : (T,) array_like of float
        Scene frames (fractional part = subframe).
    info : CacheInfo
        Header of the cache file (counts, PC2 start/rate, MDD times).
    fps : float
        Scene frame rate, ``render.fps / render.fps_base`` (frames per second).
    time_mode : {"FRAME", "TIME", "FACTOR"}
    play_mode : {"SCENE", "CUSTOM"}
    frame_start : float
        Modifier ``frame_start`` (frames in ``'FRAME'`` mode, seconds otherwise).
    frame_scale : float
        Modifier ``frame_scale``.
    interpolation : {"LINEAR", "NONE"}
    eval_frame, eval_time, eval_factor : float
        Modifier values used by ``play_mode='CUSTOM'``.
    frame_length : float
        Scene time remapping, ``render.frame_map_old / render.frame_map_new``
        (Blender's ``r.framelen``; ``ctime = frame * frame_length``).

    Returns
    -------
    i0, i1 : (T,) int64 ndarray
        Sample indices, 0-based.
    weight : (T,) float32 ndarray
        Blend factor of ``i1`` (the result is ``p[i0] * (1 - w) + p[i1] * w``;
        ``w`` is irrelevant where ``i0 == i1``).
    """
    f32 = np.float32
    frames = np.asarray(scene_frames, dtype=np.float64).reshape(-1)
    n = int(info.num_samples)
    fps32 = f32(fps)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if play_mode == "SCENE":
            cfra = np.floor(frames)
            ctime = ((cfra.astype(f32) + (frames - cfra).astype(f32)) * f32(frame_length)).astype(f32)
            if time_mode == "FRAME":
                t = ctime
            else:
                t = (ctime / fps32).astype(f32)
            t = (f32(frame_scale) * t - f32(frame_start)).astype(f32)
        elif play_mode == "CUSTOM":
            value = {"FRAME": eval_frame, "TIME": eval_time}.get(time_mode, eval_factor)
            t = np.full(len(frames), value, dtype=f32)
        else:
            raise FaceLabError(f"Unknown Mesh Cache play mode '{play_mode}'; use 'SCENE' or 'CUSTOM'.")

        if time_mode == "FRAME":
            s = t
        elif time_mode == "TIME":
            if info.format == "PC2":
                # Blender divides by fps again here (the time is already in seconds).
                s = (((t / fps32).astype(f32) - f32(info.start_frame)) / f32(info.sample_rate)).astype(f32)
                s = np.where(s >= f32(n), f32(n - 1), s)
                s = np.where(s < 0, f32(0), s).astype(f32)
            else:
                s = _mdd_time_to_sample(t, info.times.astype(f32))
        elif time_mode == "FACTOR":
            s = (np.clip(t, f32(0), f32(1)) * f32(n)).astype(f32)
        else:
            raise FaceLabError(f"Unknown Mesh Cache time mode '{time_mode}'; use 'FRAME', 'TIME' or 'FACTOR'.")

        s = s.astype(f32)
        if interpolation == "NONE":
            i = np.floor(s + f32(0.5)).astype(np.int64)
            i = np.clip(i, 0, n - 1)
            return i, i.copy(), np.ones(len(s), dtype=f32)
        if interpolation != "LINEAR":
            raise FaceLabError(f"Unknown Mesh Cache interpolation '{interpolation}'; use 'LINEAR' or 'NONE'.")
        tf = np.floor(s)
        rng = (s - tf).astype(f32)
        i0 = tf.astype(np.int64)
        snap = rng <= _FRAME_SNAP_EPS
        i1 = np.where(snap, i0, i0 + 1)
        w = np.where(snap, f32(1), rng).astype(f32)
        hi = (i0 >= n) | (i1 >= n)
        lo = ~hi & ((i0 < 0) | (i1 < 0))
        i0 = np.where(hi, n - 1, np.where(lo, 0, i0))
        i1 = np.where(hi, n - 1, np.where(lo, 0, i1))
        w = np.where(hi | lo, f32(1), w).astype(f32)
    return i0, i1, w


def _mdd_time_to_sample(t, times):
    """``meshcache_read_mdd_range_from_time`` for every time in ``t`` (float32)."""
    f32 = np.float32
    n = len(times)
    out = np.empty(len(t), dtype=f32)
    for k, tk in enumerate(t):
        hit = np.flatnonzero(times >= tk)
        if len(hit) == 0:  # every time is earlier: loop ran out, f_time == f_time_prev
            out[k] = f32(n)
            continue
        i = int(hit[0])
        if i == 0:
            out[k] = f32(0)
            continue
        f_time, f_prev = times[i], times[i - 1]
        rng = f32(f_time - f_prev)
        out[k] = f32(i) if rng <= _FRAME_SNAP_EPS else f32(f32(i - 1) + f32(f32(tk - f_prev) / rng))
    return out


def blend_samples(samples, i0, i1, weight) -> np.ndarray:
    """Blend cache samples the way the Mesh Cache modifier does (float32).

    Parameters
    ----------
    samples : callable or (S,V,3) array_like
        Either the samples themselves (an array or memmap indexed by sample
        index), or ``samples(indices (k,) int) -> (k,V,3)`` reading them.
    i0, i1 : (T,) int
        Sample indices from ``mesh_cache_samples``.
    weight : (T,) float32
        Blend factor of ``i1``.

    Returns
    -------
    (T,V,3) float32 ndarray
        ``p[i0] * (1 - w) + p[i1] * w`` (just ``p[i0]`` where ``i0 == i1``),
        positions in the cache's units.
    """
    i0 = np.asarray(i0, dtype=np.int64)
    i1 = np.asarray(i1, dtype=np.int64)
    w = np.asarray(weight, dtype=np.float32)
    need = np.unique(np.concatenate([i0, i1[i1 != i0]]))
    if callable(samples):
        block = np.asarray(samples(need), dtype=np.float32)
    else:
        block = gather_f32(samples if isinstance(samples, np.ndarray) else np.asarray(samples), need)
    pos = {int(s): k for k, s in enumerate(need)}
    out = np.empty((len(i0),) + block.shape[1:], dtype=np.float32)
    for t in range(len(i0)):
        a = block[pos[int(i0[t])]]
        if i1[t] == i0[t]:
            out[t] = a
        else:
            b = block[pos[int(i1[t])]]
            out[t] = a * (np.float32(1) - w[t]) + b * w[t]
    return out
