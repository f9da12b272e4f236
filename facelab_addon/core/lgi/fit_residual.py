"""Bounded blendshape fit plus a noise-aware, natural-neighbour-stitched residual: the default of Reconstruct.

Cong, Lan and Fedkiw 2019 rebuild the face from sparse bundles by local
geometric indexing (:class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer`)
and compare it with a blendshape fit of the dataset (§7, Fig. 4). Measured
on held-out poses, a *bounded* blendshape fit (weights in [0, 1]) is the
stronger baseline: exact local indexing passes bundle noise straight through
and takes poorly constrained local shapes far from bundles. This module keeps
the fit as the base and adds, locally, what the fit misses:

1. **Bounded fit.** ``w = argmin |A w - (q - p0)|^2`` with ``0 <= w <= 1``:
   ``A`` (3B,S) is every dataset shape's motion at the bundles. By default
   this is exactly the bounded least-squares fit, noisy bundles or not (a
   ridge of 1e-6 of the mean column energy only keeps shapes that no bundle
   sees at 0). An optional weight prior ``(sigma / tau_w)^2 |w|^2``
   (``weight_prior=tau_w``, ``sigma`` the bundle noise per axis) lowers the
   skin error with noisy bundles but shrinks the weights of shapes that the
   bundles see weakly, which the inner lips need (they then end up slightly
   worse than the bounded fit's). Solved with ``scipy.optimize.lsq_linear``
   (BVLS) on the ``S x S`` triangular factor of the system.
2. **Residual at the bundles** ``r = q - Bary (x0 + D^T w)`` (B,3): the part of
   the pose the dataset cannot reach linearly (bulges of combinations and
   in-betweens, jaw arcs).
3. **Natural-neighbour stitching of the residual** (§5's weights ``W``,
   (V,B)): ``x = x0 + D^T w + f * (W c)`` with ``c = argmin |G c - r|^2 +
   lambda |c|^2``, ``G = Bary W`` (B,B). ``lambda = sigma^2 / tau^2`` with
   ``tau^2`` the residual's own variance beyond the noise (a Wiener filter):
   without noise the surface passes exactly through every bundle; with noise
   only the part of the residual that stands above it is kept, and pure noise
   leaves the fit unchanged.
4. **Where the residual acts** ``f`` (V,): a falloff, 1 up to
   ``falloff[0]`` bundle spacings (median distance between neighbouring
   bundles) from the nearest bundle, smoothly 0 at ``falloff[1]``, and 0 on
   vertices that no dataset shape moves, times a per-vertex *gain* in [0, 1]
   learned from the dataset by leaving each shape out (how well the stitched
   residual predicts the true one there, kept only as far as the dataset's
   shapes agree on it: a James-Stein shrinkage by its standard error). Far
   from bundles, and where the
   skin does not move like its nearest bundles (the inner lips, behind the
   outer-lip bundles), the global fit stands alone. With the learned gain
   the surface no longer passes exactly through the bundles
   (``learn_gain=False``: exactly through them when there is no noise).

:func:`estimate_noise` estimates ``sigma`` from a sequence's jitter (the
second difference of every bundle's track) when the noise level is not given.
Sequences average the fit weights and residual coefficients over a centred
window (temporal smoothing, as §7 averages the barycentric weights).

Shapes: neutral (V,3), dataset shapes (S,V,3) as positions, bundles (B,3) or
(T,B,3). Units: positions, noise and residuals in scene units; weights unitless.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy.optimize import lsq_linear
from scipy.spatial import cKDTree

from ..errors import BundleError, DatasetError
from ..geometry.linsolve import one_blas_thread
from .inputs import check_bundle_frame, check_bundle_sequence, check_bundles_move, check_reconstruction_inputs
from .natural_neighbor import natural_neighbor_weights, surface_points

__all__ = ["FitResidual", "estimate_noise"]


def estimate_noise(bundles, min_triples: int = 7) -> float:
    """Bundle noise (standard deviation per axis, scene units) from the jitter of their tracks.

    For white noise of standard deviation ``sigma`` the second difference
    ``q[t+1] - 2 q[t] + q[t-1]`` of a track has standard deviation
    ``sqrt(6) sigma``; smooth motion adds little to it. The robust estimate
    is ``1.4826 median|second difference| / sqrt(6)`` over every bundle, axis
    and frame triple without NaN.

    Parameters
    ----------
    bundles : (T,B,3) array_like
        Bundle tracks, scene units; NaN where a bundle is missing.
    min_triples : int
        Fewest frame triples without NaN needed for an estimate.

    Returns
    -------
    float
        Scene units; 0.0 with fewer than ``min_triples`` complete frame
        triples (too short to tell noise from motion).

    Notes
    -----
    Fast motion sampled at a low frame rate also has large second
    differences and is taken for noise; the reconstruction then leans on the
    bounded fit. Give the noise level explicitly in that case.
    """
    Q = np.asarray(bundles, dtype=np.float64)
    if Q.ndim != 3 or len(Q) < 3:
        return 0.0
    d2 = Q[2:] - 2.0 * Q[1:-1] + Q[:-2]
    complete = np.isfinite(d2).all(axis=(1, 2))
    if complete.sum() < min_triples:
        return 0.0
    d2 = d2[complete]
    return float(1.4826 * np.median(np.abs(d2)) / np.sqrt(6.0))


def _check_dataset(D, names, tol):
    """Refuse shapes equal to the neutral or to each other (deltas ``D`` (S,V,3), ``tol`` scene units)."""
    S = len(D)
    flat = D.reshape(S, -1)
    still = np.flatnonzero(np.abs(flat).max(axis=1) <= tol)
    if len(still):
        raise DatasetError(f"Dataset shape {names[still[0]]!r} equals the neutral (moves nothing); remove it from "
                           "the dataset.")
    proj = flat @ np.random.default_rng(0).standard_normal((flat.shape[1], 4))
    d = np.abs(proj[:, None, :] - proj[None, :, :]).max(axis=2)
    scale = np.linalg.norm(flat, axis=1).max()
    i, j = np.nonzero(np.triu(d <= 1e-6 * scale * np.sqrt(flat.shape[1]), 1))
    for a, b in zip(i, j):
        if np.abs(flat[a] - flat[b]).max() <= tol:
            raise DatasetError(f"Dataset shapes {names[a]!r} and {names[b]!r} are duplicates (identical to "
                               f"{tol:.2g} scene units); remove one of them.")


class FitResidual:
    """Bounded blendshape fit + natural-neighbour residual from bundles (module docstring).

    Build once per (mesh, dataset, bundle binding); each frame then costs a
    bounded least-squares fit and two small products.

    Parameters
    ----------
    neutral : (V,3) array_like
        Neutral mesh ``x0``, scene units.
    faces : (F,3) int array_like
        Triangles.
    shapes : (S,V,3) array_like
        Dataset shapes as positions (``x0 + b_n``): at least 4, pairwise
        different, none equal to the neutral (as for the indexer).
    bundle_faces : (B,) int array_like
        Triangle of each bundle on the neutral mesh (:func:`bind_points`).
    bundle_bary : (B,3) array_like
        Barycentric coordinates of each bundle in its triangle.
    names : list of str, optional
        Shape names, for messages.
    uvs : (V,2) or (F,3,2) array_like, optional
        UV map for the natural-neighbour weights (else geodesics).
    nn_method : {"uv", "geodesic"}, optional
        Force the natural-neighbour method.
    nn : NaturalNeighbors, optional
        Precomputed natural-neighbour weights of these bundles (e.g. a
        :class:`GeometricIndexer`'s ``dataset.nn``); ``uvs`` and ``nn_method`` are
        then unused.
    weight_prior : float, optional
        ``tau_w``: prior standard deviation of a blendshape weight (unitless).
        None (default): no prior, the fit is the bounded fit. Only acts with
        noise; smaller values shrink the weights more (lower skin error with
        noisy bundles, slightly higher inner-lip error; ``docs/reconstruct.md``).
    falloff : (float, float)
        The residual acts fully up to ``falloff[0]`` bundle spacings from the
        nearest bundle and fades to 0 at ``falloff[1]`` spacings.
    noise_margin : float
        ``tau^2 = mean(r^2) - noise_margin sigma^2``: the residual is kept
        only where it stands above this many times the noise variance
        (unitless; 1 would be unbiased for white noise, larger is safer
        because the fit has already absorbed part of the noise).
    learn_gain : bool
        Learn the per-vertex gain of the residual from the dataset (leave
        one shape out; about one bounded fit per shape at build time).
    bundle_names : list of str, optional
        Bundle names for messages.

    Attributes
    ----------
    stats : dict
        Bundles, shapes, bundle spacing, memory in bytes, build time.
    face_size : float
        Bounding-box diagonal of the natural-neighbour domain, scene units.
    falloff_weights, gain, residual_weights : (V,) float64
        The distance falloff, the learned gain (1 without learning) and
        their product, the weight of the stitched residual at every vertex.
    last : dict
        Of the last frame: ``weights`` (S,), ``residual`` (largest bundle
        residual of the fit, scene units), ``lambda`` (the residual's
        regularisation), ``noise`` (scene units).
    """

    def __init__(self, neutral, faces, shapes, bundle_faces, bundle_bary, *, names=None, uvs=None, nn_method=None,
                 nn=None, weight_prior=None, falloff=(1.0, 2.5), noise_margin: float = 1.5,
                 learn_gain: bool = True, bundle_names=None):
        t0 = time.perf_counter()
        x0, F, X, self.names, bf, bb = check_reconstruction_inputs(neutral, faces, shapes, names, bundle_faces,
                                                                   bundle_bary)
        nv, S, B = len(x0), len(X), len(bf)
        if weight_prior is not None and not weight_prior > 0:
            raise ValueError(f"weight_prior must be positive or None, got {weight_prior}.")
        a, b = (float(v) for v in falloff)
        if not 0 <= a < b:
            raise ValueError(f"falloff must be two spacings 0 <= start < end, got {falloff}.")
        self.neutral, self.faces = x0, F
        self.bundle_faces, self.bundle_bary = bf.astype(np.int64), bb
        self.B, self.S, self.V = B, S, nv
        self.bundle_names = None if bundle_names is None else [str(n) for n in bundle_names]
        self.weight_prior = None if weight_prior is None else float(weight_prior)
        self.falloff = (a, b)
        self.noise_margin = float(noise_margin)

        self.nn = nn if nn is not None else natural_neighbor_weights(x0, F, bf, bb, uvs=uvs, method=nn_method)
        W = self.nn.weights.tocsr()
        dom = self.nn.domain
        self.face_size = float(np.linalg.norm(x0[dom].max(axis=0) - x0[dom].min(axis=0)))
        D = X - x0
        tol = 1e-7 * self.face_size
        _check_dataset(D, self.names, tol)
        mags = np.linalg.norm(D, axis=2).max(axis=0)
        self._active = np.flatnonzero(mags > 0)
        self._D = np.ascontiguousarray(D[:, self._active].reshape(S, -1).T.astype(np.float32))  # (3n_act, S)
        self.p0 = surface_points(x0, F, bf, bb)
        A = (surface_points(X, F, bf, bb) - self.p0).reshape(S, -1).T  # (3B,S)
        self.A = A
        check_bundles_move(np.linalg.norm(A.reshape(B, 3, S), axis=1).max(axis=1), tol, self.bundle_names)
        seen = np.abs(A).max(axis=0) > tol
        self.unseen = [self.names[s] for s in np.flatnonzero(~seen)]
        # a tiny ridge keeps shapes that no bundle sees at 0 (and the fit unique)
        self._ridge0 = 1e-6 * float(np.mean(np.sum(A * A, axis=0)))
        self._systems = {}

        Bary = sp.csr_matrix((bb.ravel(), (np.repeat(np.arange(B), 3), F[bf].ravel())), shape=(B, nv))
        self._bary_mat = Bary
        G = (Bary @ W).toarray()
        self._G = G
        ev, EV = np.linalg.eigh(G.T @ G)
        self._ev, self._EV = ev, EV
        # falloff with the distance to the nearest bundle, in bundle spacings; 0 where no shape moves
        tree = cKDTree(self.p0)
        d, _ = tree.query(x0)
        if B > 1:
            nb, _ = tree.query(self.p0, k=2)
            spacing = float(np.median(nb[:, 1]))
        else:
            spacing = self.face_size
        self.spacing = max(spacing, 1e-12 * max(self.face_size, 1e-300))
        u = np.clip((d / self.spacing - a) / (b - a), 0.0, 1.0)
        f = 1.0 - u * u * (3.0 - 2.0 * u)
        f[mags <= 0] = 0.0
        self.falloff_weights = f
        keep = np.flatnonzero(f > 0)
        self._keep = keep
        self.gain = np.zeros(nv)
        self.gain[keep] = self._learned_gain(D, W, keep) if learn_gain else 1.0
        self.residual_weights = f * self.gain
        self._Wf = sp.csr_matrix(sp.diags(self.residual_weights[keep]) @ W[keep])
        self.last = {}
        self.stats = {
            "method": "fit_residual",
            "bundles": B,
            "shapes": S,
            "vertices": nv,
            "face_size": self.face_size,
            "bundle_spacing": self.spacing,
            "shapes_no_bundle_sees": list(self.unseen),
            "vertices_with_residual": int(len(keep)),
            "mean_residual_gain": float(self.gain[keep].mean()) if len(keep) else 0.0,
            "residual_matrix_condition": float(np.linalg.cond(G)),
            "natural_neighbor_method": self.nn.method,
            "memory_bytes_total": int(self._D.nbytes + A.nbytes + G.nbytes + EV.nbytes + self._Wf.data.nbytes
                                      + self._Wf.indices.nbytes + self._Wf.indptr.nbytes),
            "build_seconds": time.perf_counter() - t0,
        }

    def _learned_gain(self, D, W, keep):
        """(len(keep),) per-vertex gain in [0, 1] of the stitched residual, learned on the dataset.

        Leave one shape out: fit it (bounded) with the others, stitch the
        fit's residual at the bundles as :meth:`reconstruct` does, and compare
        with the fit's true residual at every vertex. ``beta`` is the
        least-squares scale of the stitched residual ``P_s`` onto the true one
        ``R_s`` over all shapes ``s``, ``se`` its standard error with the shapes
        as samples (``sqrt(sum_s (P_s . (R_s - beta P_s))^2) / sum_s |P_s|^2``).
        The gain is ``clip(beta, 0, 1)^2 max(0, 1 - (se / beta)^2)``: squared
        because the scale is fitted on the shapes it is judged on, and shrunk
        (James-Stein) where the shapes disagree, so that the residual acts only
        where it helps *confidently*: 1 where stitching predicts the residual,
        0 where it does not (typically vertices whose motion is not that of the
        nearest bundles, such as the inner lips) or only by chance.
        """
        A, S, B = self.A, self.S, self.B
        Wl = np.zeros((S, S))
        for s in range(S):
            others = np.r_[0:s, s + 1:S]
            Wl[s, others] = lsq_linear(A[:, others], A[:, s], bounds=(0.0, 1.0), method="bvls").x
        r = (A.T - Wl @ A.T).reshape(S, B, 3)  # fit residuals at the bundles
        C = np.linalg.solve(self._G, r.transpose(1, 0, 2).reshape(B, 3 * S))  # (B, 3S)
        P = np.asarray(W[keep] @ C).reshape(len(keep), S, 3)  # stitched
        Dk = D[:, keep]
        R = Dk - np.tensordot(Wl, Dk, axes=1)  # (S, k, 3) true residuals
        num_s = np.einsum("ksd,skd->ks", P, R)  # (k, S) per-shape agreement
        den_s = np.einsum("ksd,ksd->ks", P, P)
        den = den_s.sum(axis=1)
        beta = num_s.sum(axis=1) / np.maximum(den, 1e-300) * (den > 0)
        # standard error of beta with the shapes as samples: P_s . (R_s - beta P_s) = num_s - beta den_s
        se = np.sqrt(np.sum((num_s - beta[:, None] * den_s) ** 2, axis=1)) / np.maximum(den, 1e-300)
        confidence = np.clip(1.0 - se * se / np.maximum(beta * beta, 1e-300), 0.0, 1.0) * (beta > 0)
        return np.clip(beta, 0.0, 1.0) ** 2 * confidence

    # ------------------------------------------------------------------ the fit

    def _system(self, noise: float):
        """(R, Qt): ``|A w - r|^2 + ridge |w|^2 = |R w - Qt r|^2 + const``, cached per noise level."""
        key = round(float(noise), 15)
        sysm = self._systems.get(key)
        if sysm is None:
            lam = self._ridge0 + (0.0 if self.weight_prior is None else (float(noise) / self.weight_prior) ** 2)
            Aa = np.vstack([self.A, np.sqrt(lam) * np.eye(self.S)])
            Qf, R = np.linalg.qr(Aa, mode="reduced")  # Aa = Qf R, Qf (3B+S, S)
            sysm = (R, np.ascontiguousarray(Qf[: len(self.A)].T))
            if len(self._systems) > 8:
                self._systems.clear()
            self._systems[key] = sysm
        return sysm

    def _check_bundles(self, q):
        return check_bundle_frame(q, self.B, self.bundle_names)

    def fit_weights(self, bundles, noise: float = 0.0):
        """(S,) bounded blendshape weights in [0, 1] for one frame of bundles (B,3); ``noise`` in scene units."""
        q = self._check_bundles(bundles)
        R, Qt = self._system(noise)
        return np.clip(lsq_linear(R, Qt @ (q - self.p0).ravel(), bounds=(0.0, 1.0), method="bvls").x, 0.0, 1.0)

    def _coefficients(self, q, noise):
        """Fit weights (S,) and residual coefficients (B,3) of one frame."""
        R, Qt = self._system(noise)
        w = np.clip(lsq_linear(R, Qt @ (q - self.p0).ravel(), bounds=(0.0, 1.0), method="bvls").x, 0.0, 1.0)
        r = (q - self.p0) - (self.A @ w).reshape(self.B, 3)
        sig2 = float(noise) ** 2
        if sig2 > 0:
            tau2 = float(np.mean(r * r)) - self.noise_margin * sig2
            lam = np.inf if tau2 <= 1e-12 * sig2 else sig2 / tau2
        else:
            lam = 0.0
        if np.isinf(lam):
            c = np.zeros_like(r)
        else:
            EV = self._EV
            c = EV @ ((EV.T @ (self._G.T @ r)) / (self._ev + lam)[:, None])
        self.last = {"weights": w, "residual": float(np.linalg.norm(r, axis=1).max()), "lambda": float(lam),
                     "noise": float(noise)}
        return w, c

    def _blend(self, w, c):
        X = self.neutral.copy()
        X[self._active] += (self._D @ w.astype(np.float32)).reshape(-1, 3)
        X[self._keep] += self._Wf @ c
        return X

    # ------------------------------------------------------------------ per frame

    def reconstruct(self, bundles, noise: float = 0.0):
        """Rebuild the face for one frame of bundles.

        Parameters
        ----------
        bundles : (B,3) array_like
            Bundle positions (in the neutral's rigid frame), scene units.
        noise : float
            Bundle noise, standard deviation per axis, scene units (0: the
            whole residual at the bundles is stitched).

        Returns
        -------
        (V,3) float64 ndarray
            Scene units. ``self.last`` holds the fit weights and the residual.
        """
        q = self._check_bundles(bundles)
        if not np.isfinite(noise) or noise < 0:
            raise BundleError(f"The bundle noise must be a finite length >= 0, got {noise}.")
        with one_blas_thread():
            return self._blend(*self._coefficients(q, noise))

    def reconstruct_sequence(self, bundles, *, noise=None, smooth: int = 1, progress=None):
        """Rebuild every frame of an animated bundle sequence.

        Parameters
        ----------
        bundles : (T,B,3) array_like
            Bundle positions per frame, scene units. A frame with any NaN
            bundle is skipped.
        noise : float, optional
            Bundle noise (standard deviation per axis, scene units); None:
            :func:`estimate_noise` of the sequence.
        smooth : int
            Centred moving average of the fit weights and residual
            coefficients over this many frames (1 = off; even values are
            rounded up); skipped frames leave the window.
        progress : callable, optional
            ``progress(done, total)`` after every frame is fitted.

        Returns
        -------
        frames : (T,V,3) float64 ndarray
            Scene units; skipped frames are NaN.
        skipped : list of int
            Frames skipped because of NaN bundle positions.
        """
        Q = check_bundle_sequence(bundles, self.B)
        out = np.full((len(Q), self.V, 3), np.nan)
        skipped = self.reconstruct_stream(Q, out.__setitem__, noise=noise, smooth=smooth, progress=progress)
        return out, skipped

    def reconstruct_stream(self, bundles, sink, *, noise=None, smooth: int = 1, progress=None):
        """:meth:`reconstruct_sequence` without the (T,V,3) result: each frame is handed to ``sink``.

        The per-frame fit (weights and residual coefficients, ``S + 3B``
        numbers a frame) is kept for the whole sequence; each frame's face is
        blended from them and passed on at once, so memory does not grow with
        the frames times the vertices.

        Parameters
        ----------
        bundles, noise, smooth, progress
            As in :meth:`reconstruct_sequence`.
        sink : callable(t, X)
            Called with the frame index ``t`` and its face ``X`` (V,3) float64
            (scene units, a new array) for every frame that is not skipped, in
            increasing ``t``.

        Returns
        -------
        skipped : list of int
            Frames skipped because of NaN bundle positions (never passed to ``sink``).
        """
        Q = check_bundle_sequence(bundles, self.B)
        sigma = estimate_noise(Q) if noise is None else float(noise)
        if not np.isfinite(sigma) or sigma < 0:
            raise BundleError(f"The bundle noise must be a finite length >= 0, got {noise}.")
        self.noise = sigma
        T = len(Q)
        ok = np.isfinite(Q).all(axis=(1, 2))
        skipped = [int(t) for t in np.flatnonzero(~ok)]
        Wt = np.zeros((T, self.S))
        Ct = np.zeros((T, self.B, 3))
        with one_blas_thread():
            for n, t in enumerate(np.flatnonzero(ok)):
                Wt[t], Ct[t] = self._coefficients(Q[t], sigma)
                if progress is not None:
                    progress(n + 1, int(ok.sum()))
            half = max(int(smooth), 1) // 2
            for t in np.flatnonzero(ok):
                win = [s for s in range(t - half, t + half + 1) if 0 <= s < T and ok[s]]
                sink(int(t), self._blend(Wt[win].mean(axis=0), Ct[win].mean(axis=0)))
        self.last_sequence = {"weights": Wt, "coefficients": Ct, "noise": sigma, "skipped": skipped}
        return skipped
