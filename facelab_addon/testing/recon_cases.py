"""Other actors and bundle layouts for Reconstruct from Bundles' benchmark and tests.

The local geometric indexing data of :mod:`facelab_addon.testing.datasets`
is one face (ICT-FaceKit's mean identity) with one marker pattern. To measure
Reconstruct on cases it was not tuned on, this module makes:

* :func:`ict_identity`: another actor, the ICT neutral and every expression
  moved by a random combination of ICT's identity targets (``x + sum_i a_i
  (identity_i - neutral)``, ``a_i`` uniform in ``[-spread, spread]``); the
  expression deltas stay additive, as in ICT-FaceKit's model. Combine with
  :class:`~facelab_addon.testing.datasets.ICTShapeGenerator`'s bulge
  parameters for another actor's nonlinearity.
* :func:`random_bundle_layout`: bundles scattered at random (with a minimum
  spacing) over the same face region as ``ict_bundle_layout``'s painted
  pattern, instead of its farthest-point sampling.

Units: the ICT model's (centimetres unless loaded with ``scale``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.geometry.mesh import face_normals

__all__ = ["ict_identity", "random_bundle_layout"]


def ict_identity(ict, seed: int = 1, spread: float = 1.5):
    """A copy of the ICT model with another identity (module docstring).

    Parameters
    ----------
    ict : ICTModel
    seed : int
        Draws the identity weights.
    spread : float
        Identity weights are uniform in ``[-spread, spread]`` (unitless).

    Returns
    -------
    ICTModel
        Same topology, UVs and parts; ``neutral`` and ``expressions`` moved,
        ``identities`` empty.
    """
    if not ict.identities:
        raise ValueError("This ICT model has no identity targets; load the full ICT-FaceKit.")
    rng = np.random.default_rng(seed)
    names = sorted(ict.identities)
    a = rng.uniform(-spread, spread, len(names))
    off = sum(float(ai) * (ict.identities[n] - ict.neutral) for ai, n in zip(a, names))
    return dataclasses.replace(ict, neutral=ict.neutral + off,
                               expressions={n: e + off for n, e in ict.expressions.items()}, identities={})


def random_bundle_layout(ict, n: int = 100, seed: int = 0, min_spacing: float = 0.6):
    """Bundles at random points of the face region, at least ``min_spacing`` apart.

    Parameters
    ----------
    ict : ICTModel
    n : int
        Number of bundles (fewer if the region is full).
    seed : int
    min_spacing : float
        Minimum distance between bundles, centimetres (times ``ict.scale``).

    Returns
    -------
    bundle_faces : (n,) int64 ndarray
    bundle_bary : (n,3) float64 ndarray
    """
    rng = np.random.default_rng(seed)
    X, F = ict.neutral, ict.faces
    s = 1.0 / ict.scale
    fn = face_normals(X, F)
    cen = X[F].mean(axis=1) * s
    ok = ict.part_face_mask("M_Face") & (fn[:, 2] > 0.35)
    ok &= (np.abs(cen[:, 0]) < 6.0) & (cen[:, 1] > -8.5) & (cen[:, 1] < 8.5) & (cen[:, 2] > 5.5)
    for name in ("eyeBlink_L", "eyeBlink_R", "mouthRollLower", "mouthRollUpper"):
        if name in ict.expressions:
            mv = np.linalg.norm(ict.expressions[name] - X, axis=1) * s
            ok &= mv[F].max(axis=1) < (0.15 if name.startswith("eye") else 0.4)
    cand = rng.permutation(np.flatnonzero(ok))
    chosen, pts = [], np.empty((0, 3))
    for f in cand:
        if len(pts) == 0 or np.linalg.norm(pts - cen[f], axis=1).min() >= min_spacing:
            chosen.append(f)
            pts = np.vstack([pts, cen[f]])
            if len(chosen) == n:
                break
    faces = np.array(chosen, dtype=np.int64)
    return faces, rng.dirichlet([4.0, 4.0, 4.0], size=len(faces))
