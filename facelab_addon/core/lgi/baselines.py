"""The paper's blendshape baseline for local geometric indexing (Cong, Lan and Fedkiw 2019, §7, Fig. 4).

:class:`BlendshapeFit` fits the dataset shapes, as a linear blendshape rig, to
the bundles with soft [0, 1] bounds on the weights (Fig. 4, middle). The
paper's other baseline, Gaussian RBF interpolation of the per-bundle shape
weights, is ``GeometricIndexer.reconstruct(..., stitching="rbf")``
(:mod:`facelab_addon.core.lgi.stitch`).

Shapes: neutral (V,3), dataset shapes (S,V,3) as positions, bundles (B,3).
Units: positions in scene units; blendshape weights are unitless.
"""

from __future__ import annotations

import numpy as np

from .natural_neighbor import surface_points

__all__ = ["BlendshapeFit"]


class BlendshapeFit:
    """Dataset shapes as a linear blendshape rig fit to the bundles (§7 baseline).

    Minimises ``|A w - r|^2 + mu sum_s (min(w_s, 0)^2 + max(w_s - 1, 0)^2)
    + ridge |w|^2``, with ``A`` the bundles' motion on every shape (scene
    units) and ``r = bundles - neutral bundles``: the paper's "Euclidean
    distances from the bundles to their surface points subject to a soft
    constraint that penalizes the weights to lie between 0 and 1". Solved by
    a semismooth Newton iteration over the active bounds (exact for this
    piecewise quadratic, usually 3-6 steps).

    Parameters
    ----------
    neutral : (V,3) array_like
    faces : (F,3) int array_like
    shapes : (S,V,3) array_like
        Positions of the dataset shapes, scene units.
    bundle_faces : (B,) int array_like
    bundle_bary : (B,3) array_like
    bound_weight : float
        ``mu`` relative to the mean diagonal of ``A^T A``.
    ridge : float
        Tikhonov weight relative to the mean diagonal of ``A^T A`` (keeps
        shapes that no bundle sees at 0).
    """

    def __init__(self, neutral, faces, shapes, bundle_faces, bundle_bary, *, bound_weight: float = 1.0,
                 ridge: float = 1e-6):
        x0 = np.asarray(neutral, dtype=np.float64)
        X = np.asarray(shapes, dtype=np.float64)
        self.neutral = x0
        self.deltas = X - x0
        p0 = surface_points(x0, faces, bundle_faces, bundle_bary)
        P = surface_points(X, faces, bundle_faces, bundle_bary)  # (S,B,3)
        self.p0 = p0
        self.A = (P - p0).reshape(len(X), -1).T  # (3B, S)
        self.AtA = self.A.T @ self.A
        s = float(np.mean(np.diag(self.AtA)))
        self.mu = bound_weight * s
        self.ridge = ridge * s

    def weights(self, bundles, iterations: int = 30):
        """(S,) blendshape weights for one frame of bundles (B,3), unitless."""
        r = (np.asarray(bundles, dtype=np.float64) - self.p0).ravel()
        Atr = self.A.T @ r
        S = self.AtA.shape[0]
        H0 = self.AtA + self.ridge * np.eye(S)
        w = np.linalg.solve(H0, Atr)
        for _ in range(iterations):
            low, high = w < 0, w > 1
            act = (low | high).astype(np.float64)
            H = H0 + self.mu * np.diag(act)
            w_new = np.linalg.solve(H, Atr + self.mu * high)
            if np.array_equal(w_new < 0, low) and np.array_equal(w_new > 1, high):
                return w_new
            w = w_new
        return w

    def reconstruct(self, bundles):
        """(V,3) vertices ``x0 + sum_s w_s b_s`` for one frame of bundles, scene units."""
        w = self.weights(bundles)
        return self.neutral + np.tensordot(w, self.deltas, axes=1)
