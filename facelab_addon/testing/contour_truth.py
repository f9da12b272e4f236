"""Ground-truth contour inputs for tests, benchmarks and demos of the contour solve.

* :func:`ict_contour_loops`: :func:`~facelab_addon.core.solve.contour_loops.contour_loops`
  set up for an ICT-FaceKit model (free ``M_Face`` surface, the lips' weld to
  the mouth bag :data:`~facelab_addon.testing.synthetic.ICT_MOUTH_LOOP`, the
  sclera parts as eyeballs).
* :func:`synthetic_tracked_curves`: the tracked curves a tracker would
  deliver for a known mesh (Bhat et al. 2013, §4.2): the occluding contour on
  the envelope of the mouth or eye opening, projected and resampled, with
  optional pixel noise.

Conventions: vertices float64 (V,3) scene units; pixels top-left origin, y
down; cameras OpenCV (``core.capture.camera.Camera``).
"""

from __future__ import annotations

import numpy as np

from ..core.errors import FaceLabError, MeshError
from ..core.geometry.polyline import resample_polyline
from ..core.solve.contour_loops import ContourLoops, TrackedCurve, contour_loops
from ..core.solve.matching import half_points
from ..core.solve.occlusion import envelope_counts
from .synthetic import ICT_MOUTH_LOOP

__all__ = ["ict_contour_loops", "synthetic_tracked_curves"]


def ict_contour_loops(model, **kwargs) -> ContourLoops:
    """:func:`contour_loops` for an ICT-FaceKit model (``core.capture.ict.ICTModel``).

    Free surface: the ``M_Face`` part; mouth loop: vertices 6632-6705 (the
    lips' weld to the mouth bag); eyeballs: ``M_ScleraLeft`` /
    ``M_ScleraRight``. Keyword arguments are passed on.
    """
    kw = dict(
        fixed=~model.part_vertex_mask("M_Face"),
        mouth_loop=ICT_MOUTH_LOOP,
        eyeballs={
            "left": np.flatnonzero(model.part_vertex_mask("M_ScleraLeft")),
            "right": np.flatnonzero(model.part_vertex_mask("M_ScleraRight")),
        },
    )
    kw.update(kwargs)
    return contour_loops(model.neutral, model.faces, **kw)


def synthetic_tracked_curves(
    vertices,
    faces,
    cameras,
    loops: ContourLoops,
    *,
    names=None,
    spacing_px: float = 0.25,
    noise_px: float = 0.0,
    seed: int = 0,
) -> list:
    """The truth's occluding contours as a tracker would deliver them.

    For every camera and curve name, the half loop with the most silhouette
    edges on the *envelope of the opening* (silhouette edges that bound the
    mouth or eye opening with no other candidate's silhouette nearer to the
    opening at the same lateral image position: the line an artist traces
    along the dark opening; ties go to the rest-pose default) is projected
    and resampled every ``spacing_px`` pixels, corner to corner, ordered
    from image-left.

    Parameters
    ----------
    vertices : (V,3) float
        The ground-truth mesh, scene units.
    faces : (F,3) int
    cameras : list of Camera
    loops : ContourLoops
    names : list of str, optional
        Curve names to make (default: all the loops support).
    spacing_px : float
        Sample spacing along the curve, pixels.
    noise_px : float
        Standard deviation of Gaussian noise added to every sample, pixels.
    seed : int
        Noise seed.

    Returns
    -------
    list of TrackedCurve
        Curves whose samples all fall inside the image; the others are left
        out (a tracker cannot follow them).
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.shape != (loops.n_vertices, 3):
        raise MeshError(f"The truth has {len(V)} vertices, the loops were built for {loops.n_vertices}.")
    names = loops.curve_names() if names is None else list(names)
    rng = np.random.default_rng(seed)
    out = []
    for ci, cam in enumerate(cameras):
        counts = envelope_counts(V, cam, loops)
        for name in names:
            if name not in loops.halves:
                raise FaceLabError(f"The loops have no '{name}' candidates; use one of {loops.curve_names()}.")
            lo, hi = loops._pack.offsets[name]
            c = counts[lo:hi]
            best = np.flatnonzero(c == c.max())
            k = int(best[np.argmin(np.abs(best - loops.default_loop[name]))])
            X = half_points(V, loops.halves[name][k])
            if (cam.depth(X) <= 0).any():
                continue
            P = resample_polyline(cam.project(X), spacing_px)
            if noise_px > 0:
                P = P + rng.normal(0.0, noise_px, P.shape)
            if not cam.in_frame(P).all():
                continue
            if P[-1, 0] < P[0, 0]:
                P = P[::-1]
            out.append(TrackedCurve(name=name, camera=ci, pixels=P))
    return out
