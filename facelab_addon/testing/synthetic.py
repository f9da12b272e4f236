"""Ground-truth lip scenarios for the benchmarks, the demo and the tests.

A *scenario* starts from a known face shape (the truth, for example an
ICT-FaceKit pose), projects the truth's inner-lip silhouettes into a frontal
camera as the artist's sketch would be drawn (Dinev et al. 2018, §5, Fig. 3a),
and injects a smooth, deterministic capture error confined to the inner lips
("gap": lips pulled apart where they should touch, "cross": lips pushed
through each other). A correction method is then judged in 2D (its inner-lip
silhouette against the sketch, pixels) and in 3D (its inner-lip vertices
against the truth, millimetres).

Everything here is NumPy/SciPy; nothing imports bpy.

Mouth structure
---------------
All functions share one description of the mouth, :class:`Mouth`, built by
:func:`find_mouth` from the mesh and the ``fixed`` mask (the hidden parts:
mouth bag, teeth, gums, eyes, back of the head):

* the *mouth loop* is the border between the free lip surface and the fixed
  mouth bag (on ICT-FaceKit the 74-vertex ring 6632-6705, where the lips weld
  to the mouth bag). It is detected as the lowest closed border of the free
  triangles (not the largest one, which is the face's outer border), or taken
  from ``loop`` / ``near``;
* the *mouth corners* are the loop vertices with the smallest and largest
  coordinate along ``lateral = up x forward`` (image left and right in a
  frontal view);
* every free vertex within ``band_mm`` (geodesic, along mesh edges) of the
  loop gets the loop vertex it is closest to (its *column*) and the lip side
  of that loop vertex: +1 upper lip (above the corner-to-corner line along
  ``up``), -1 lower lip;
* the *lip tip* of a column is its vertex that reaches furthest into the mouth
  opening: the lowest one (along ``up``) of an upper-lip column, the highest
  of a lower-lip column. The tips form the line where the lips touch when the
  mouth is closed, and the inner-lip silhouettes seen from the front.

Conventions: vertices (V,3) float64 in scene units; ``units_per_mm`` scene
units per millimetre (0.1 for centimetres, the ICT-FaceKit default; 0.001 for
metres). Pixels: top-left origin, y down (``camera.Camera``).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra

from ..core.capture.camera import Camera
from ..core.errors import FaceLabError
from ..core.geometry.axes import unit_axis
from ..core.geometry.mesh import edge_length_graph, validate_mesh
from ..core.geometry.silhouette import lip_side, silhouette_edges
from ..core.lips.mouth import Mouth, find_mouth

__all__ = [
    "ICT_MOUTH_LOOP",
    "ICT_UP",
    "ICT_FORWARD",
    "frontal_camera",
    "lip_contours",
    "lip_error_weights",
    "inner_lip_mask",
    "inject_lip_error",
    "lip_separation",
]

#: ICT-FaceKit default: the 74 vertices where the lips weld to the mouth bag
#: (``M_Face`` / ``M_BackHead`` border around the mouth), neutral-mesh ids.
ICT_MOUTH_LOOP = np.arange(6632, 6706)
#: ICT-FaceKit axes: Y up, the face looks along +Z.
ICT_UP = (0.0, 1.0, 0.0)
ICT_FORWARD = (0.0, 0.0, 1.0)


def frontal_camera(
    vertices,
    mouth_center,
    distance: float = 40.0,
    focal_mm: float = 50.0,
    width: int = 1920,
    height: int = 1080,
    *,
    sensor_width_mm: float = 36.0,
    up=ICT_UP,
    forward=ICT_FORWARD,
) -> Camera:
    """A camera in front of the mouth, looking at it (the sketch view).

    Parameters
    ----------
    vertices : (V,3) float
        The face, scene units (used when ``mouth_center`` is given as vertex
        ids).
    mouth_center : (3,) float, or (k,) int
        The point looked at (scene units), or vertex ids whose mean it is
        (for example ``Mouth.loop``).
    distance : float
        Camera distance from ``mouth_center`` along ``forward``, scene units
        (40 = 40 cm for a centimetre scene such as ICT-FaceKit).
    focal_mm, sensor_width_mm : float
        Lens and sensor width in millimetres (a 50 mm lens on a 36 mm
        full-frame sensor by default).
    width, height : int
        Image size, pixels.
    up, forward : (3,) float
        Face up axis and the direction the face looks (ICT: +Y, +Z); the
        camera looks along ``-forward``.

    Returns
    -------
    Camera
        OpenCV convention, pixels top-left origin, y down.
    """
    V = np.asarray(vertices, dtype=np.float64)
    mc = np.asarray(mouth_center)
    if np.issubdtype(mc.dtype, np.integer):
        c = V[mc.reshape(-1)].mean(axis=0)
    else:
        c = mc.astype(np.float64).reshape(3)
    fwd = unit_axis(forward)
    cam = Camera.look_at(c + distance * fwd, c, unit_axis(up), focal_mm, sensor_width_mm, width, height)
    if (cam.depth(c[None]) <= 0).any():
        raise FaceLabError("The mouth is behind the frontal camera; 'distance' must be positive.")
    return cam


def lip_contours(vertices, faces, camera: Camera, fixed=None, *, mouth: Mouth | None = None, margin_mm=1.5,
                 spacing_px: float = 1.0):
    """The inner-lip silhouettes as an artist would sketch them.

    Only silhouette edges of the inner lips count: both ends free, within
    ``margin_mm`` (geodesic) beyond their column's lip tip from the mouth loop
    (so the lip fronts, nose, cheeks and chin are excluded), strictly between
    the mouth corners, and on the lip whose side they are on (the
    projected-normal test of ``silhouette.lip_side`` must agree with the mesh
    side). Of these, each lip's contour is the *envelope* bounding the mouth
    opening: at every pixel column the lowest upper-lip silhouette and the
    highest lower-lip silhouette (occlusion is ignored, as in
    ``silhouette.contour_distance``). Columns no silhouette covers are skipped,
    so the polyline bridges them with a straight segment.

    Parameters
    ----------
    vertices : (V,3) float
        The shape to draw (usually the truth), scene units.
    faces : (F,3) int
    camera : Camera
    fixed : (V,) bool, optional
        Hidden vertices (used to find the mouth when ``mouth`` is not given).
    mouth : Mouth, optional
        From :func:`find_mouth`; computed from ``vertices`` if omitted. Pass the
        truth's mouth to extract the contours of a deformed copy.
    margin_mm : float
        How far (mm, geodesic) beyond the lip tip the silhouette may lie.
    spacing_px : float
        Horizontal sample spacing of the polylines, pixels.

    Returns
    -------
    upper : (N,2) float64
        Upper-lip inner contour, pixels, ordered left to right.
    lower : (M,2) float64
        Lower-lip inner contour, pixels, ordered left to right.

    Raises
    ------
    FaceLabError
        When a lip has no inner silhouette in this view.
    """
    V, F = validate_mesh(vertices, faces)
    if mouth is None:
        mouth = find_mouth(V, F, fixed)
    band = np.isfinite(mouth.loop_distance) & (
        mouth.loop_distance <= mouth.tip_depth + margin_mm * mouth.units_per_mm
    ) & (np.abs(mouth.lateral_t) < 1.0)
    E = silhouette_edges(V, F, camera, face_mask=mouth.free_faces)
    E = E[band[E].all(axis=1)]
    out = []
    for s, name in ((1, "upper"), (-1, "lower")):
        Es = E[(mouth.side[E] == s).all(axis=1)]
        if len(Es):
            ls = lip_side(V, F, camera, Es.ravel()).reshape(-1, 2)
            Es = Es[(ls == s).all(axis=1)]
        if len(Es) == 0:
            raise FaceLabError(f"No {name}-lip inner silhouette is visible from this camera.")
        p = camera.project(V)
        a, b = p[Es[:, 0]], p[Es[:, 1]]
        x0, x1 = np.minimum(a[:, 0], b[:, 0]), np.maximum(a[:, 0], b[:, 0])
        xs = np.arange(np.floor(x0.min()), np.ceil(x1.max()) + spacing_px, spacing_px)
        xs = xs[(xs >= x0.min()) & (xs <= x1.max())]
        dx = b[:, 0] - a[:, 0]
        t = (xs[None, :] - a[:, 0:1]) / np.where(np.abs(dx) < 1e-12, 1e-12, dx)[:, None]
        inside = (xs[None, :] >= x0[:, None]) & (xs[None, :] <= x1[:, None])
        y = a[:, 1:2] + np.clip(t, 0, 1) * (b[:, 1] - a[:, 1])[:, None]
        if s == 1:
            ye = np.where(inside, y, -np.inf).max(axis=0)
        else:
            ye = np.where(inside, y, np.inf).min(axis=0)
        ok = np.isfinite(ye)
        out.append(np.stack([xs[ok], ye[ok]], axis=1))
    return out[0], out[1]


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def lip_error_weights(vertices, faces, fixed=None, *, mouth: Mouth | None = None, radius_mm: float = 6.0,
                      corner_power: float = 3.0):
    """Smooth weights in [0, 1] of the inner-lip error, and the lip side.

    ``w = across(v) * along(v)`` on the free vertices of the lip band:

    * across the lip: ``(1 - (g/R)^2)^2`` with ``g`` the geodesic distance to
      the lip-tip line of the vertex's own lip and ``R = radius_mm``, times a
      smoothstep from 0 at the mouth loop (where the lip welds to the fixed
      mouth bag) to 1 at the lip tip;
    * along the mouth: ``(1 - |t|^p)^2`` with ``t`` the lateral position (-1 and
      +1 at the mouth corners) and ``p = corner_power``: largest at the
      midline, zero at and beyond the corners.

    Both factors are C1 and reach zero at the region border, so the error has
    no crease. Weights depend on the shape passed (use the truth).

    Parameters
    ----------
    vertices : (V,3) float
        Scene units.
    faces : (F,3) int
    fixed : (V,) bool, optional
        Hidden vertices (weights are zero there).
    mouth : Mouth, optional
        Default ``find_mouth(vertices, faces, fixed)``.
    radius_mm : float
        Reach of the error from the lip tips across the lips, millimetres.
    corner_power : float
        Exponent ``p`` of the corner falloff (larger: flatter in the middle).

    Returns
    -------
    weights : (V,) float64
        In [0, 1].
    side : (V,) int8
        +1 upper lip, -1 lower lip, 0 elsewhere.
    """
    V, F = validate_mesh(vertices, faces)
    if mouth is None:
        mouth = find_mouth(V, F, fixed)
    n = len(V)
    R = radius_mm * mouth.units_per_mm
    G = edge_length_graph(V, F[mouth.free_faces], min_length=1e-12)[0]
    g_tip = np.full(n, np.inf)
    for s in (1, -1):
        tips = mouth.tip[(mouth.side[mouth.tip] == s) & (np.abs(mouth.lateral_t[mouth.tip]) < 1.0)]
        if len(tips):
            d = dijkstra(G, directed=False, indices=tips, min_only=True, limit=R)
            sel = mouth.side == s
            g_tip[sel] = d[sel]
    across = np.where(np.isfinite(g_tip), (1.0 - np.minimum(g_tip / R, 1.0) ** 2) ** 2, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        inward = _smoothstep(np.where(mouth.tip_depth > 0, mouth.loop_distance / mouth.tip_depth, 1.0))
    inward = np.where(np.isfinite(mouth.loop_distance), inward, 0.0)
    t = np.abs(mouth.lateral_t)
    along = np.clip(1.0 - t**corner_power, 0.0, 1.0) ** 2
    w = across * inward * along
    w[mouth.side == 0] = 0.0
    if fixed is not None:
        w[np.asarray(fixed, bool)] = 0.0
    return w, mouth.side.copy()


def inner_lip_mask(vertices, faces, fixed=None, *, mouth: Mouth | None = None, radius_mm: float = 6.0,
                   corner_power: float = 3.0, threshold: float = 1e-3):
    """(V,) bool: the inner-lip region over which 3D lip errors are measured.

    Definition: the vertices where :func:`lip_error_weights` (same arguments)
    exceeds ``threshold``, i.e. the support of the injected error: free
    vertices within ``radius_mm`` (geodesic) of the lip-tip lines, between the
    mouth loop and the lip fronts, strictly between the mouth corners. It
    depends only on the truth shape, not on the error kind or amount. On
    ICT-FaceKit (6 mm) it holds about 900 vertices.

    Parameters
    ----------
    vertices, faces, fixed, mouth, radius_mm, corner_power
        As in :func:`lip_error_weights`.
    threshold : float
        Weight below which a vertex is outside the region.
    """
    w, _ = lip_error_weights(vertices, faces, fixed, mouth=mouth, radius_mm=radius_mm, corner_power=corner_power)
    return w > threshold


def inject_lip_error(
    vertices,
    faces,
    fixed=None,
    *,
    kind: str = "gap",
    amount_mm: float = 2.5,
    mouth: Mouth | None = None,
    radius_mm: float = 6.0,
    corner_power: float = 3.0,
):
    """A realistic, smooth capture error of the inner lips.

    The lip tips are displaced along ``mouth.up`` by
    ``±amount_mm / 2 * weights`` (:func:`lip_error_weights`), the upper and
    lower lip in opposite directions, so at the midline the lips end up
    ``amount_mm`` further apart ("gap": the capture failed to close the lips,
    upper lip up, lower lip down) or ``amount_mm`` further into each other
    ("cross": they interpenetrate where they should just touch). The error
    fades smoothly to zero across the lips (within ``radius_mm`` of the lip
    tips, and at the weld to the mouth bag) and toward the mouth corners. It
    is deterministic.

    Parameters
    ----------
    vertices : (V,3) float
        The truth, scene units. Not modified.
    faces : (F,3) int
    fixed : (V,) bool, optional
        Hidden vertices; they never move.
    kind : {"gap", "cross"}
    amount_mm : float
        Extra separation ("gap") or overlap ("cross") at the midline, mm
        (``mouth.units_per_mm`` converts to scene units).
    mouth : Mouth, optional
        Default ``find_mouth(vertices, faces, fixed)``.
    radius_mm, corner_power : float
        Shape of the error, see :func:`lip_error_weights`.

    Returns
    -------
    captured : (V,3) float64
        The truth with the error, scene units.
    error_mask : (V,) bool
        Where the error is non-zero (``inner_lip_mask`` with the same
        arguments).
    """
    V, F = validate_mesh(vertices, faces)
    if kind not in ("gap", "cross"):
        raise FaceLabError(f"Unknown lip error kind {kind!r}; use 'gap' or 'cross'.")
    if mouth is None:
        mouth = find_mouth(V, F, fixed)
    w, side = lip_error_weights(V, F, fixed, mouth=mouth, radius_mm=radius_mm, corner_power=corner_power)
    sign = 1.0 if kind == "gap" else -1.0
    d = sign * 0.5 * amount_mm * mouth.units_per_mm * (side * w)
    captured = V + d[:, None] * mouth.up[None, :]
    return captured, w > 1e-3


def lip_separation(vertices, mouth: Mouth, at: float = 0.0) -> float:
    """Signed distance between the lips along ``mouth.up`` at a lateral position.

    For every lip column of ``mouth`` (topology from the truth), the vertex of
    ``vertices`` reaching furthest into the mouth opening is found (lowest of
    an upper-lip column, highest of a lower one, within ``tip_depth + 3 mm`` of
    the loop); each lip's tip line is interpolated at lateral position ``at``
    (-1, +1 = corners).

    Parameters
    ----------
    vertices : (V,3) float
        Any shape with the mouth's topology, scene units.
    mouth : Mouth
    at : float
        Normalised lateral position (0 = between the corners).

    Returns
    -------
    float
        Upper tip minus lower tip along ``up``, scene units: positive when the
        lips are apart, negative when they cross.
    """
    V = np.asarray(vertices, dtype=np.float64)
    h = (V - mouth.center) @ mouth.up
    t = mouth.lateral_position(V)
    ok = np.isfinite(mouth.loop_distance) & (mouth.loop_distance <= mouth.tip_depth + 3.0 * mouth.units_per_mm)
    res = []
    for s in (1, -1):
        idx = np.flatnonzero(ok & (mouth.side == s))
        key = s * h[idx]
        order = np.lexsort((key, mouth.column[idx]))
        col = mouth.column[idx][order]
        first = np.r_[True, col[1:] != col[:-1]]
        tips = idx[order][first]
        o = np.argsort(t[tips])
        res.append(np.interp(at, t[tips][o], h[tips][o]))
    return float(res[0] - res[1])
