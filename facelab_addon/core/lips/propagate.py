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
* ``patches=10`` (default, an addition to the paper): the lip region is
  covered by overlapping local patches, each predicted by its own reduced
  regression (the same thin SVDs and ``k × k`` θ̄) from the mouth triangles
  near it, and blended with a partition of unity. One global θ forces every
  part of the lips to use the same combination of training frames; local
  maps let, say, the left corner follow a smile while the lower lip follows
  the jaw, which matters when k is below the number of independent mouth
  motions. Still exact on the span of the training frames. ``patches=1``
  is the paper's single map. On the ICT benchmark
  (``benchmarks/propagate.py``, k = 10) the held-out inner-lip RMS error is
  22% of the uncorrected capture's with the defaults, 31% with one
  rest-centred map and 39% with the paper's uncentred map.
* Memory: frames are read in their own dtype (a float32 sequence is not
  upcast as a whole); only the mouth and lip vertices are gathered and
  converted to float64, a block of frames at a time. ``predict(captured, out=captured)``
  writes only the interior lip vertices. For :meth:`LipRegressor.extrapolation`
  and :func:`suggest_frames` on the same sequence, compute
  :meth:`LipRegressor.mouth_features` once and pass it as ``features=``.
* ``ridge`` (default 0, the paper): Tikhonov term ``λ ||θ̄||²`` in the
  reduced normal equations; ``ridge="loo"`` picks λ by leave-one-out
  prediction error of the lip gradients. Singular values below ``rtol``
  times the size of the training deformation are dropped (rank tolerance).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import FaceLabError, MeshError
from ..geometry.gradients import rest_inverse, shape_matrices
from ..geometry.laplacian import poisson_operator
from ..geometry.linsolve import SPDFactor
from .regions import region_border, validate_regions

__all__ = ["LipRegressor", "suggest_frames"]

_BLOCK = 64  # frames per block of the per-frame loops (working memory ~ block x region size)


def _as_frames(a, n_vertices, what, used=None):
    """Validate frames as a (T,V,3) float32 or float64 array, without copying them.

    float32 and float64 arrays are returned as they are (a (V,3) frame as a
    (1,V,3) view); other dtypes are converted to float64. Callers convert
    only the vertices they read to float64. NaNs are looked for in ``used``
    vertices only, a block of frames at a time.
    """
    A = np.asarray(a)
    if A.dtype != np.float32 and A.dtype != np.float64:
        A = A.astype(np.float64)
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
    bad = []
    for s in range(0, len(A), _BLOCK):
        blk = A[s : s + _BLOCK] if used is None else A[s : s + _BLOCK, used]
        fin = np.isfinite(blk).reshape(len(blk), -1).all(axis=1)
        bad.extend((s + np.flatnonzero(~fin)).tolist())
        if len(bad) >= 5:
            break
    if bad:
        raise MeshError(
            f"The {what} contain NaN or infinite coordinates in frames {bad[:5]}; "
            "fix or re-import those frames."
        )
    return A


def _same_array(a, b):
    """True when ``a`` and ``b`` are the same elements of the same buffer (e.g. ``out`` is the input)."""
    return a is b or (
        isinstance(a, np.ndarray) and a.shape == b.shape and a.dtype == b.dtype and a.strides == b.strides
        and a.__array_interface__["data"][0] == b.__array_interface__["data"][0]
    )


_OVERLAP = 1.0


def _lip_patches(rest, faces, mouth_faces, lip_faces, count, input_radius):
    """Overlapping local patches of the lip region and the mouth triangles that feed each one.

    Returns a list of ``(mouth_sel, lip_sel, lip_weight)``: indices into
    ``mouth_faces`` and ``lip_faces`` and the (n_p,) partition-of-unity weight
    of each lip triangle in the patch (weights of a triangle sum to 1 over
    patches), plus the patch spacing (scene units).
    """
    from scipy.sparse.csgraph import dijkstra

    R = rest
    nv = len(R)
    LT = faces[lip_faces]
    MT = faces[mouth_faces]
    if count <= 1:
        return [(np.arange(len(MT)), np.arange(len(LT)), np.ones(len(LT)))], np.inf

    def graph(tris):
        e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
        w = np.linalg.norm(R[e[:, 0]] - R[e[:, 1]], axis=1)
        return sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(nv, nv)).tocsr()

    lv = np.unique(LT)
    G = graph(LT)
    # farthest-point sampling of patch centres, geodesic on the lip region
    c0 = int(lv[np.argmax(np.linalg.norm(R[lv] - R[lv].mean(axis=0), axis=1))])
    centres = [c0]
    dmin = dijkstra(G, directed=False, indices=c0)[lv]
    big = 1e300
    for _ in range(int(count) - 1):
        i = int(np.argmax(np.where(np.isfinite(dmin), dmin, big)))
        if dmin[i] <= 0:
            break
        centres.append(int(lv[i]))
        dmin = np.minimum(dmin, dijkstra(G, directed=False, indices=lv[i])[lv])
    D = dijkstra(G, directed=False, indices=np.asarray(centres))[:, lv]  # (P, nL)
    P = len(centres)
    Dc = D[:, np.searchsorted(lv, centres)]
    np.fill_diagonal(Dc, np.inf)
    nn = Dc.min(axis=1)
    spacing = float(np.median(nn[np.isfinite(nn)])) if np.isfinite(nn).any() else float(np.ptp(R[lv], axis=0).max())
    cover = float(np.max(np.min(D, axis=0)))
    radius = max(_OVERLAP * spacing, 1.05 * cover)
    Wv = np.clip(1.0 - D / radius, 0.0, None)  # (P, nL)
    Wv /= Wv.sum(axis=0, keepdims=True)
    loc = np.searchsorted(lv, LT)  # (n, 3) into lv
    Wt = Wv[:, loc].mean(axis=2)  # (P, n), columns sum to 1
    rho = spacing if input_radius is None else float(input_radius)
    Gfull = graph(faces)
    out = []
    for p in range(P):
        lip_sel = np.flatnonzero(Wt[p] > 0)
        support = np.unique(LT[lip_sel])
        d = dijkstra(Gfull, directed=False, indices=support, min_only=True, limit=rho)
        mouth_sel = np.flatnonzero(np.isfinite(d[MT]).all(axis=1))
        if len(mouth_sel) < 3:
            mouth_sel = np.arange(len(MT))
        out.append((mouth_sel, lip_sel, Wt[p, lip_sel]))
    return out, spacing


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
    patches : int
        Number of local regressions. 1 is the paper's single global map from
        the whole mouth region to the whole lip region. With ``P > 1`` the lip
        region is covered by ``P`` overlapping patches (geodesic
        farthest-point centres, partition-of-unity weights) and each patch is
        predicted by its own reduced regression from the mouth triangles
        within ``input_radius`` of it, so, for example, the left corner and
        the lower lip can combine the training frames differently. Default 10.
    input_radius : float, optional
        Geodesic reach (scene units) of each patch's mouth input. Default:
        the spacing between patch centres (about 1 cm on ICT-FaceKit).
    center : {"rest", None}
        ``"rest"`` (default) regresses gradient offsets from the identity, so
        the rest pose predicts itself; ``None`` is the paper's uncentred model.
    ridge : float or "loo"
        Tikhonov weight on each reduced map (unitless, relative to the mean
        squared singular value of the training mouth matrix); ``"loo"`` picks
        it per patch by leave-one-out error. 0 (default) is the paper.
    rtol : float
        Relative singular-value cut-off for the thin SVDs (rank tolerance).
    backend : {"auto", "cholespy", "splu"}
        Sparse factorisation of the Poisson system.

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
    theta_bars : list of (rX, rY) ndarrays
        The reduced maps θ̄ of the patches (one for ``patches=1``).

    Raises
    ------
    RegionError, MeshError
        On empty/overlapping regions, a lip region with no border, degenerate
        triangles or bad shapes (messages say how to fix them).
    """

    def __init__(self, rest_vertices, faces, mouth_faces, lip_faces, *, patches: int = 10, input_radius=None,
                 center="rest", ridge=0.0, rtol=1e-4, backend="auto"):
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
        if not (ridge == "loo" or (np.isscalar(ridge) and float(ridge) >= 0)):
            raise ValueError(f"ridge must be a non-negative number or 'loo', got {ridge!r}")
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
        self._mouth_verts, inv = np.unique(self._mouth_tris, return_inverse=True)
        self._mouth_local = inv.reshape(-1, 3)
        self._lip_verts_all, inv = np.unique(self._lip_tris, return_inverse=True)
        self._lip_local = inv.reshape(-1, 3)
        self._used = np.union1d(self._mouth_verts, self._lip_verts_all)  # vertices read per frame

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
            self._factor = SPDFactor(self._L_II, backend, what="lip Poisson system")
        except Exception as e:  # pragma: no cover - validated regions make L_II SPD
            raise FaceLabError(
                f"The inner-lip Poisson system could not be factored ({e}); check for degenerate or "
                "disconnected triangles in 'FL_lips'."
            ) from e
        # divergence of the identity gradients: the constant part for center="rest"
        ident = np.broadcast_to(np.eye(3), (len(self.lip_faces), 3, 3))
        self._b_ident = self._D_I @ ident.transpose(0, 2, 1).reshape(-1, 3)  # (nI, 3)

        self._patches, self.patch_spacing = _lip_patches(R, F, self.mouth_faces, self.lip_faces, int(patches),
                                                        input_radius)
        self.n_patches = len(self._patches)
        Dc = self._D_I.tocsc()
        self._D_patch = [Dc[:, (3 * ls[:, None] + np.arange(3)).ravel()].tocsr() for _, ls, _ in self._patches]
        self._Y = None  # (9m, k) training mouth features
        self._X = None  # (9n, k) training lip features
        self.k = 0

    # ------------------------------------------------------------------ features
    def _grad(self, frames, rinv, verts, local):
        P = frames[:, verts, :]
        return np.matmul(shape_matrices(P, local), rinv)  # (T, f, 3, 3)

    def mouth_gradients(self, frames) -> np.ndarray:
        """(T,m,3,3) deformation gradients of the mouth triangles of ``frames`` (T,V,3)."""
        A = _as_frames(frames, self.n_vertices, "frames", self._used)
        return self._grad(A, self._mouth_rinv, self._mouth_verts, self._mouth_local)

    def lip_gradients(self, frames) -> np.ndarray:
        """(T,n,3,3) deformation gradients of the inner-lip triangles of ``frames`` (T,V,3)."""
        A = _as_frames(frames, self.n_vertices, "frames", self._used)
        return self._grad(A, self._lip_rinv, self._lip_verts_all, self._lip_local)

    def _feat(self, G):
        T = G.shape[0]
        if self.center == "rest":
            G = G - np.eye(3)
        return G.reshape(T, -1)

    def _mouth_feat(self, frames):
        """(T, 9m) mouth features of validated frames (any float dtype; computed in float64)."""
        return self._feat(self._grad(frames, self._mouth_rinv, self._mouth_verts, self._mouth_local))

    def mouth_features(self, captured) -> np.ndarray:
        """Whole-mouth feature vectors ``y`` of frames, one row per frame.

        The deformation gradients of the mouth triangles (order of
        ``mouth_faces``, each 3×3 flattened row-major), minus the identity
        when ``center="rest"``. They are what :meth:`extrapolation` and
        :func:`suggest_frames` compare with the training span: compute them
        once and pass them to both as ``features=`` so the sequence is read
        once. Needs no fit.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Frames, scene units. float32 frames are read in place (only the
            mouth vertices are converted to float64, a block at a time).

        Returns
        -------
        (T, 9m) float64 ndarray
            Unitless; ``m = len(mouth_faces)``. 72·m bytes a frame (about
            0.1 MB on ICT-FaceKit, 100 MB for 1000 frames).

        Raises
        ------
        FaceLabError
            If no frames are given, or they have a different topology or NaN
            coordinates in the mouth or lip region (``MeshError``).
        """
        A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
        out = np.empty((len(A), 9 * len(self.mouth_faces)))
        for s in range(0, len(A), _BLOCK):
            out[s : s + _BLOCK] = self._mouth_feat(A[s : s + _BLOCK])
        return out

    def _check_features(self, features):
        Y = np.asarray(features)
        d = 9 * len(self.mouth_faces)
        if Y.ndim != 2 or Y.shape[1] != d:
            raise FaceLabError(
                f"features have shape {Y.shape}, expected (T, {d}) (9 per mouth triangle); compute them with "
                "mouth_features() of this regressor."
            )
        if len(Y) == 0:
            raise FaceLabError("No features given (0 frames); pass at least one frame.")
        return Y

    # ------------------------------------------------------------------ training
    def fit(self, corrected):
        """Fit the reduced regression(s) on corrected frames, replacing any earlier training.

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
        self._Y = self._feat(self._grad(C, self._mouth_rinv, self._mouth_verts, self._mouth_local)).T.copy()
        self._X = self._feat(self._grad(C, self._lip_rinv, self._lip_verts_all, self._lip_local)).T.copy()
        self._refit()
        return self

    def add(self, corrected):
        """Add corrected frame(s) to the training set and update the fit.

        Re-runs the thin SVDs on the stacked ``k+1`` columns (cost
        ``O(9m k²)`` per patch, milliseconds); the result equals :meth:`fit`
        on all frames.

        Parameters
        ----------
        corrected : (V,3) or (j,V,3) array_like
            New corrected frame(s), scene units.

        Returns
        -------
        self
        """
        C = self._training_frames(corrected)
        y = self._feat(self._grad(C, self._mouth_rinv, self._mouth_verts, self._mouth_local)).T
        x = self._feat(self._grad(C, self._lip_rinv, self._lip_verts_all, self._lip_local)).T
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
        return _as_frames(c, self.n_vertices, "corrected frames", self._used)

    def _thin_svd(self, M):
        """Thin SVD ``M = U C`` (``C = Σ Vᵀ``) of a feature matrix (rows = 9 per triangle, k columns).

        Singular values below ``rtol`` times the size of the *deformation*
        (the Frobenius norm of ``M`` minus the identity gradients, so the
        uncentred paper model is not dominated by the identity) are dropped.
        Computed through the k×k Gram matrix (``O(rows·k²)``, several times
        faster than LAPACK on tall matrices); its precision, ``sqrt(eps)``
        times the largest singular value, is far below the rank tolerance.
        """
        w, Vv = np.linalg.eigh(M.T @ M)
        w, Vv = w[::-1], np.ascontiguousarray(Vv[:, ::-1])  # descending; contiguous for BLAS
        s = np.sqrt(np.clip(w, 0.0, None))
        if self.center == "rest":
            ref = float(np.sqrt(np.sum(M * M)))
        else:
            ident = np.tile(np.eye(3).ravel(), M.shape[0] // 9)[:, None]
            ref = float(np.linalg.norm(M - ident))
        ref = max(ref, 1e-12 * (s[0] if s.size else 0.0), 1e-300)
        r = int(np.sum(s > max(self.rtol, 1e-7) * ref)) if s.size else 0
        U = (M @ Vv[:, :r]) / s[:r]
        return U, s[:r, None] * Vv[:, :r].T

    def _refit(self):
        Y, X = self._Y, self._X
        self.k = Y.shape[1]
        m, n = len(self.mouth_faces), len(self.lip_faces)
        Y3 = Y.reshape(m, 9, self.k)
        X3 = X.reshape(n, 9, self.k)
        # global span of the mouth features: extrapolation score and suggest_frames
        self._UY, _ = self._thin_svd(Y)
        Yd = Y if self.center == "rest" else Y - np.tile(np.eye(3).ravel(), m)[:, None]
        self._sigma = float(np.sqrt(np.mean(np.sum(Yd * Yd, axis=0))))
        nI = len(self.interior_vertices)
        self.theta_bars, self.ridges_used = [], []
        self._pfit = []
        Zs, Ws, zid = [], [], []
        for (mouth_sel, lip_sel, w), Dp in zip(self._patches, self._D_patch):
            UY, CY = self._thin_svd(Y3[mouth_sel].reshape(-1, self.k))
            UX, CX = self._thin_svd(X3[lip_sel].reshape(-1, self.k))
            lam = self._choose_ridge(CY, CX)
            th = self._solve_theta(CY, CX, lam)  # (rX, rY)
            self.theta_bars.append(th)
            self.ridges_used.append(lam)
            rY = th.shape[1]
            # lip gradients of this patch per unit coefficient, weighted: (rY, n_p, 3, 3)
            Mp = (UX @ th).T.reshape(rY, len(lip_sel), 3, 3) * w[None, :, None, None]
            self._pfit.append((UX, th, UY))
            # divergence of those gradients on the interior vertices: (nI*3, rY)
            Fr = Mp.transpose(1, 3, 0, 2).reshape(3 * len(lip_sel), rY * 3)  # rows (t, a), cols (j, c): F[c, a]
            Zs.append((Dp @ Fr).reshape(nI, rY, 3).transpose(0, 2, 1).reshape(nI * 3, rY))
            # U_Yᵀ vec(D_d D_r^-1) = Σ_ik D_d[i,k] W[i,k]:  W[i,k,f,r] = Σ_j U[f,i,j,r] Ri[f,k,j]
            mp = len(mouth_sel)
            U4 = UY.reshape(mp, 3, 3, rY).transpose(0, 2, 1, 3).reshape(mp, 3, 3 * rY)  # (f, j, (i, r))
            Wf = np.matmul(self._mouth_rinv[mouth_sel], U4).reshape(mp, 3, 3, rY)  # (f, k, i, r)
            Ws.append(np.ascontiguousarray(Wf.transpose(2, 1, 0, 3)))  # (i, k, f, r)
            zid.append(np.tile(np.eye(3).ravel(), len(mouth_sel)) @ UY if self.center == "rest" else np.zeros(rY))
        self._Zdiv = np.concatenate(Zs, axis=1)  # (nI*3, Σ rY)
        self._Wp = Ws
        self._z_ident = np.concatenate(zid)

    def _solve_theta(self, CY, CX, lam):
        rY = CY.shape[0]
        if rY == 0 or CX.shape[0] == 0:
            return np.zeros((CX.shape[0], rY))
        A = CY @ CY.T  # (rY, rY)
        B = CX @ CY.T  # (rX, rY)
        if lam > 0:
            A = A + lam * np.mean(np.diag(A)) * np.eye(rY)
        # θ̄ A = B  <=>  A θ̄ᵀ = Bᵀ (A symmetric). The rank was already cut at rtol in the thin SVD
        # (A = diag(s²) up to rounding); lstsq only guards against exact singularity.
        sol, *_ = np.linalg.lstsq(A, B.T, rcond=1e-12)
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
        """Reduced coefficients ``z_p = U_Y,pᵀ y_p`` of all patches, (T, Σ rY), for validated frames.

        ``y = vec(D_d D_r^-1)`` is linear in the shape matrix ``D_d``, so
        ``U_Yᵀ y = Σ D_d[i,k] W[i,k]`` with ``W`` folded at fit time: a frame
        costs its mouth shape matrices and nine small GEMMs per patch.
        """
        e = _shape_components(frames, self._mouth_verts, self._mouth_local)
        zs = []
        for (mouth_sel, _, _), W in zip(self._patches, self._Wp):
            z = np.zeros((len(frames), W.shape[-1]))
            for i in range(3):
                for k in range(3):
                    z += e[k][i][:, mouth_sel] @ W[i, k]
            zs.append(z)
        return np.concatenate(zs, axis=1) - self._z_ident

    def _residual_norms(self, Y):
        """(T,) norms of mouth features ``Y`` (T, 9m) outside the global training span."""
        r = Y - (Y @ self._UY) @ self._UY.T
        return np.sqrt(np.sum(r * r, axis=1))

    def predict_lip_gradients(self, captured) -> np.ndarray:
        """Predicted inner-lip deformation gradients ``x = θ y`` (blended over patches).

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
        A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
        T = len(A)
        z = self._coefficients(A)
        x = np.zeros((T, len(self.lip_faces), 9))
        o = 0
        for (_, lip_sel, w), (UX, th, _) in zip(self._patches, self._pfit):
            r = th.shape[1]
            xp = (z[:, o : o + r] @ th.T) @ UX.T  # (T, 9 n_p)
            x[:, lip_sel] += xp.reshape(T, len(lip_sel), 9) * w[None, :, None]
            o += r
        x = x.reshape(T, -1, 3, 3)
        if self.center == "rest":
            x = x + np.eye(3)
        return x

    def predict(self, captured, *, out=None, chunk: int = 256) -> np.ndarray:
        """Correct the inner lips of captured frames.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like
            Captured frames, scene units, same topology as the rest mesh.
            float32 or float64 arrays are read without a copy; only the
            mouth and lip vertices are converted to float64, a chunk at a
            time, so float32 gives the same result as float64 (up to float32
            rounding of the written vertices).
        out : (T,V,3) ndarray, optional
            Where to write the result, any float dtype. It may be
            ``captured`` itself, for in-place correction of long sequences:
            then only the interior lip vertices are written (and they are
            never read). Another array first receives a copy of
            ``captured``. Default: a new float64 array. In place, the
            working memory is a few tens of MB whatever the sequence length
            and dtype (about 50 MB with the default chunk on ICT-FaceKit).
        chunk : int
            Frames per batch (working memory ~ chunk × lip size).

        Returns
        -------
        (T,V,3) ndarray
            ``out`` (float64 when not given): captured positions everywhere
            except the interior lip vertices, which are the Poisson
            reconstruction from ``θ y`` with the border vertices held at
            their captured positions (scene units). A single (V,3) frame
            gives a (1,V,3) result.

        Raises
        ------
        FaceLabError
            If the regressor was not fitted, or the frames have a different
            topology or NaN coordinates in the mouth or lip region.
        """
        self._require_fit()
        A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
        T = len(A)
        if out is None:
            out = A.astype(np.float64)  # always a copy
        elif not _same_array(out, A):
            if out.shape != A.shape:
                raise FaceLabError(f"out has shape {out.shape}, expected {A.shape}; pass an array like the frames.")
            out[...] = A
        iv, bv = self.interior_vertices, self.border_vertices
        nI = len(iv)
        for s in range(0, T, int(chunk)):
            e = min(T, s + int(chunk))
            t = e - s
            z = self._coefficients(A[s:e])
            rhs = (self._Zdiv @ z.T).reshape(nI, 3, t).transpose(0, 2, 1)  # (nI, t, 3)
            if self.center == "rest":
                rhs = rhs + self._b_ident[:, None, :]
            xb = np.asarray(A[s:e][:, bv, :], dtype=np.float64).transpose(1, 0, 2).reshape(len(bv), 3 * t)
            rhs = rhs.reshape(nI, 3 * t) - self._L_IB @ xb
            xi = self._factor.solve(rhs).reshape(nI, t, 3)
            out[s:e, iv, :] = xi.transpose(1, 0, 2)
        return out

    def extrapolation(self, captured=None, *, features=None) -> np.ndarray:
        """How far each frame's mouth gradients lie outside the span of the training frames.

        ``e = ||y - U_Y U_Yᵀ y|| / σ`` where ``y`` is the frame's whole-mouth
        feature vector (gradients minus the identity when ``center="rest"``),
        ``U_Y`` an orthonormal basis of the training features, and ``σ`` the
        RMS deformation ``||y_i - I||`` of the training mouths. It is 0 on
        training frames and their linear combinations (where the regression
        is exact), scale-free (gradients are unitless and do not change with
        the scene unit), and about 1 when a frame departs from the training
        span as much as a typical training pose departs from rest.

        Parameters
        ----------
        captured : (T,V,3) or (V,3) array_like, optional
            Frames, scene units (read a block at a time, never copied whole).
        features : (T, 9m) array_like, optional
            Instead of ``captured``: their :meth:`mouth_features`, for
            example to share them with :func:`suggest_frames`. Not modified.

        Returns
        -------
        (T,) float64 ndarray
        """
        self._require_fit()
        if (captured is None) == (features is None):
            raise ValueError("extrapolation() takes captured frames or their features, not both or neither")
        if features is None:
            A = _as_frames(captured, self.n_vertices, "captured frames", self._used)
            block = lambda s: self._mouth_feat(A[s : s + _BLOCK])  # noqa: E731
        else:
            A = self._check_features(features)
            block = lambda s: A[s : s + _BLOCK]  # noqa: E731
        out = np.empty(len(A))
        for s in range(0, len(A), _BLOCK):
            out[s : s + _BLOCK] = self._residual_norms(block(s))
        return out / max(self._sigma, 1e-12)

    def training_span(self) -> np.ndarray:
        """(9m, r) orthonormal basis ``U_Y`` of the training mouth features (whole mouth region)."""
        self._require_fit()
        return self._UY


def _shape_components(frames, verts, local):
    """Shape-matrix columns of triangles ``local`` over vertices ``verts`` for frames (T,V,3), in float64.

    Returns three (3,T,f) arrays ``e[k][i]``: column k (edge 1, edge 2,
    phantom offset), coordinate i. Component-major layout keeps every
    operation contiguous (about 3x faster than (T,f,3,3) for many frames).
    """
    Xt = np.ascontiguousarray(frames[:, verts, :].transpose(2, 0, 1), dtype=np.float64)  # (3, T, nv)
    p0 = Xt[:, :, local[:, 0]]
    e1 = Xt[:, :, local[:, 1]] - p0
    e2 = Xt[:, :, local[:, 2]] - p0
    c = np.empty_like(e1)
    np.subtract(e1[1] * e2[2], e1[2] * e2[1], out=c[0])
    np.subtract(e1[2] * e2[0], e1[0] * e2[2], out=c[1])
    np.subtract(e1[0] * e2[1], e1[1] * e2[0], out=c[2])
    s = np.sqrt(np.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]))
    c *= np.divide(1.0, s, out=np.zeros_like(s), where=s > 0)
    return e1, e2, c


def _mouth_features(frames, rest_vertices, faces, mouth_faces, chunk=_BLOCK):
    """(T, 9m) mouth gradients minus the identity of validated frames (any float dtype), float64."""
    F = np.asarray(faces, dtype=np.int64)[np.asarray(mouth_faces, dtype=np.int64)]
    verts, inv = np.unique(F, return_inverse=True)
    local = inv.reshape(-1, 3)
    rinv = rest_inverse(np.asarray(rest_vertices, dtype=np.float64), F, name="mouth region")
    T = len(frames)
    out = np.empty((T, 9 * len(F)))
    for s in range(0, T, chunk):
        P = frames[s : s + chunk][:, verts, :]  # shape_matrices converts these to float64
        out[s : s + chunk] = (np.matmul(shape_matrices(P, local), rinv) - np.eye(3)).reshape(len(P), -1)
    return out


def _deflate(R, q, block=_BLOCK):
    """``R -= (R q) qᵀ`` in place, a block of rows at a time (no full-size temporary)."""
    for s in range(0, len(R), block):
        b = R[s : s + block]
        b -= np.outer(b @ q, q)


def suggest_frames(captured=None, count: int = 1, *, regressor: LipRegressor | None = None, rest_vertices=None,
                   faces=None, mouth_faces=None, exclude=(), features=None,
                   overwrite_features: bool = False) -> np.ndarray:
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

    Memory: one (T, 9m) float64 array of mouth features (``m`` mouth
    triangles; about 0.1 MB a frame on ICT-FaceKit), projected and deflated
    in place a block of rows at a time. With ``features=...`` and
    ``overwrite_features=True`` the given array is that working array, so
    nothing of full size is allocated.

    Parameters
    ----------
    captured : (T,V,3) array_like, optional
        The captured sequence, scene units (float32 is read in place, a block
        of frames at a time). Required unless ``features`` is given.
    count : int
        Number of frames to propose.
    regressor : LipRegressor, optional
        A fitted regressor; supplies the rest mesh, faces, mouth region,
        feature centring and training span.
    rest_vertices : (V,3) array_like, optional
        Rest positions (needed without ``regressor`` and ``features``).
    faces : (F,3) int array_like, optional
        Triangles (needed without ``regressor`` and ``features``).
    mouth_faces : (m,) int array_like, optional
        Mouth-region triangles (needed without ``regressor`` and ``features``).
    exclude : sequence of int
        Frames never to propose (for example the ones already corrected);
        their directions are added to the starting span.
    features : (T, 9m) array_like, optional
        Instead of ``captured``: precomputed mouth features of the sequence,
        one row per frame. With a regressor, ``regressor.mouth_features(captured)``
        (the same array can first go to ``regressor.extrapolation(features=...)``,
        so the sequence is read once). Without one, the mouth deformation
        gradients minus the identity (any fixed order of the 9m entries), i.e.
        ``mouth_features`` of a ``center="rest"`` regressor on these mouth
        triangles. The result equals passing ``captured``.
    overwrite_features : bool
        Use ``features`` (if a C-contiguous float64 ndarray) as the working
        array instead of copying it; its contents are then undefined.

    Returns
    -------
    (c,) int64 ndarray
        Frame indices in order of priority, ``c = min(count, frames left)``;
        fewer when the remaining frames already lie in the span.
    """
    if (captured is None) == (features is None):
        raise ValueError("suggest_frames() takes captured frames or their features, not both or neither")
    if features is not None:
        if regressor is not None:
            F0 = regressor._check_features(features)
        else:
            F0 = np.asarray(features)
            if F0.ndim != 2 or F0.shape[1] % 9 or len(F0) == 0:
                raise FaceLabError(f"features have shape {F0.shape}, expected (T, 9m) with T >= 1 (9 per mouth "
                                   "triangle).")
            if mouth_faces is not None and F0.shape[1] != 9 * len(np.asarray(mouth_faces).ravel()):
                raise FaceLabError(f"features have {F0.shape[1]} columns but there are {len(mouth_faces)} mouth "
                                   "triangles (9 columns each); compute them on the same mouth region.")
        own = overwrite_features and isinstance(F0, np.ndarray) and F0.dtype == np.float64 and F0.flags.c_contiguous
        Rz = F0 if own else np.array(F0, dtype=np.float64, order="C")
    elif regressor is not None:
        Rz = regressor.mouth_features(captured)
    else:
        if rest_vertices is None or faces is None or mouth_faces is None:
            raise FaceLabError(
                "suggest_frames needs either a fitted regressor or rest_vertices, faces and mouth_faces; pass them."
            )
        R = np.asarray(rest_vertices, dtype=np.float64)
        A = _as_frames(captured, len(R), "captured frames")
        Rz = _mouth_features(A, R, faces, mouth_faces)
    Q = regressor._UY if regressor is not None and regressor._Y is not None else None
    T = len(Rz)
    # feature scale (threshold of "already in the span"), then residuals after projecting on Q, in place
    sq = np.empty(T)
    for s in range(0, T, _BLOCK):
        b = Rz[s : s + _BLOCK]
        sq[s : s + _BLOCK] = np.sum(b * b, axis=1)
        if Q is not None and Q.shape[1]:
            b -= (b @ Q) @ Q.T
    scale = max(float(np.sqrt(np.mean(sq))), 1e-300)
    excl = np.zeros(T, dtype=bool)
    ex = np.asarray(list(exclude), dtype=np.int64)
    if ex.size:
        excl[ex[(ex >= 0) & (ex < T)]] = True
    # ... and on the excluded frames
    for i in np.flatnonzero(excl):
        nv = np.linalg.norm(Rz[i])
        if nv > 1e-10 * scale:
            _deflate(Rz, Rz[i] / nv)
    picks = []
    norms = np.empty(T)
    for _ in range(int(count)):
        for s in range(0, T, _BLOCK):
            norms[s : s + _BLOCK] = np.linalg.norm(Rz[s : s + _BLOCK], axis=1)
        norms[excl] = -1.0
        if picks:
            norms[picks] = -1.0
        i = int(np.argmax(norms))
        if norms[i] <= 1e-10 * scale:
            break
        picks.append(i)
        _deflate(Rz, Rz[i] / norms[i])
    return np.asarray(picks, dtype=np.int64)
