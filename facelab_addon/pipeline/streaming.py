"""Per-frame results handed to a :class:`~facelab_addon.pipeline.correctives.CorrectionWriter` in chunks.

The solvers of Reconstruct from Bundles and Solve Performance produce one (n,3) result per
frame, in frame order, through a callback; :class:`FrameChunks` collects them into a chunk
buffer of a fixed size and passes each full chunk to the writer (which spools it to disk), so
no (T,n,3) array of the shot is ever built. Memory: one ``(chunk, n, 3)`` float64 buffer.
"""

from __future__ import annotations

import numpy as np

__all__ = ["CHUNK_BYTES", "FrameChunks"]

#: Size of the chunk buffer in bytes (float64): about 32 MB, at least one frame.
CHUNK_BYTES = 32_000_000


class FrameChunks:
    """Collect per-frame corrections and hand them to a writer chunk by chunk.

    Parameters
    ----------
    writer : object with ``add(frames (c,), deltas (c,n,3))``
        Usually a :class:`~facelab_addon.pipeline.correctives.CorrectionWriter`.
    frames : (T,) array_like
        Scene frame of every frame index ``t`` the callback may receive.
    n : int
        Vertices per frame.
    base : (n,3) array_like, optional
        Subtracted from every frame (e.g. the neutral, to turn positions into deltas).
    matrix : (3,3) array_like, optional
        Applied to every (row) vector after ``base``: ``d @ matrix.T`` (e.g. world to local).
    fill : bool
        Frames never passed (skipped by the solver) are written as zero corrections
        (``True``), or left out of the writer (``False``).
    chunk : int, optional
        Frames per chunk; default :data:`CHUNK_BYTES` worth of float64 frames.

    Notes
    -----
    Call the object as ``chunks(t, X)`` with increasing frame indices ``t`` and ``X``
    (n,3); then :meth:`close` writes what is left (and the skipped frames at the end).
    Each frame is transformed on its own, so the stored values do not depend on the
    chunk size.
    """

    def __init__(self, writer, frames, n: int, *, base=None, matrix=None, fill: bool = True, chunk: int | None = None):
        self.writer = writer
        self.frames = np.asarray(frames)
        self.n = int(n)
        self.base = None if base is None else np.asarray(base, dtype=np.float64)
        self.matrix_t = None if matrix is None else np.ascontiguousarray(np.asarray(matrix, dtype=np.float64).T)
        self.fill = bool(fill)
        size = chunk if chunk is not None else CHUNK_BYTES // max(24 * self.n, 1)
        self.chunk = max(1, int(size))
        self._buf = None  # allocated on the first frame, not during the solver's set-up before it
        self._idx = np.empty(self.chunk, dtype=np.int64)
        self._k = 0
        self._next = 0
        self.written = 0  # frames handed to the writer

    def __call__(self, t: int, X) -> None:
        t = int(t)
        if t < self._next:
            raise ValueError(f"Frames must come in increasing order: got #{t} after #{self._next - 1}.")
        if self.fill:
            for s in range(self._next, t):
                self._push(s, None)
        self._push(t, X)
        self._next = t + 1

    def _push(self, t, X) -> None:
        if self._buf is None:
            self._buf = np.empty((self.chunk, self.n, 3))
        row = self._buf[self._k]
        if X is None:
            row[:] = 0.0
        else:
            row[:] = X
            if self.base is not None:
                row -= self.base
            if self.matrix_t is not None:
                row[:] = row @ self.matrix_t
        self._idx[self._k] = t
        self._k += 1
        if self._k == self.chunk:
            self.flush()

    def flush(self) -> None:
        """Hand the buffered frames to the writer."""
        if self._k:
            self.writer.add(self.frames[self._idx[: self._k]], self._buf[: self._k])
            self.written += self._k
            self._k = 0

    def close(self) -> None:
        """Write the zero frames left at the end (``fill``) and the last partial chunk."""
        if self.fill:
            for s in range(self._next, len(self.frames)):
                self._push(s, None)
            self._next = len(self.frames)
        self.flush()
