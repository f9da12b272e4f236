"""Writing PC2 and MDD point-cache files, sample by sample.

The byte layouts are those read by :mod:`.pointcache` (and by Blender's Mesh
Cache modifier). :class:`PointCacheWriter` writes one (V,3) sample at a time,
so a bake never holds the whole (T,V,3) sequence, into ``<path>.tmp``, which
replaces ``path`` only when every announced sample was written.
``write_pc2`` / ``write_mdd`` write a whole array at once. A stored per-frame correction is written
as a cache of fixed positions plus the correction, a block of frames at a time
(:func:`correction_layout`, :func:`write_offset_cache`).

Positions are object-local, scene units, stored as float32 (little-endian for
PC2, big-endian for MDD); MDD sample times are in seconds. No bpy in this
module.
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CacheFileError, CacheVertexCountError, FaceLabError, MeshError, OutputError
from .pointcache import PC2_HEADER, PC2_HEADER_BYTES, PC2_MAGIC

__all__ = ["PointCacheWriter", "write_pc2", "write_mdd", "check_writable", "check_name_length", "output_error",
           "CacheLayout", "correction_layout", "write_offset_cache"]


def output_error(path, err: OSError) -> OutputError:
    """An :class:`~facelab_addon.core.errors.OutputError` naming ``path``, what the system refused and the fix."""
    p = Path(os.fspath(path))
    if isinstance(err, PermissionError):
        why = "permission denied (a read-only folder or file)"
    elif isinstance(err, (FileExistsError, NotADirectoryError)):
        why = "a part of the path is a file, not a folder"
    elif isinstance(err, IsADirectoryError):
        why = "it is a folder"
    elif getattr(err, "errno", None) == 28:
        why = "the disk is full"
    elif getattr(err, "errno", None) == errno.ENAMETOOLONG:
        why = "the name is longer than the file system allows"
    else:
        why = err.strerror or type(err).__name__
    return OutputError(f"Cannot write '{p}': {why}. Choose a file in a writable folder (or free disk space).")


#: File-name and path limits (bytes) when the file system does not say (``os.pathconf``): Linux, macOS.
NAME_MAX, PATH_MAX = 255, 4096
#: What the writers append to a file's name while it is written (``<name>.tmp``).
TMP_SUFFIX = ".tmp"


def check_name_length(path) -> Path:
    """Refuse a path the file system cannot hold: a name over its limit (255 bytes on common file
    systems; the name plus :data:`TMP_SUFFIX`, which the writers use meanwhile) or a path over 4,096 bytes.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    pathlib.Path

    Raises
    ------
    OutputError
        Naming the over-long part, its length in bytes and the limit.
    """
    p = Path(os.fspath(path))
    anc = p.parent
    try:
        while not anc.is_dir() and anc != anc.parent:
            anc = anc.parent
    except OSError:  # a parent name itself too long
        anc = Path(p.anchor or ".")
    try:
        name_max = os.pathconf(anc, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        name_max = NAME_MAX
    full = len(os.fsencode(p))
    if full > PATH_MAX:
        raise OutputError(f"Cannot write '{p}': the path is {full:,} bytes long, more than the {PATH_MAX:,} the "
                          "system allows. Choose a shorter folder or file name.")
    extra = len(TMP_SUFFIX.encode())
    for part, last in [(x, False) for x in p.parts[1 if p.anchor else 0:-1]] + [(p.name, True)]:
        n = len(os.fsencode(part))
        if n + (extra if last else 0) > name_max:
            tmp = f" (plus the {extra} of the '{TMP_SUFFIX}' the writer adds meanwhile)" if last else ""
            raise OutputError(
                f"Cannot write '{p}': the name '{part[:40]}…' is {n} bytes long in UTF-8{tmp}, more than the file "
                f"system's limit of {name_max} bytes. Give the .blend, the object or the file a shorter name "
                "(non-Latin letters take 2-4 bytes each), or choose a shorter file name.")
    return p


def check_writable(path) -> Path:
    """Refuse, before any work, a destination file that cannot be written.

    The nearest existing folder of ``path`` must be a folder a file can be
    created in (probed with a temporary file, removed at once; the missing
    folders are created by the writers), and ``path`` itself must not be a
    folder.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    OutputError
        ``path`` is a folder, a parent is a file, the folder is not writable,
        or ``path`` exists and is read-only.
    """
    p = Path(os.fspath(path))
    check_name_length(p)
    if p.is_dir():
        raise OutputError(f"Cannot write '{p}': it is a folder. Give a file name, such as '{p / 'capture.pc2'}'.")
    anc = p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if anc.exists() and not anc.is_dir():
        raise OutputError(f"Cannot write '{p}': '{anc}' is a file, not a folder. Choose another path.")
    if anc.is_dir():
        try:  # a real probe: permission bits do not tell (root, read-only mounts, /sys)
            with tempfile.TemporaryFile(dir=anc):
                pass
        except OSError as e:
            raise output_error(p, e) from None
    if p.is_file() and not os.access(p, os.W_OK):
        raise OutputError(f"Cannot write '{p}': the file exists and is read-only. Choose another file, or make it "
                          "writable.")
    return p


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

    Raises
    ------
    OutputError
        The destination cannot be written (read-only folder, a parent that
        is a file, disk full), here or in :meth:`write` / :meth:`close`.

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
            header = np.zeros(1, dtype=PC2_HEADER)
            header["magic"] = PC2_MAGIC
            header["version"] = 1
            header["num_points"] = self.num_points
            header["start_frame"] = start_frame
            header["sample_rate"] = sample_rate
            header["num_samples"] = self.num_samples
            head = header.tobytes()
            assert len(head) == PC2_HEADER_BYTES and head[:12] == PC2_MAGIC
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
        check_writable(self.path)
        self._tmp = self.path.with_name(self.path.name + TMP_SUFFIX)
        self._f = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self._tmp, "wb")
            self._f.write(head)
        except OSError as e:
            self.abort()
            raise output_error(self.path, e) from None
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
            try:
                self._f.write(np.ascontiguousarray(s, dtype=self._dtype).tobytes())
            except OSError as e:
                self.abort()
                raise output_error(self.path, e) from None
            self.written += 1

    def close(self) -> Path:
        """Finish the file (moved from ``.tmp`` onto ``path``) and return its path.

        Raises
        ------
        MeshError
            When fewer samples than announced were written (the partial file is removed).
        OutputError
            When the file cannot be moved in place (the partial file is removed).
        """
        if self._f is None:
            return self.path
        try:
            self._f.close()
        except OSError as e:
            self._f = None
            self.abort()
            raise output_error(self.path, e) from None
        self._f = None
        if self.written != self.num_samples:
            self._tmp.unlink(missing_ok=True)
            raise MeshError(
                f"Only {self.written} of {self.num_samples} samples were written to '{self.path}'; nothing was saved."
            )
        try:
            os.replace(self._tmp, self.path)
        except OSError as e:
            self.abort()
            raise output_error(self.path, e) from None
        return self.path

    def abort(self) -> None:
        """Drop the partial file; ``path`` is left as it was."""
        if self._f is not None:
            with contextlib.suppress(OSError):
                self._f.close()
            self._f = None
        with contextlib.suppress(OSError):
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
    OutputError
        The destination cannot be written.
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


@dataclass
class CacheLayout:
    """Which samples a correction cache holds (:func:`correction_layout`).

    Attributes
    ----------
    format : str
        ``"PC2"`` or ``"MDD"``.
    frames : (T,) float64 ndarray
        The scene frame of each row of the stored correction.
    span : (S,) float64 ndarray
        The scene frames of the file's samples: whole frames from the first stored frame to the last, or the
        evenly spaced stored frames.
    rows : dict
        Scene frame (rounded to 1e-6) -> index of that frame in the stored correction; span frames without a
        correction are absent (they hold the fixed positions alone).
    header : dict
        The ``PointCacheWriter`` timing keywords (PC2: ``start_frame``, ``sample_rate``; MDD: ``times``, s).
    """

    format: str
    frames: np.ndarray
    span: np.ndarray
    rows: dict
    header: dict

    def row(self, frame):
        """The stored correction's index of scene ``frame``, or None."""
        return self.rows.get(float(round(frame, 6)))


def _evenly_spaced(frames) -> bool:
    if len(frames) < 2:
        return True
    d = np.diff(frames)
    return bool((d > 0).all() and np.allclose(d, d[0], rtol=0, atol=1e-6))


def correction_layout(frames, fmt: str, fps: float) -> CacheLayout:
    """The samples of a cache holding a correction stored on scene ``frames``.

    Parameters
    ----------
    frames : (T,) float array_like
        Scene frames of the correction's rows, whole or evenly spaced.
    fmt : {"PC2", "MDD"}
    fps : float
        Scene frames per second (MDD sample times).

    Returns
    -------
    CacheLayout

    Raises
    ------
    FaceLabError
        Frames neither whole nor evenly spaced.
    """
    frames = np.asarray(frames, dtype=np.float64)
    fmt = str(fmt).upper()
    if np.allclose(frames, np.round(frames)):
        span = np.arange(int(round(frames.min())), int(round(frames.max())) + 1, dtype=np.float64)
    elif _evenly_spaced(np.sort(frames)):
        span = np.sort(frames)
    else:
        raise FaceLabError("A correction cache needs whole or evenly spaced frames; store it on whole frames.")
    rows = {float(round(f, 6)): i for i, f in enumerate(frames)}
    header = dict(start_frame=float(span[0]), sample_rate=1.0) if fmt == "PC2" else dict(times=span / float(fps))
    return CacheLayout(fmt, frames, span, rows, header)


def write_offset_cache(path, layout: CacheLayout, read, base, vertices=None) -> None:
    """Write ``base`` plus the correction on ``vertices`` for every sample of ``layout``, a block at a time.

    Parameters
    ----------
    path : str or os.PathLike
    layout : CacheLayout
    read : callable
        ``read(i, j)``: the correction's rows ``i:j`` (j - i, n, 3), scene units.
    base : (m, 3) float array_like
        Positions every sample starts from (object local, scene units; zeros for a cache of the correction alone).
    vertices : (n,) int array_like, optional
        Rows of ``base`` the correction moves (default: all ``m``, n = m).

    Raises
    ------
    OutputError
        The file cannot be written (nothing is left at ``path`` then).
    """
    base = np.asarray(base, dtype=np.float32)
    m, span = len(base), layout.span
    block = max(1, min(256, (48 << 20) // (12 * m)))  # ~48 MB of positions at a time
    buf = np.empty((block, m, 3), np.float32)
    writer = PointCacheWriter(path, layout.format, m, len(span), **layout.header)
    try:
        for i in range(0, len(span), block):
            fr = span[i:i + block]
            b = buf[: len(fr)]
            b[:] = base
            rows = [layout.row(f) for f in fr]
            t0 = rows[0]
            if t0 is not None and rows == list(range(t0, t0 + len(fr))):
                runs = [(0, t0, t0 + len(fr))]
            else:
                runs = [(k, t, t + 1) for k, t in enumerate(rows) if t is not None]
            for k, a, z in runs:
                d = np.asarray(read(a, z), dtype=np.float32)
                if vertices is None:
                    b[k : k + z - a] += d
                else:
                    b[k : k + z - a, vertices] += d
            writer.write(b)
        writer.close()
    except BaseException:
        writer.abort()
        raise
