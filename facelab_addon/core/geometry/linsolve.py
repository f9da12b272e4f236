"""Factor-once / solve-many for sparse symmetric positive-definite systems.

Uses ``cholespy`` (CHOLMOD's sparse Cholesky factorisation) when it is installed
and falls back to SciPy's SuperLU with a symmetric ordering. Never call ``spsolve`` in a
loop: build one ``SPDFactor`` and call ``solve`` many times.

Also the BLAS thread controls of the solvers: small dense systems and
per-frame work run on one BLAS thread (``small_dense_threads``,
``one_blas_thread``), where more threads cost more to start than they share, and
``idle_core`` tells whether a second thread would get a core of its own.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import FaceLabError, UsageError

__all__ = ["SPDFactor", "idle_core", "one_blas_thread", "small_dense_threads"]

try:  # pragma: no cover - import guard
    from cholespy import CholeskySolverD, MatrixType

    _HAVE_CHOLESPY = True
except Exception:  # pragma: no cover
    _HAVE_CHOLESPY = False


class SPDFactor:
    """Sparse Cholesky (or LU) factor of an SPD matrix ``A`` (n,n).

    Parameters
    ----------
    A : (n,n) sparse matrix
        Symmetric positive definite.
    backend : {"auto", "cholespy", "splu"}
    what : str
        Name of the system, for error messages.
    """

    def __init__(self, A, backend: str = "auto", what: str = "deformation system"):
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        self.what = what
        if backend == "auto":
            backend = "cholespy" if _HAVE_CHOLESPY else "splu"
        self.backend = backend
        if backend == "cholespy":
            C = A.tocoo()
            try:
                self._s = CholeskySolverD(
                    self.n, C.row.astype(np.int32), C.col.astype(np.int32), C.data.astype(np.float64), MatrixType.COO
                )
            except Exception as e:  # not positive definite
                raise FaceLabError(
                    f"The {what} is singular ({e}); add position weights or fixed vertices, "
                    "or check the regions for a part with no border."
                ) from e
        elif backend == "splu":
            from scipy.sparse.linalg import splu

            try:
                self._lu = splu(
                    A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0, options={"SymmetricMode": True}
                )
            except RuntimeError as e:
                raise FaceLabError(
                    f"The {what} is singular ({e}); add position weights or fixed vertices, "
                    "or check the regions for a part with no border."
                ) from e
        else:
            raise UsageError(f"unknown backend {backend!r}; use 'auto', 'cholespy' or 'splu'")

    def solve(self, B) -> np.ndarray:
        """Solve ``A X = B`` for ``B`` of shape (n,) or (n,k); returns the same shape."""
        B = np.asarray(B, dtype=np.float64)
        one = B.ndim == 1
        B2 = np.ascontiguousarray(B.reshape(self.n, -1))
        if self.backend == "cholespy":
            X = np.zeros_like(B2)
            self._s.solve(B2, X)
        else:
            X = self._lu.solve(B2)
        if not np.all(np.isfinite(X)):
            raise FaceLabError(f"The {self.what} is singular; add position weights or fixed vertices.")
        return X.ravel() if one else X


def small_dense_threads(n: int = 1):
    """Context manager limiting BLAS to ``n`` threads (if ``threadpoolctl`` is installed).

    The dense systems of the Woodbury updates are a few hundred unknowns; on a
    busy machine multithreaded BLAS spends more time waiting for its threads
    than computing.
    """
    try:
        from threadpoolctl import threadpool_limits
    except Exception:  # optional dependency
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=n, user_api="blas")


_BLAS = []


def one_blas_thread():
    """Context limiting BLAS to one thread: on per-frame work multithreaded BLAS only spins on a busy
    machine. A cached threadpoolctl controller (cheap to enter per frame); no-op without it."""
    if not _BLAS:
        try:
            from threadpoolctl import ThreadpoolController

            _BLAS.append(ThreadpoolController())
        except Exception:  # optional dependency
            _BLAS.append(None)
    if _BLAS[0] is None:
        import contextlib

        return contextlib.nullcontext()
    return _BLAS[0].limit(limits=1, user_api="blas")


def idle_core() -> bool:
    """True when the machine has an idle core (1-minute load average below ``cpu_count - 0.5``)."""
    import os

    try:
        return os.getloadavg()[0] < (os.cpu_count() or 1) - 0.5
    except (OSError, AttributeError):  # no load average (Windows): assume idle cores
        return True
