"""Regression propagation of lip corrections.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4 "Automatic Lip Correction Learning". The deformation gradients
``y`` of the trusted mouth region predict the gradients ``x`` of the inner-lip
region through a linear map ``x = θ y`` learnt from ``k`` corrected frames.
With ``Y = U_Y C_Y`` and ``X = U_X C_X`` (thin SVDs of the training matrices,
one column per frame), the reduced unknown ``θ̄ = U_Xᵀ θ U_Y`` (at most
``k × k``) solves the normal equations ``θ̄ C_Y C_Yᵀ = C_X C_Yᵀ`` and
``θ = U_X θ̄ U_Yᵀ`` is never formed. Predicted gradients become positions by
a sparse Poisson solve with the lip/mouth border vertices held at their
captured positions (Dirichlet).

Implementation notes (deviations are marked):

* The Poisson system is the usual gradient-domain least squares
  ``min_x Σ_t a_t ||∇_t x - F_t||²`` over the lip triangles (``∇_t`` the
  rest-pose gradient of the piecewise-linear map, ``a_t`` the rest area),
  i.e. a cotangent Laplacian. Its interior block is factored once, in
  ``__init__`` (cholespy, else SuperLU). Because the border moves every
  frame, prediction is linear in (mouth coefficients, border positions): a
  frame costs its mouth gradients, a few small dense products and one
  back-substitution; all frames of a chunk share one multi-column solve.
  The paper reports 5.15 s a frame; this layout needs about a millisecond.
* ``center="rest"`` (default, an addition to the paper): the regression runs
  on gradients minus the identity, ``x - I = θ (y - I)``, so the rest pose
  maps to itself and a single training frame already gives a pose-scaled
  correction. ``center=None`` is the paper's model verbatim.
* ``ridge`` (default 0, the paper): Tikhonov term ``λ ||θ̄||²`` in the
  reduced normal equations; ``ridge="loo"`` picks λ by leave-one-out
  prediction error of the lip gradients.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .errors import FaceLabError, MeshError
from .gradients import rest_inverse, shape_matrices
from .regions import region_border, validate_regions

__all__ = ["LipRegressor", "suggest_frames", "poisson_operator"]

try:  # pragma: no cover - import guard
    from cholespy import CholeskySolverD, MatrixType

    _HAVE_CHOLESPY = True
except Exception:  # pragma: no cover
    _HAVE_CHOLESPY = False


class _Factor:
    """Sparse SPD factor, built once; ``solve`` takes (n,) or (n,c) right-hand sides."""

    def __init__(self, A, backend: str = "auto"):
        A = sp.csr_matrix(A)
        self.n = A.shape[0]
        if backend == "auto":
            backend = "cholespy" if _HAVE_CHOLESPY else "splu"
        self.backend = backend
        if backend == "cholespy":
            C = A.tocoo()
            self._s = CholeskySolverD(
                self.n, C.row.astype(np.int32), C.col.astype(np.int32), C.data.astype(np.float64), MatrixType.COO
            )
        elif backend == "splu":
            from scipy.sparse.linalg import splu

            self._lu = splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0, options={"SymmetricMode": True})
        else:
            raise ValueError(f"unknown backend {backend!r}")

    def solve(self, B):
        B = np.ascontiguousarray(B, dtype=np.float64)
        if self.backend == "cholespy":
            X = np.empty_like(B)
            self._s.solve(B, X)
            return X
        return self._lu.solve(B)


def poisson_operator(rest_vertices, faces, region_faces):
    """Gradient-domain Poisson operator of a triangle region.

    For positions ``x`` (one coordinate) the per-triangle gradient is
    ``G x`` (3 per triangle, in the rest triangle's plane). The energy
    ``Σ_t a_t ||(G x)_t - g_t||²`` has normal equations ``L x = D g`` with
    ``L = Gᵀ A G`` (the cotangent Laplacian of the region) and ``D = Gᵀ A``.
    Targets for coordinate ``c`` from deformation gradients ``F (n,3,3)`` are
    ``g_t = F_t[c, :]``, i.e. the matrix ``F.transpose(0,2,1).reshape(3n, 3)``.

    Parameters
    ----------
    rest_vertices : (V,3) array_like
        Rest positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    region_faces : (n,) int array_like
        Triangles of the region.

    Returns
    -------
    L : (V,V) scipy.sparse.csr_matrix
        Stiffness matrix, units of area / length² (unitless); zero outside
        the region's vertices.
    D : (V,3n) scipy.sparse.csr_matrix
        Divergence operator, units of area (scene units²).
    """
    R = np.asarray(rest_vertices, dtype=np.float64)
    T = np.asarray(faces, dtype=np.int64)[np.asarray(region_faces, dtype=np.int64)]
    n = len(T)
    p0, p1, p2 = R[T[:, 0]], R[T[:, 1]], R[T[:, 2]]
    nrm = np.cross(p1 - p0, p2 - p0)
    a2 = np.linalg.norm(nrm, axis=1)
    nh = nrm / a2[:, None]
    grads = np.stack(
        [np.cross(nh, p2 - p1), np.cross(nh, p0 - p2), np.cross(nh, p1 - p0)], axis=1
    ) / a2[:, None, None]  # (n, corner, xyz)
    rows = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)  # (n, corner, axis)
    cols = np.broadcast_to(T[:, :, None], (n, 3, 3))
    G = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, len(R)))
    area = np.repeat(0.5 * a2, 3)
    D = (G.T @ sp.diags(area)).tocsr()
    L = (D @ G).tocsr()
    return L, D


def _as_frames(a, n_vertices, what):
    A = np.asarray(a, dtype=np.float64)
    if A.ndim == 2:
        A = A[None]
    if A.ndim != 3 or A.shape[1:] != (n_vertices, 3):
        raise MeshError(
            f"The {what} have shape {np.asarray(a).shape} but the rest mesh has {n_vertices} vertices: "
            f"expected ({n_vertices},3) or (T,{n_vertices},3). The topology differs from the rest mesh; "
            "use frames of the same mesh (same vertex count and order)."
        )
    if A.shape[0] == 0:
        raise FaceLabError(f"No {what} given (0 frames); pass at least one frame.")
    fin = np.isfinite(A).reshape(len(A), -1).all(axis=1)
    if not fin.all():
        raise MeshError(
            f"The {what} contain NaN or infinite coordinates in frames {np.flatnonzero(~fin)[:5].tolist()}; "
            "fix or re-import those frames."
        )
    return A


class LipRegressor:
    """Learn inner-lip deformation gradients from the mouth region (Dinev et al. 2018, §4).

    Parameters
    ----------
    rest_vertices : (V,3) array_like
        Rest (neutral) positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    mouth_faces : (m,) int array_like
        Triangles of the trusted mouth region (vertex group ``FL_mouth``).
    lip_faces : (n,) int array_like
        Triangles of the inner-lip region (``FL_lips``), predicted.
    center : {"rest", None}
        ``"rest"`` regresses gradient offsets from the identity (the rest pose
        predicts itself); ``None`` is the paper's uncentred model.
    ridge : float or "loo"
        Tikhonov weight on the reduced map (unitless, relative to the mean
        squared singular value of the training mouth matrix); ``"loo"`` picks
        it by leave-one-out error among a few candidates. 0 is the paper.
    rtol : float
        Relative singular-value cut-off for the thin SVDs (rank tolerance).
    backend : {"auto", "cholespy", "splu"}
        Sparse factorisation used for the Poisson system.

    Attributes
    ----------
    lip_vertices : (nL,) int64
        Vertices of the lip triangles.
    border_vertices : (nB,) int64
        Lip vertices also used by a non-lip triangle; kept at captured positions.
    interior_vertices : (nI,) int64
        Lip vertices that are solved for.
    k : int
        Number of training frames.

    Raises
    ------
    RegionError, MeshError
        On empty/overlapping regions, a lip region with no border, degenerate
        triangles or bad shapes (messages say how to fix them).
    """

    def __init__(self, rest_vertices, faces, mouth_faces, lip_faces, *, center="rest", ridge=0.0, rtol=1e-10,
                 backend="auto"):
        R = np.asarray(rest_vertices, dtype=np.float64)
        F = np.asarray(faces)
        if R.ndim != 2 or R.shape[1] != 3 or len(R) == 0:
            raise MeshError(f"rest_vertices must be a non-empty (V,3) array, got shape {R.shape}.")
        if not np.isfinite(R).all():
            raise MeshError("The rest mesh has NaN or infinite coordinates; fix the rest pose.")
        if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer):
            raise MeshError(f"faces must be an (F,3) integer array of triangles, got {F.shape}; triangulate first.")
        F = F.astype(np.int64)
        if F.size and (F.min() < 0 or F.max() >= len(R)):
            raise MeshError(f"Face indices are out of range [0, {len(R)}); the faces do not belong to this mesh.")
        if center not in ("rest", None):
            raise ValueError(f"center must be 'rest' or None, got {center!r}")
        self.rest = R
        self.faces = F
        self.n_vertices = len(R)
        self.center = center
        self.ridge = ridge
        self.rtol = float(rtol)
        self.mouth_faces, self.lip_faces = validate_regions(F, mouth_faces, lip_faces, len(R))
        self._mouth_tris = F[self.mouth_faces]
        self._lip_tris = F[self.lip_faces]
        self._mouth_rinv = rest_inverse(R, self._mouth_tris, name="mouth region")
        self._lip_rinv = rest_inverse(R, self._lip_tris, name="inner-lip region")
        # mouth vertices, gathered once per chunk
        self._mouth_verts, inv = np.unique(self._mouth_tris, return_inverse=True)
        self._mouth_local = inv.reshape(-1, 3)
        self._lip_verts_all, inv = np.unique(self._lip_tris, return_inverse=True)
        self._lip_local = inv.reshape(-1, 3)

        # Poisson system on the lip triangles, Dirichlet on the border
        L, D = poisson_operator(R, F, self.lip_faces)
        self.lip_vertices = self._lip_verts_all
        self.border_vertices = region_border(F, self.lip_faces, len(R))
        interior = np.setdiff1d(self.lip_vertices, self.border_vertices)
        if interior.size == 0:
            raise FaceLabError(
                "Every inner-lip vertex is on the border, so nothing would be predicted; widen 'FL_lips' "
                "(Auto Regions with a larger lip width)."
            )
        self.interior_vertices = interior
        L = L.tocsr()
        self._L_II = L[interior][:, interior].tocsc()
        self._L_IB = L[interior][:, self.border_vertices].tocsr()
        self._D_I = D[interior].tocsr()  # (nI, 3n)
        try:
            self._factor = _Factor(self._L_II, backend)
        except Exception as e:  # pragma: no cover - validated regions make L_II SPD
            raise FaceLabError(
                f"The inner-lip Poisson system could not be factored ({e}); check for degenerate or "
                "disconnected triangles in 'FL_lips'."
            ) from e
        # divergence of the identity gradients (= L_I· rest): constant part for center="rest"
        ident = np.broadcast_to(np.eye(3), (len(self.lip_faces), 3, 3))
        self._b_ident = self._D_I @ ident.transpose(0, 2, 1).reshape(-1, 3)  # (nI, 3)
        self._Y = None  # (9m, k) training mouth features
        self._X = None  # (9n, k) training lip features
        self.k = 0

    # ------------------------------------------------------------------ features
    def _grad(self, frames, rinv, verts, local):
        P = frames[:, verts, :]
        return np.matmul(shape_matrices(P, local), rinv)  # (T, f, 3, 3)

    def mouth_gradients(self, frames) -> np.ndarray:
        """(T,m,3,3) deformation gradients of the mouth triangles of ``frames`` (T,V,3)."""
        A = _as_frames(frames, self.n_vertices, "frames")
        return self._grad(A, self._mouth_rinv, self._mouth_verts, self._mouth_local)

    def lip_gradients(self, frames) -> np.ndarray:
        """(T,n,3,3) deformation gradients of the inner-lip triangles of ``frames`` (T,V,3)."""
        A = _as_frames(frames, self.n_vertices, "frames")
        return self._grad(A, self._lip_rinv, self._lip_verts_all, self._lip_local)

    def _feat(self, G):
        T = G.shape[0]
        if self.center == "rest":
            G = G - np.eye(3)
        return G.reshape(T, -1)

    # ------------------------------------------------------------------ training
    def fit(self, corrected):
        """Fit the reduced regression on corrected frames.

        Parameters
        ----------
        corrected : (k,V,3) array_like
            Corrected (ground-truth) frames, scene units. For each, the mouth
            gradients give ``y`` (the mouth is trusted, so corrected = captured
            there) and the lip gradients give ``x``.

        Returns
        -------
        self

        Raises
        ------
        FaceLabError
            With fewer than one training frame, a topology that differs from
            the rest mesh, or NaN coordinates.
        """
        C = self._training_frames(corrected)
        self._Y = self._feat(self.mouth_gradients(C)).T.copy()
        self._X = self._feat(self.lip_gradients(C)).T.copy()
        self._refit()
        return self

    def add(self, corrected):
        """Add corrected frame(s) to the training set and update the fit.

        Re-runs the thin SVDs on the stacked ``k+1`` columns (cost
        ``O(9m k²)``, about a millisecond); the result equals :meth:`fit` on
        all frames.

        Parameters
        ----------
        corrected : (V,3) or (j,V,3) array_like
            New corrected frame(s), scene units.

        Returns
        -------
        self
        """
        C = self._training_frames(corrected)
        y = self._feat(self.mouth_gradients(C)).T
        x = self._feat(self.lip_gradients(C)).T
        if self._Y is None:
            self._Y, self._X = y.copy(), x.copy()
        else:
            self._Y = np.hstack([self._Y, y])
            self._X = np.hstack([self._X, x])
        self._refit()
        return self

    def _training_frames(self, corrected):
        c = np.asarray(corrected)
        if c.size == 0 or (c.ndim == 3 and c.shape[0] == 0):
            raise FaceLabError(
                "No corrected frames were given; correct at least one frame (sketch or sculpt it) before training."
            )
        return _as_frames(c, self.n_vertices, "corrected frames")

    def _refit(self):
        Y, X = self._Y, self._X
        self.k = Y.shape[1]
        UY, sY, VYt = np.linalg.svd(Y, full_matrices=False)
        UX, sX, VXt = np.linalg.svd(X, full_matrices=False)
        rY = int(np.sum(sY > self.rtol * max(sY[0], 1e-300))) if sY.size else 0
        rX = int(np.sum(sX > self.rtol * max(sX[0], 1e-300))) if sX.size else 0
        self._UY, self._UX = UY[:, :rY], UX[:, :rX]
        CY = sY[:rY, None] * VYt[:rY]  # (rY, k)
        CX = sX[:rX, None] * VXt[:rX]  # (rX, k)
        self._CY, self._CX = CY, CX
        lam = self._choose_ridge(CY, CX)
        self.ridge_used = lam
        self.theta_bar = self._solve_theta(CY, CX, lam)  # (rX, rY)
        # deformation magnitude of the training mouths (scale of the extrapolation score)
        Yd = Y if self.center == "rest" else Y - np.tile(np.eye(3).ravel(), Y.shape[0] // 9)[:, None]
        self._sigma = float(np.sqrt(np.mean(np.sum(Yd * Yd, axis=0))))
        # fold U_X θ̄ and the divergence into (nI, 3, rY)
        M = self._UX @ self.theta_bar  # (9n, rY)
        n = len(self.lip_faces)
        Mr = M.T.reshape(rY, n, 3, 3).transpose(0, 1, 3, 2).reshape(rY, 9 * n)  # row j: F_j^T, row-major
        Z = np.stack([self._D_I @ Mr[j].reshape(3 * n, 3) for j in range(rY)], axis=-1) if rY else np.zeros(
            (len(self.interior_vertices), 3, 0))
        self._Zdiv = Z  # (nI, 3, rY)

    def _solve_theta(self, CY, CX, lam):
        rY = CY.shape[0]
        if rY == 0:
            return np.zeros((CX.shape[0], 0))
        A = CY @ CY.T  # (rY, rY)
        B = CX @ CY.T  # (rX, rY)
        if lam > 0:
            A = A + lam * np.mean(np.diag(A)) * np.eye(rY)
        # θ̄ A = B  <=>  A θ̄ᵀ = Bᵀ (A symmetric)
        sol, *_ = np.linalg.lstsq(A, B.T, rcond=self.rtol)
        return sol.T

    def _choose_ridge(self, CY, CX):
        if self.ridge != "loo":
            return float(self.ridge)
        k = CY.shape[1]
        if k < 3:
            return 0.0
        best, best_err = 0.0, np.inf
        for lam in (0.0, 1e-4, 1e-3, 1e-2, 3e-2, 1e-1, 3e-1, 1.0):
            err = 0.0
            for i in range(k):
                keep = np.arange(k) != i
                th = self._solve_theta(CY[:, keep], CX[:, keep], lam)
                err += float(np.sum((th @ CY[:, i] - CX[:, i]) ** 2))
            if err < best_err * (1 - 1e-9):
                best, best_err = lam, err
        return best

    def _require_fit(self):
        if self._Y is None:
            raise FaceLabError("The lip regressor has no training frames; call fit() with corrected frames first.")

    # ------------------------------------------------------------------ prediction
    def _coefficients(self, frames):
        """Reduced coefficients z = U_Yᵀ y (T, rY) and the residual norms (T,)."""
        y = self._feat(self.mouth_gradients(frames))
        z = y @ self._UY
        res = np.sqrt(np.maximum(np.sum(y * y, axis=1) - np.sum(z * z, axis=1), 0.0))
        return z, res

    def predict_lip_gradients(self, captured) -> np.ndarray:
        """Predicted inner-lip deformation gradients ``x = θ y``.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Captured frames, scene units.

        Returns
        -------
        (T,n,3,3) float64 ndarray
            One unitless 3×3 gradient per lip triangle (order of ``lip_faces``).
        """
        self._require_fit()
        A = _as_frames(captured, self.n_vertices, "captured frames")
        z, _ = self._coefficients(A)
        x = (z @ self.theta_bar.T) @ self._UX.T  # (T, 9n)
        x = x.reshape(len(A), -1, 3, 3)
        if self.center == "rest":
            x = x + np.eye(3)
        return x

    def predict(self, captured, *, out=None, chunk: int = 256) -> np.ndarray:
        """Correct the inner lips of captured frames.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Captured frames, scene units, same topology as the rest mesh.
        out : (T,V,3) ndarray, optional
            Where to write the result (may be ``captured`` itself, for
            in-place correction of long sequences). Default: a new array.
        chunk : int
            Frames per batch (memory ~ chunk × lip size).

        Returns
        -------
        (T,V,3) float64 ndarray
            Captured positions everywhere except the interior lip vertices,
            which are the Poisson reconstruction from ``θ y`` with the border
            vertices held at their captured positions (scene units). A single
            (V,3) frame gives a (1,V,3) result.

        Raises
        ------
        FaceLabError
            If the regressor was not fitted, or the frames have a different
            topology or NaN coordinates.
        """
        self._require_fit()
        A = _as_frames(captured, self.n_vertices, "captured frames")
        T = len(A)
        if out is None:
            out = A.copy()
        elif out is not A:
            if out.shape != A.shape:
                raise FaceLabError(f"out has shape {out.shape}, expected {A.shape}; pass an array like the frames.")
            out[...] = A
        iv, bv = self.interior_vertices, self.border_vertices
        for s in range(0, T, int(chunk)):
            e = min(T, s + int(chunk))
            t = e - s
            z, _ = self._coefficients(A[s:e])
            rhs = np.einsum("icj,tj->itc", self._Zdiv, z)  # (nI, t, 3)
            if self.center == "rest":
                rhs += self._b_ident[:, None, :]
            xb = A[s:e][:, bv, :].transpose(1, 0, 2).reshape(len(bv), 3 * t)
            rhs = rhs.reshape(len(iv), 3 * t) - self._L_IB @ xb
            xi = self._factor.solve(rhs).reshape(len(iv), t, 3)
            out[s:e, iv, :] = xi.transpose(1, 0, 2)
        return out

    def extrapolation(self, captured) -> np.ndarray:
        """How far each frame's mouth gradients lie outside the training span.

        ``e = ||y - U_Y U_Yᵀ y|| / σ`` where ``y`` is the frame's mouth
        feature vector (gradients minus the identity when ``center="rest"``)
        and ``σ`` the RMS deformation ``||y_i - I||`` of the training mouths.
        It is 0 on training frames and on their linear combinations (where the
        regression is exact), scale-free (gradients are unitless and do not
        change with the scene unit), and about 1 when a frame departs from
        the training span as much as a typical training pose departs from
        rest.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Frames, scene units.

        Returns
        -------
        (T,) float64 ndarray
        """
        self._require_fit()
        A = _as_frames(captured, self.n_vertices, "captured frames")
        out = np.empty(len(A))
        for s in range(0, len(A), 256):
            _, res = self._coefficients(A[s : s + 256])
            out[s : s + 256] = res
        return out / max(self._sigma, 1e-12)

    def training_span(self) -> np.ndarray:
        """(9m, r) orthonormal basis ``U_Y`` of the training mouth features."""
        self._require_fit()
        return self._UY


def _mouth_features(frames, rest_vertices, faces, mouth_faces, chunk=256):
    F = np.asarray(faces, dtype=np.int64)[np.asarray(mouth_faces, dtype=np.int64)]
    verts, inv = np.unique(F, return_inverse=True)
    local = inv.reshape(-1, 3)
    rinv = rest_inverse(np.asarray(rest_vertices, dtype=np.float64), F, name="mouth region")
    T = len(frames)
    out = np.empty((T, 9 * len(F)))
    for s in range(0, T, chunk):
        P = np.asarray(frames[s : s + chunk], dtype=np.float64)[:, verts, :]
        out[s : s + chunk] = (np.matmul(shape_matrices(P, local), rinv) - np.eye(3)).reshape(len(P), -1)
    return out


def suggest_frames(captured, count: int = 1, *, regressor: LipRegressor | None = None, rest_vertices=None,
                   faces=None, mouth_faces=None, exclude=()) -> np.ndarray:
    """Propose the next frames worth correcting.

    Greedy pivoted Gram-Schmidt in mouth-gradient space (Dinev et al. 2018,
    §6.2: train on extreme poses): each pick is the frame whose mouth
    gradients lie farthest outside the span of the frames already known, and
    its direction is then added to the span. With no regressor the span
    starts empty (features are gradients minus the identity), so the first
    pick is the most extreme pose (largest deformation from rest) and the
    next ones are the poses least explained by the earlier picks. With a
    regressor the span starts as its training span, so the first pick is the
    frame of largest :meth:`LipRegressor.extrapolation`.

    Parameters
    ----------
    captured : (T,V,3) array_like
        The captured sequence, scene units.
    count : int
        Number of frames to propose.
    regressor : LipRegressor, optional
        A fitted regressor; supplies the rest mesh, faces, mouth region,
        feature centring and training span.
    rest_vertices : (V,3) array_like, optional
        Rest positions (needed without ``regressor``).
    faces : (F,3) int array_like, optional
        Triangles (needed without ``regressor``).
    mouth_faces : (m,) int array_like, optional
        Mouth-region triangles (needed without ``regressor``).
    exclude : sequence of int
        Frames never to propose (for example the ones already corrected);
        their directions are added to the starting span.

    Returns
    -------
    (c,) int64 ndarray
        Frame indices in order of priority, ``c = min(count, frames left)``;
        fewer when the remaining frames already lie in the span.
    """
    if regressor is not None:
        A = _as_frames(captured, regressor.n_vertices, "captured frames")
        Y = np.concatenate([regressor._feat(regressor.mouth_gradients(A[s : s + 256])) for s in range(0, len(A), 256)])
        Q = regressor._UY.copy() if regressor._Y is not None else np.zeros((Y.shape[1], 0))
    else:
        if rest_vertices is None or faces is None or mouth_faces is None:
            raise FaceLabError(
                "suggest_frames needs either a fitted regressor or rest_vertices, faces and mouth_faces; pass them."
            )
        R = np.asarray(rest_vertices, dtype=np.float64)
        A = _as_frames(captured, len(R), "captured frames")
        Y = _mouth_features(A, R, faces, mouth_faces)
        Q = np.zeros((Y.shape[1], 0))
    T = len(Y)
    excl = np.zeros(T, dtype=bool)
    ex = np.asarray(list(exclude), dtype=np.int64)
    if ex.size:
        excl[ex[(ex >= 0) & (ex < T)]] = True
    # residuals after projecting on Q (and on excluded frames)
    Rz = Y - (Y @ Q) @ Q.T if Q.shape[1] else Y.copy()
    scale = max(float(np.sqrt(np.mean(np.sum(Y * Y, axis=1)))), 1e-300)
    for i in np.flatnonzero(excl):
        v = Rz[i]
        nv = np.linalg.norm(v)
        if nv > 1e-10 * scale:
            q = v / nv
            Rz -= np.outer(Rz @ q, q)
    picks = []
    for _ in range(int(count)):
        norms = np.linalg.norm(Rz, axis=1)
        norms[excl] = -1.0
        if picks:
            norms[picks] = -1.0
        i = int(np.argmax(norms))
        if norms[i] <= 1e-10 * scale:
            break
        picks.append(i)
        q = Rz[i] / norms[i]
        Rz -= np.outer(Rz @ q, q)
    return np.asarray(picks, dtype=np.int64)
