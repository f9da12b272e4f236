"""Point-cache files (PC2, MDD) and the sample mapping of Blender's Mesh Cache modifier.

A captured facial performance often reaches Blender as a vertex cache: a file
that stores every vertex position of every frame, played back by a *Mesh Cache*
modifier. This module reads and writes the two formats that modifier reads,
and reproduces, in NumPy, how the modifier turns a scene frame into cache
samples, so the captured sequence ``(T,V,3)`` can be read straight from the
file instead of evaluating Blender frame by frame.

Formats (exactly what Blender's ``MOD_meshcache_pc2.cc`` / ``_mdd.cc`` read)
-------------------------------------------------------------------------
PC2 (3ds Max *Point Cache 2*), little-endian::

    char[12]  b"POINTCACHE2\\0"
    int32     version (1)
    int32     numPoints
    float32   startFrame      (frames)
    float32   sampleRate      (frames between samples)
    int32     numSamples
    float32   xyz[numSamples][numPoints][3]

MDD (LightWave *Motion Designer*), big-endian, no magic number::

    int32     numFrames
    int32     numPoints
    float32   times[numFrames]   (seconds)
    float32   xyz[numFrames][numPoints][3]

Positions are object-local, scene units. Reading never converts to float64:
``mmap=True`` returns a read-only ``np.memmap`` view of the file, and
``frames=`` reads only the requested samples, so 1000 frames of a
26,719-vertex face (320 MB of float32) need not be loaded at once.

Mesh Cache modifier semantics (Blender 5.0, ``MOD_meshcache.cc``)
------------------------------------------------------------------
``mesh_cache_samples`` maps scene frames to (sample, sample, weight) triples
and ``axis_conversion_matrix`` gives the modifier's axis matrix; both are
checked against the evaluated modifier in ``tests/blender/test_caches.py``.
Notable behaviour (all replicated here):

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

No bpy in this module.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CacheFileError, CacheVertexCountError, FaceLabError, MeshError  # noqa: F401

__all__ = [
    "CacheFileError",
    "CacheVertexCountError",
    "CacheInfo",
    "PC2_MAGIC",
    "pc2_info",
    "mdd_info",
    "cache_info",
    "check_vertex_count",
    "read_pc2",
    "write_pc2",
    "read_mdd",
    "write_mdd",
    "read_cache",
    "PointCacheWriter",
    "mesh_cache_samples",
    "blend_samples",
    "axis_conversion_matrix",
    "integrate_matrices",
    "integrate_offsets_to_key",
]

PC2_MAGIC = b"POINTCACHE2\0"
_PC2_HEADER_BYTES = 32
_PC2_HEADER = np.dtype(
    [
        ("magic", "S12"),
        ("version", "<i4"),
        ("num_points", "<i4"),
        ("start_frame", "<f4"),
        ("sample_rate", "<f4"),
        ("num_samples", "<i4"),
    ]
)
_FRAME_SNAP_EPS = np.float32(0.0001)  # MOD_meshcache_util.hh


@dataclass(frozen=True)
class CacheInfo:
    """Header of a point-cache file.

    Attributes
    ----------
    path : str
    format : str
        ``"PC2"`` or ``"MDD"``.
    num_points : int
        V, points per sample.
    num_samples : int
        T, samples in the file.
    start_frame : float or None
        PC2 only: frame of sample 0 (frames).
    sample_rate : float or None
        PC2 only: frames between two samples.
    times : (T,) float32 ndarray or None
        MDD only: time of every sample, seconds.
    data_offset : int
        Byte offset of the first coordinate.
    dtype : numpy.dtype
        On-disk dtype of the coordinates (``<f4`` for PC2, ``>f4`` for MDD).
    """

    path: str
    format: str
    num_points: int
    num_samples: int
    start_frame: float | None
    sample_rate: float | None
    times: np.ndarray | None
    data_offset: int
    dtype: np.dtype

    @property
    def nbytes(self) -> int:
        """Bytes of coordinate data, ``T * V * 12``."""
        return self.num_samples * self.num_points * 12


# --------------------------------------------------------------------------- headers


def _open_size(path, what):
    p = Path(os.fspath(path))
    if not p.is_file():
        raise CacheFileError(
            f"{what} file not found: '{p}'. Check the path (a Mesh Cache modifier's path is "
            "relative to the .blend when it starts with //)."
        )
    return p, p.stat().st_size


def _check_data_size(p, size, offset, T, V, what):
    need = offset + T * V * 12
    if size < need:
        have = max(size - offset, 0) // (V * 12) if V > 0 else 0
        raise CacheFileError(
            f"{what} file '{p}' is truncated: its header announces {T} samples of {V} points "
            f"({need} bytes) but the file has {size} bytes (about {have} whole samples). "
            "Re-export or re-copy the cache."
        )


def pc2_info(path) -> CacheInfo:
    """Read and check the header of a PC2 file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    CacheInfo

    Raises
    ------
    CacheFileError
        Missing file, wrong magic (not ``b"POINTCACHE2\\0"``), a non-positive
        point or sample count, or a file shorter than its header announces.
    """
    p, size = _open_size(path, "PC2")
    if size < _PC2_HEADER_BYTES:
        raise CacheFileError(
            f"PC2 file '{p}' is truncated: {size} bytes, shorter than the 32-byte header. "
            "Re-export the cache."
        )
    with open(p, "rb") as f:
        raw = f.read(_PC2_HEADER_BYTES)
    if raw[:12] != PC2_MAGIC:
        hint = ""
        if raw[:11] == PC2_MAGIC[:11]:
            hint = " (the magic is not NUL-terminated)"
        raise CacheFileError(
            f"'{p}' is not a PC2 file: it starts with {raw[:12]!r} instead of {PC2_MAGIC!r}{hint}. "
            "Pick a .pc2 point cache, or set the Mesh Cache format to MDD if it is an MDD file."
        )
    h = np.frombuffer(raw, dtype=_PC2_HEADER)[0]
    V, T = int(h["num_points"]), int(h["num_samples"])
    if V <= 0 or T <= 0:
        raise CacheFileError(
            f"PC2 file '{p}' has {V} points and {T} samples in its header; a cache needs at least "
            "one of each. Re-export the cache."
        )
    _check_data_size(p, size, _PC2_HEADER_BYTES, T, V, "PC2")
    return CacheInfo(
        path=str(p),
        format="PC2",
        num_points=V,
        num_samples=T,
        start_frame=float(h["start_frame"]),
        sample_rate=float(h["sample_rate"]),
        times=None,
        data_offset=_PC2_HEADER_BYTES,
        dtype=np.dtype("<f4"),
    )


def mdd_info(path) -> CacheInfo:
    """Read and check the header (counts and time table) of an MDD file.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    CacheInfo
        ``times`` holds the (T,) float32 sample times in seconds.

    Raises
    ------
    CacheFileError
        Missing file, a PC2 file given as MDD, implausible counts (for
        example a little-endian file) or a file shorter than announced.
    """
    p, size = _open_size(path, "MDD")
    if size < 8:
        raise CacheFileError(f"MDD file '{p}' is truncated: {size} bytes, shorter than the 8-byte header.")
    with open(p, "rb") as f:
        head = f.read(12)
    if head == PC2_MAGIC:
        raise CacheFileError(
            f"'{p}' is a PC2 file, not an MDD file. Set the Mesh Cache format to PC2 (or read it with read_pc2)."
        )
    T, V = (int(x) for x in np.frombuffer(head[:8], dtype=">i4"))
    if T <= 0 or V <= 0:
        raise CacheFileError(
            f"MDD file '{p}' has {T} frames and {V} points in its header; a cache needs at least one "
            "of each. Is it really an MDD file (big-endian)? Re-export the cache."
        )
    offset = 8 + 4 * T
    need = offset + T * V * 12
    if size < need and size >= 8:
        # A little-endian writer produces absurd counts; say so instead of "truncated".
        Tl, Vl = (int(x) for x in np.frombuffer(head[:8], dtype="<i4"))
        if Tl > 0 and Vl > 0 and 8 + 4 * Tl + 12 * Tl * Vl == size:
            raise CacheFileError(
                f"MDD file '{p}' is little-endian ({Tl} frames, {Vl} points); MDD must be big-endian. "
                "Re-export it with an MDD writer that follows the format (Blender's, or FaceLab's write_mdd)."
            )
    _check_data_size(p, size, offset, T, V, "MDD")
    times = np.fromfile(p, dtype=">f4", count=T, offset=8).astype(np.float32)
    return CacheInfo(
        path=str(p),
        format="MDD",
        num_points=V,
        num_samples=T,
        start_frame=None,
        sample_rate=None,
        times=times,
        data_offset=offset,
        dtype=np.dtype(">f4"),
    )


def cache_info(path, fmt: str | None = None) -> CacheInfo:
    """Header of a PC2 or MDD file.

    Parameters
    ----------
    path : str or os.PathLike
    fmt : {"PC2", "MDD"}, optional
        Default: ``"PC2"`` when the file starts with the PC2 magic, else MDD.

    Returns
    -------
    CacheInfo
    """
    if fmt is None:
        p, size = _open_size(path, "Point cache")
        with open(p, "rb") as f:
            fmt = "PC2" if f.read(12) == PC2_MAGIC else "MDD"
    fmt = fmt.upper()
    if fmt == "PC2":
        return pc2_info(path)
    if fmt == "MDD":
        return mdd_info(path)
    raise CacheFileError(f"Unknown point-cache format '{fmt}'; use 'PC2' or 'MDD'.")


def check_vertex_count(info: CacheInfo, num_vertices: int, *, name: str = "the mesh") -> CacheInfo:
    """Raise unless the cache has one point per mesh vertex.

    Parameters
    ----------
    info : CacheInfo
    num_vertices : int
        V of the mesh the cache is played on.
    name : str
        The mesh/object name, for the message.

    Returns
    -------
    CacheInfo
        ``info``, unchanged.

    Raises
    ------
    CacheVertexCountError
        (a ``CacheFileError`` and a ``MeshError``) when the counts differ.
    """
    if info.num_points != int(num_vertices):
        raise CacheVertexCountError(
            f"{info.format} cache '{info.path}' has {info.num_points} points but {name} has "
            f"{int(num_vertices)} vertices. Use the cache exported from this mesh (same topology, "
            "no modifiers that add or remove vertices), or re-export it."
        )
    return info


# --------------------------------------------------------------------------- reading


def _sample_index(frames, T, path):
    idx = np.asarray(frames)
    if idx.dtype == bool:
        raise CacheFileError("frames= must be sample indices (ints), not a mask; use np.flatnonzero(mask).")
    if not np.issubdtype(idx.dtype, np.integer):
        raise CacheFileError(
            f"frames= must be integer sample indices (0-based), got dtype {idx.dtype}; "
            "convert scene frames with mesh_cache_samples first."
        )
    idx = idx.astype(np.int64).reshape(-1)
    bad = (idx < -T) | (idx >= T)
    if bad.any():
        raise CacheFileError(
            f"Sample indices {idx[bad][:5].tolist()} are outside the {T} samples of '{path}' "
            f"(valid: 0..{T - 1}); ask for samples the cache has."
        )
    return np.where(idx < 0, idx + T, idx)


def _gather_f32(source, idx=None) -> np.ndarray:
    """Samples ``source[idx]`` (all when None) as a new native float32 (k,V,3) array.

    Copies one sample at a time, so a memmap (any byte order) is read once
    and no temporary of the whole selection is made.
    """
    n = len(source) if idx is None else len(idx)
    out = np.empty((n,) + tuple(source.shape[1:]), dtype=np.float32)
    for k in range(n):
        out[k] = source[k if idx is None else int(idx[k])]
    return out


def _read_samples(info: CacheInfo, frames, mmap: bool) -> np.ndarray:
    shape = (info.num_samples, info.num_points, 3)
    mm = np.memmap(info.path, dtype=info.dtype, mode="r", offset=info.data_offset, shape=shape)
    if frames is None:
        return mm if mmap else _gather_f32(mm)
    return _gather_f32(mm, _sample_index(frames, info.num_samples, info.path))


def read_pc2(path, frames=None, *, mmap: bool = False):
    """Read a PC2 point cache.

    Parameters
    ----------
    path : str or os.PathLike
    frames : array_like of int, optional
        0-based sample indices to read (in any order, repeats allowed). Only
        these samples are read from disk. Default: all samples.
    mmap : bool
        With ``frames=None``, return a read-only ``np.memmap`` of shape
        (T,V,3) (dtype ``<f4``, native on little-endian machines) instead of
        loading the file: nothing is copied until it is indexed.

    Returns
    -------
    frames : (T,V,3) float32 ndarray (or np.memmap)
        Object-local positions, scene units. T is ``len(frames)`` when given.
    start_frame : float
        Header start frame (frames).
    sample_rate : float
        Header sample rate (frames between samples).

    Raises
    ------
    CacheFileError
        See ``pc2_info``; also for out-of-range ``frames``.
    """
    info = pc2_info(path)
    return _read_samples(info, frames, mmap), info.start_frame, info.sample_rate


def read_mdd(path, frames=None, *, mmap: bool = False):
    """Read an MDD point cache.

    Parameters
    ----------
    path : str or os.PathLike
    frames : array_like of int, optional
        0-based sample indices to read. Default: all samples.
    mmap : bool
        With ``frames=None``, return a read-only ``np.memmap`` of shape
        (T,V,3) with the on-disk big-endian dtype ``>f4`` (NumPy computes
        with it transparently; ``np.asarray(x, np.float32)`` converts).

    Returns
    -------
    frames : (T,V,3) float32 ndarray (or np.memmap)
        Object-local positions, scene units.
    times : (T,) float32 ndarray
        Sample times in seconds (of the returned samples when ``frames`` is
        given).

    Raises
    ------
    CacheFileError
        See ``mdd_info``; also for out-of-range ``frames``.
    """
    info = mdd_info(path)
    data = _read_samples(info, frames, mmap)
    times = info.times if frames is None else info.times[_sample_index(frames, info.num_samples, info.path)]
    return data, times


def read_cache(path, frames=None, *, fmt: str | None = None, mmap: bool = False):
    """Positions of a PC2 or MDD file, whichever it is.

    Parameters
    ----------
    path : str or os.PathLike
    frames : array_like of int, optional
        0-based sample indices. Default: all.
    fmt : {"PC2", "MDD"}, optional
        Default: detected from the file.
    mmap : bool
        See ``read_pc2``.

    Returns
    -------
    (T,V,3) float32 ndarray
        Object-local positions, scene units.
    """
    info = cache_info(path, fmt)
    return _read_samples(info, frames, mmap)


# --------------------------------------------------------------------------- writing


def _check_frames(frames, what="frames"):
    a = np.asarray(frames)
    if a.ndim == 2 and a.shape[1] == 3:
        a = a[None]
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] == 0 or a.shape[1] == 0:
        raise MeshError(f"{what} must be a non-empty (T,V,3) array of positions, got shape {a.shape}.")
    if not np.issubdtype(a.dtype, np.number):
        raise MeshError(f"{what} must be numeric, got dtype {a.dtype}.")
    return a


class PointCacheWriter:
    """Write a PC2 or MDD file sample by sample (for bakes that never hold (T,V,3)).

    The file is written to ``<path>.tmp`` and moved onto ``path`` only when
    all ``num_samples`` samples were written and the writer is closed, so a
    failed bake never leaves a truncated file (nor clobbers the cache that
    is being read while baking).

    Parameters
    ----------
    path : str or os.PathLike
    fmt : {"PC2", "MDD"}
    num_points : int
        V.
    num_samples : int
        T, announced in the header.
    start_frame : float
        PC2 header start frame (frames).
    sample_rate : float
        PC2 header sample rate (frames between samples).
    times : (T,) array_like, optional
        MDD sample times in seconds (required for MDD).

    Examples
    --------
    >>> with PointCacheWriter("a.pc2", "PC2", V, T, start_frame=1.0) as w:  # doctest: +SKIP
    ...     for co in frames:
    ...         w.write(co)            # (V,3)
    """

    def __init__(self, path, fmt, num_points, num_samples, *, start_frame=1.0, sample_rate=1.0, times=None):
        self.path = Path(os.fspath(path))
        self.format = str(fmt).upper()
        self.num_points = int(num_points)
        self.num_samples = int(num_samples)
        if self.num_points <= 0 or self.num_samples <= 0:
            raise MeshError(
                f"A point cache needs at least one point and one sample (got {self.num_points} points, "
                f"{self.num_samples} samples)."
            )
        if self.format == "PC2":
            self._dtype = np.dtype("<f4")
            header = np.zeros(1, dtype=_PC2_HEADER)
            header["magic"] = PC2_MAGIC
            header["version"] = 1
            header["num_points"] = self.num_points
            header["start_frame"] = start_frame
            header["sample_rate"] = sample_rate
            header["num_samples"] = self.num_samples
            head = header.tobytes()
            assert len(head) == _PC2_HEADER_BYTES and head[:12] == PC2_MAGIC
        elif self.format == "MDD":
            if times is None:
                raise MeshError("MDD needs one time per sample (seconds); pass times=.")
            t = np.asarray(times, dtype=np.float64).reshape(-1)
            if len(t) != self.num_samples or not np.isfinite(t).all():
                raise MeshError(f"MDD times must be {self.num_samples} finite values in seconds, got {len(t)}.")
            self._dtype = np.dtype(">f4")
            head = np.array([self.num_samples, self.num_points], dtype=">i4").tobytes() + t.astype(">f4").tobytes()
        else:
            raise CacheFileError(f"Unknown point-cache format '{fmt}'; use 'PC2' or 'MDD'.")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._f = open(self._tmp, "wb")
        self._f.write(head)
        self.written = 0

    def write(self, positions) -> None:
        """Append samples.

        Parameters
        ----------
        positions : (V,3) or (k,V,3) array_like
            Object-local positions, scene units; must be finite.
        """
        a = _check_frames(positions, "positions")
        if a.shape[1] != self.num_points:
            raise CacheVertexCountError(
                f"Sample has {a.shape[1]} points but the cache '{self.path}' was opened for {self.num_points}; "
                "the mesh changed its vertex count during the bake (disable topology-changing modifiers)."
            )
        if self.written + len(a) > self.num_samples:
            raise MeshError(f"More samples than announced ({self.num_samples}) for '{self.path}'.")
        for k in range(len(a)):  # one sample at a time: no (T,V,3) temporaries
            s = a[k]
            if not np.isfinite(s).all():
                raise MeshError(
                    f"Sample {self.written} has NaN or infinite positions; fix the mesh on that frame before baking."
                )
            self._f.write(np.ascontiguousarray(s, dtype=self._dtype).tobytes())
            self.written += 1

    def close(self) -> Path:
        """Finish the file (moved from ``.tmp`` onto ``path``) and return its path.

        Raises
        ------
        MeshError
            When fewer samples than announced were written (the partial file is removed).
        """
        if self._f is None:
            return self.path
        self._f.close()
        self._f = None
        if self.written != self.num_samples:
            self._tmp.unlink(missing_ok=True)
            raise MeshError(
                f"Only {self.written} of {self.num_samples} samples were written to '{self.path}'; nothing was saved."
            )
        os.replace(self._tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Drop the partial file; ``path`` is left as it was."""
        if self._f is not None:
            self._f.close()
            self._f = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self.abort()
            return False
        self.close()
        return False


def write_pc2(path, frames, start=1.0, sample_rate=1.0) -> Path:
    """Write a PC2 point cache.

    Parameters
    ----------
    path : str or os.PathLike
    frames : (T,V,3) array_like
        Object-local positions, scene units (any float dtype; stored float32).
        A single (V,3) frame is accepted as T=1.
    start : float
        Header start frame (frames), the frame of sample 0.
    sample_rate : float
        Header sample rate: frames between two samples (1 = every frame).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    MeshError
        On a wrong shape or NaN/inf positions (nothing is written).
    """
    a = _check_frames(frames)
    with PointCacheWriter(path, "PC2", a.shape[1], a.shape[0], start_frame=start, sample_rate=sample_rate) as w:
        w.write(a)
    return w.path


def write_mdd(path, frames, fps=24.0, start_frame=1, *, times=None) -> Path:
    """Write an MDD point cache (big-endian).

    Parameters
    ----------
    path : str or os.PathLike
    frames : (T,V,3) array_like
        Object-local positions, scene units.
    fps : float
        Frames per second used for the time table.
    start_frame : float
        Scene frame of sample 0. Sample ``i`` gets the time
        ``(start_frame + i) / fps`` seconds, Blender's clock (scene frame
        ``f`` is at ``f / fps`` s), so a Mesh Cache modifier in
        ``time_mode='TIME'`` with ``frame_start=0`` plays sample ``i`` on
        scene frame ``start_frame + i``.
    times : (T,) array_like, optional
        Explicit sample times (seconds); overrides ``fps``/``start_frame``.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    MeshError
        On a wrong shape, NaN/inf positions or a non-positive ``fps``.
    """
    a = _check_frames(frames)
    if times is None:
        if not fps > 0:
            raise MeshError(f"fps must be positive, got {fps}.")
        times = (float(start_frame) + np.arange(a.shape[0], dtype=np.float64)) / float(fps)
    with PointCacheWriter(path, "MDD", a.shape[1], a.shape[0], times=times) as w:
        w.write(a)
    return w.path


# --------------------------------------------------------------------------- Mesh Cache modifier mapping

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
        block = _gather_f32(samples if isinstance(samples, np.ndarray) else np.asarray(samples), need)
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


def integrate_matrices(rest, deformed, face_offsets, corner_verts) -> np.ndarray:
    """Per-vertex 3x3 maps of the Mesh Cache modifier's ``'INTEGRATE'`` mode.

    In ``deform_mode='INTEGRATE'`` Blender (``BKE_mesh_calc_relative_deform``)
    does not add a shape key's offset ``d`` to the cache position; it carries
    it in the local frame of every face corner (``barycentric_transform``) and
    averages over the corners of the vertex, so the evaluated position is
    ``deformed[v] + M[v] @ d[v]``: exact addition where the cache is a
    translation of the rest mesh, ``R @ d`` where it is rotated by ``R``,
    ``s * d`` where scaled by ``s``. A correction ``delta`` wanted *on top of*
    cache frame ``t`` must therefore be stored as the key offset
    ``solve(M[v], delta[v])`` (``integrate_offsets_to_key``).

    Parameters
    ----------
    rest : (V,3) array_like
        The mesh's own vertex positions (``mesh.vertices.co``, the Basis),
        object-local scene units.
    deformed : (V,3) array_like
        The cache positions on the frame, after the modifier's axis matrix
        (what the modifier shows with the keys muted).
    face_offsets : (P+1,) array_like of int
        Start of each polygon in ``corner_verts`` (``polygons.loop_start``
        plus the total corner count).
    corner_verts : (C,) array_like of int
        Vertex of every polygon corner (``loops.vertex_index``).

    Returns
    -------
    (V,3,3) float64 ndarray
        Linear maps (dimensionless); all zeros for vertices on no face (Blender
        drops the offset of loose vertices).
    """
    S = np.asarray(rest, dtype=np.float64)
    O = np.asarray(deformed, dtype=np.float64)
    off = np.asarray(face_offsets, dtype=np.int64)
    cv = np.asarray(corner_verts, dtype=np.int64)
    sizes = np.diff(off)
    face_of = np.repeat(np.arange(len(sizes)), sizes)
    local = np.arange(len(cv)) - off[face_of]
    n = sizes[face_of]
    prev = cv[off[face_of] + (local - 1) % n]
    nxt = cv[off[face_of] + (local + 1) % n]
    cur = cv

    def frame(P, scale_normal_by=None):
        e1 = P[prev] - P[cur]
        e2 = P[nxt] - P[cur]
        nrm = np.cross(P[cur] - P[prev], P[nxt] - P[cur])  # normal_tri_v3(prev, cur, next)
        area2 = np.linalg.norm(nrm, axis=1)
        nrm = nrm / np.where(area2 > 0, area2, 1.0)[:, None]
        return e1, e2, nrm, 0.5 * area2

    e1s, e2s, ns, As = frame(S)
    e1o, e2o, no, Ao = frame(O)
    k = np.sqrt(Ao / np.where(As > 0, As, 1.0))
    Bs = np.stack([e1s, e2s, ns], axis=2)  # (C,3,3) columns
    Bo = np.stack([e1o, e2o, no * k[:, None]], axis=2)
    ok = As > 0
    L = np.zeros((len(cv), 3, 3))
    if ok.any():
        L[ok] = Bo[ok] @ np.linalg.inv(Bs[ok])
    Vn = len(S)
    M = np.zeros((Vn, 3, 3))
    np.add.at(M, cur, L)
    cnt = np.bincount(cur, minlength=Vn).astype(np.float64)
    M /= np.where(cnt > 0, cnt, 1.0)[:, None, None]
    return M


def integrate_offsets_to_key(matrices, deltas) -> np.ndarray:
    """Shape-key offsets that show as ``deltas`` on top of an ``'INTEGRATE'`` Mesh Cache.

    Parameters
    ----------
    matrices : (V,3,3) array_like
        From ``integrate_matrices`` for the frame the correction is made on.
    deltas : (V,3) array_like
        Wanted displacement of the evaluated mesh on that frame,
        object-local scene units.

    Returns
    -------
    (V,3) float64 ndarray
        Offsets to store in the shape key (key = Basis + offsets), scene
        units. Vertices whose map is singular (loose vertices) get the least
        squares solution (zero for a zero map).
    """
    M = np.asarray(matrices, dtype=np.float64)
    d = np.asarray(deltas, dtype=np.float64)
    out = np.zeros_like(d)
    det = np.linalg.det(M)
    good = np.abs(det) > 1e-12
    if good.any():
        out[good] = np.linalg.solve(M[good], d[good][..., None])[..., 0]
    for v in np.flatnonzero(~good):
        out[v] = np.linalg.lstsq(M[v], d[v], rcond=None)[0]
    return out
