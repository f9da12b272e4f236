"""Eyelid contour targets lifted onto the eyeball (Bhat et al. 2013, §4.1).

"High Fidelity Facial Animation Capture and Retargeting With Contours": the
eyelid curves are fitted as 3D targets on the cornea. With
``MatchParams(eyelids='3d')`` or ``'both'``, :func:`~facelab_addon.core.solve.matching.match_contours`
hands its eyelid correspondences (pixel targets on mesh-edge points) to
``lift_eyelids``, which projects each target from its camera onto the
eyeball sphere (:mod:`facelab_addon.core.geometry.sphere`, fitted to the
eyeball vertices of the mesh being matched, refitted only when they move)
grown by the lid point's height over it: the current height on that mesh (so
a lid that matches the image is its own fixed point) or the rest-pose height
(``ContourLoops.eyelid_offset``). The results are 3D targets fitted like
bundles (Eq. 2). Targets whose camera ray meets the sphere near its limb
(ill-conditioned, or hidden by the eye) are dropped.

Conventions: vertices float64 (V,3) scene units; pixels top-left origin, y
down; cameras OpenCV (``core.capture.camera.Camera``). NumPy only, no bpy.
"""

from __future__ import annotations

import numpy as np

from ..geometry.sphere import fit_sphere, project_to_sphere

__all__: list = []  # used through match_contours(..., MatchParams(eyelids='3d' or 'both'))


def _eyeball_sphere(V, loops, side):
    """Sphere fitted to the eyeball vertices of ``V``; refitted only when they moved."""
    P = V[loops.eyeballs[side]]
    hit = loops._sphere_cache.get(side)
    if hit is not None and hit[0].shape == P.shape and np.array_equal(hit[0], P):
        return hit[1]
    cr = fit_sphere(P)
    loops._sphere_cache[side] = (P.copy(), cr)
    return cr


def lift_eyelids(V, cameras, loops, out, lift, min_cos, height="current"):
    """Project the 2D targets of the 3D eyelid correspondences onto the eyeball (batched per eye and camera).

    Each target lies on the camera ray of its curve pixel, on the eyeball sphere
    grown by the lid point's height over it: the current height on ``V``
    (``height='current'``) or the rest height (``'rest'``).
    """
    groups = {}
    for i, side, ci in lift:
        groups.setdefault((side, ci), []).append(i)
    spheres = {}
    for (side, ci), idx in groups.items():
        if side not in spheres:
            spheres[side] = _eyeball_sphere(V, loops, side)
        c, r = spheres[side]
        cam = cameras[ci]
        cs = [out[i] for i in idx]
        px = np.concatenate([cc.pixels for cc in cs])
        pv = np.concatenate([cc.vertices for cc in cs])
        pb = np.concatenate([cc.bary for cc in cs])
        if height == "current":
            P = pb[:, 0, None] * V[pv[:, 0]] + pb[:, 1, None] * V[pv[:, 1]]
            rad = np.linalg.norm(P - c, axis=1)
        else:
            off = loops.eyelid_offset
            rad = r + pb[:, 0] * off[pv[:, 0]] + pb[:, 1] * off[pv[:, 1]]
        X, hit = project_to_sphere(cam, px, c, rad)
        # keep points whose ray meets the eyeball clearly: near the limb seen from this camera the lift is
        # ill-conditioned (and a lid point beyond the limb is hidden by the eye itself)
        ray = X - cam.center
        nrm = X - c
        cos = -np.einsum("ij,ij->i", ray, nrm) / (
            np.sqrt(np.einsum("ij,ij->i", ray, ray) * np.maximum(np.einsum("ij,ij->i", nrm, nrm), 1e-300)))
        keep = hit & (cos >= min_cos)
        start = 0
        for i, cc in zip(idx, cs):
            n = len(cc.vertices)
            kp = keep[start : start + n]
            Xi = X[start : start + n]
            start += n
            cc.pixels = None
            if kp.sum() < 2:
                continue  # dropped by the caller
            if kp.all():
                cc.targets = Xi
            else:
                cc.vertices, cc.bary, cc.curve_t, cc.targets = cc.vertices[kp], cc.bary[kp], cc.curve_t[kp], Xi[kp]
