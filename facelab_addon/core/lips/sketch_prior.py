"""Where the sketch refinement may move the mesh, and how strongly each vertex keeps its place.

Dinev et al. 2018 §5 (Eq. 1) anchor every vertex to its captured position with one weight
``lambda_pos`` and preserve the captured Laplacian coordinates with ``lambda_reg``. Because
``E_reg = ||L (X - X̄)||^2`` is a bi-Laplacian energy of the displacement, the balance of the two
sets how far a silhouette's displacement carries across the lips: about
``(lambda_reg / lambda_pos)^(1/4)`` edge rings (2.3 with the paper's 3 / 0.1), so a capture error
that is smooth across the whole lip band is corrected only beside the silhouette. This module
provides the parts that make the refinement independent of the mesh's resolution, units and
topology:

* :func:`separate_parts`: the vertices off the largest connected piece (teeth, tongue, eyes): the
  hidden parts held when no ``fixed`` mask is given;
* :func:`sketch_scale`: the width of the sketched mouth in scene units (the sketch's width in
  pixels back-projected at the depth of the lips), the unit of every size below;
* :func:`free_region`: the vertices within a geodesic radius (a multiple of the mouth width) of
  the lip area, or the interior of a painted lip region (``FL_lips``) with its border held;
* :func:`anchor_weights`: the per-vertex ``w_i`` of ``E_pos``: the paper's constant, or the
  ``"smooth"`` prior where ``w_i = lambda_reg * (h_i / reach)^4`` (``h_i`` the local edge length)
  so the displacement decays over ``reach`` scene units whatever the mesh density; or the ``"band"``
  prior: the same outside a painted lip region, and inside it (whose border is held, so the border
  bounds the correction) a reach of at least :data:`BAND_RINGS` edge lengths, so the silhouettes'
  displacement carries across the lip band on a coarse mesh as on a dense one;
* :func:`depth_terms`: with several views, ``E_reg`` once more on the component of the Laplacian
  coordinates along the main camera's rays (the depth it cannot see), so a second view's correction
  comes out smooth in depth;
* :func:`rest_depth_terms`: with one view, the depth it cannot see taken from the face's rest pose:
  the correction is kept off the main camera's rays as they cross the face at rest, turned with the
  head (a trimmed rigid fit from the rest pose to the frame), so a nodded head's correction keeps
  the nod's share of depth.

Shapes: vertices (V,3) float64 scene units, triangles (F,3) int64, masks (V,) bool.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ..errors import UsageError
from ..geometry.deform import PointConstraints
from ..geometry.mesh import connected_components, edge_length_graph, faces_within
from ..geometry.rigid import rigid_fit

__all__ = ["PRIORS", "BAND_RINGS", "separate_parts", "sketch_scale", "crop_faces", "local_faces", "free_region",
           "seed_distances",
           "anchor_weights", "mean_edge_length", "depth_terms", "rest_depth_terms", "REST_KEEP", "HEAD_RADIUS"]

#: The energies :func:`anchor_weights` offers: Dinev et al.'s Eq. 1 as written, the smooth prior, or the band prior.
PRIORS = ("paper", "smooth", "band")
#: The band prior's least reach inside the painted lip region, in edge lengths (see :func:`anchor_weights`).
BAND_RINGS = 3.0
#: :func:`rest_depth_terms`: the fraction of the head's vertices (those that moved most rigidly) the head's turn
#: is fitted on; an opened jaw, a smile or a raised brow is left out.
REST_KEEP = 0.5
#: :func:`rest_depth_terms`: the head's vertices are those within this many mouth widths of the lips.
HEAD_RADIUS = 1.5


def separate_parts(faces, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices not on the largest connected piece of the mesh (teeth, tongue, eyes...).

    Vertices used by no triangle count as separate. With one piece, nothing is separate.

    Parameters
    ----------
    faces : (F,3) int array_like
    n_vertices : int
    """
    F = np.asarray(faces, dtype=np.int64)
    lab = connected_components(F, int(n_vertices))
    used = np.zeros(int(n_vertices), bool)
    used[F.ravel()] = True
    if not used.any():
        return np.zeros(int(n_vertices), bool)
    counts = np.bincount(lab[used], minlength=lab.max() + 1)
    return lab != int(np.argmax(counts))


def sketch_scale(camera, sketch_px, points) -> float:
    """Width of the sketched mouth in scene units.

    The horizontal extent of the sketch in pixels times the median depth of ``points`` (the lips
    near the sketch) over the focal length: independent of the mesh, its units and the image size.

    Parameters
    ----------
    camera : Camera
    sketch_px : (N,2) float
        Sketch samples, pixels.
    points : (k,3) float
        Lip vertices near the sketch, scene units (in front of the camera).

    Returns
    -------
    float
        Scene units (> 0).
    """
    P = np.asarray(sketch_px, dtype=np.float64)
    extent = float(np.hypot(np.ptp(P[:, 0]), np.ptp(P[:, 1])))
    z = camera.depth(np.asarray(points, dtype=np.float64))
    z = float(np.median(z[z > 0])) if np.any(z > 0) else 1.0
    return max(extent, 1.0) * z / float(camera.K[0, 0])


def crop_faces(vertices, faces, seeds, radius: float) -> np.ndarray:
    """(k,) int64 indices of the triangles inside the bounding box of ``seeds`` grown by ``radius``.

    Every vertex within geodesic (or Euclidean) distance ``radius`` of a seed is in the box, so
    searches and operators bounded by ``radius`` need only these triangles.
    """
    V = np.asarray(vertices, dtype=np.float64)
    P = V[np.asarray(seeds, bool)]
    lo, hi = P.min(0) - radius, P.max(0) + radius
    inside = (V[:, 0] >= lo[0]) & (V[:, 0] <= hi[0])
    for k in (1, 2):
        inside &= (V[:, k] >= lo[k]) & (V[:, k] <= hi[k])
    return np.flatnonzero(faces_within(inside, faces))


def local_faces(faces, region, rings: int = 2) -> np.ndarray:
    """(k,) int64 indices of the triangles within ``rings`` triangle rings of the vertices ``region`` (V,) bool.

    With ``rings=2`` every vertex of ``region`` and its neighbours keep their whole one-ring, so a
    Laplacian built from these triangles has the rows of the whole mesh on them.
    """
    F = np.asarray(faces)
    m = np.asarray(region, bool).copy()
    sel = faces_within(m, F, every=False)
    for _ in range(int(rings) - 1):
        m[F[sel].ravel()] = True
        sel = faces_within(m, F, every=False)
    return np.flatnonzero(sel)


def mean_edge_length(vertices, faces, n_vertices: int | None = None) -> np.ndarray:
    """(V,) mean length of the edges at each vertex, scene units (0 for unused vertices)."""
    V = np.asarray(vertices, dtype=np.float64)
    n = len(V) if n_vertices is None else int(n_vertices)
    G, E, w = edge_length_graph(V, faces, n)
    s = np.bincount(E.ravel(), weights=np.repeat(w, 2), minlength=n)
    c = np.bincount(E.ravel(), minlength=n)
    return np.divide(s, c, out=np.zeros(n), where=c > 0)


def seed_distances(vertices, faces, seeds, limit: float) -> np.ndarray:
    """(V,) geodesic distance (along edges, scene units) of every vertex from the vertices ``seeds`` (V,) bool,
    ``inf`` beyond ``limit`` (only the triangles in the seeds' box grown by ``limit`` are searched)."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    n = len(V)
    seeds = np.asarray(seeds, bool)
    src = np.flatnonzero(seeds)
    if len(src) == 0:
        return np.full(n, np.inf)
    # a geodesic ball lies inside the Euclidean one: search only the triangles in the seeds' box + limit
    Fc = F[crop_faces(V, F, seeds, limit)]
    G = edge_length_graph(V, Fc, n, min_length=1e-12)[0]
    return dijkstra(G, directed=False, indices=src, min_only=True, limit=float(limit))


def free_region(vertices, faces, seeds, radius: float, *, fixed=None, lips=None, distances=None):
    """The vertices the refinement solves for; every other vertex is held exactly.

    Parameters
    ----------
    vertices : (V,3) float
        Scene units.
    faces : (F,3) int
    seeds : (V,) bool
        The lip area near the sketch.
    radius : float
        Geodesic reach (along edges, scene units) of the region from ``seeds``.
    fixed : (V,) bool, optional
        Hidden vertices: never free.
    lips : (V,) bool, optional
        A painted inner-lip region (``FL_lips``). When given, the free vertices are those of its
        triangles except its border (the vertices it shares with outside triangles, held as the
        Poisson solve of Propagate holds them); ``radius`` still bounds them.
    distances : (V,) float, optional
        :func:`seed_distances` of ``seeds`` with a ``limit`` of at least ``radius`` (kept by a caller
        that asks for the region of the same seeds at several radii); default computed here.

    Returns
    -------
    (V,) bool
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    n = len(V)
    seeds = np.asarray(seeds, bool)
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    if not seeds.any():
        return np.zeros(n, bool)
    d = seed_distances(V, F, seeds, radius) if distances is None else np.asarray(distances)
    region = (d <= float(radius)) & ~fixed
    if lips is not None:
        lips = np.asarray(lips, bool)
        inside = faces_within(lips, F)
        on_lip = np.zeros(n, bool)
        on_lip[F[inside].ravel()] = True
        outside = np.zeros(n, bool)
        outside[F[~inside].ravel()] = True
        region &= on_lip & ~outside
    return region


def anchor_weights(vertices, faces, region, *, prior: str, lambda_pos: float, lambda_reg: float,
                   reach: float | None = None, fixed=None, edge_length=None, lips=None,
                   band_rings: float = BAND_RINGS) -> np.ndarray:
    """(V,) weights ``w_i`` of ``E_pos = sum_i w_i ||x_i - x̄_i||^2``.

    Parameters
    ----------
    vertices : (V,3) float
        Scene units.
    faces : (F,3) int
    region : (V,) bool
        Free vertices (others are held exactly; their weight does not matter).
    prior : {"paper", "smooth", "band"}
        ``"paper"``: ``lambda_pos`` everywhere and 1 on ``fixed`` (Eq. 1). ``"smooth"``:
        ``lambda_reg * (h_i / reach)^4`` with ``h_i`` the mean edge length at the vertex, so the
        bi-Laplacian ``E_reg`` carries a silhouette's displacement about ``reach`` scene units
        across the lips on any mesh density; never more than ``lambda_pos``. ``"band"``: as
        ``"smooth"``, but on the vertices of ``lips`` the reach is at least ``band_rings`` edge
        lengths: inside a lip region whose border is held the border bounds the correction, and on a
        coarse mesh (edges of a few mm) a reach of about one edge would leave the correction on the
        silhouettes' own ring.
    lambda_pos, lambda_reg : float
        Weights of Eq. 1.
    reach : float, optional
        Decay length of the smooth prior, scene units (required for ``"smooth"``).
    fixed : (V,) bool, optional
    edge_length : (V,) float, optional
        Precomputed :func:`mean_edge_length`.
    lips : (V,) bool, optional
        ``"band"``: the painted lip region (without it, ``"band"`` is ``"smooth"``).
    band_rings : float
        ``"band"``: inside ``lips`` the reach is at least this many of the vertex's edge lengths.
    """
    n = len(vertices)
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    if prior == "paper":
        return np.where(fixed, 1.0, float(lambda_pos))
    if prior not in ("smooth", "band"):
        raise UsageError(f"prior must be one of {PRIORS}, got {prior!r}")
    if reach is None or not reach > 0:
        raise UsageError(f"the {prior} prior needs a positive reach (scene units), got {reach!r}")
    h = mean_edge_length(vertices, faces, n) if edge_length is None else np.asarray(edge_length, float)
    r = np.full(n, float(reach))
    if prior == "band" and lips is not None:
        lm = np.asarray(lips, bool)
        r[lm] = np.maximum(r[lm], float(band_rings) * h[lm])
    w = float(lambda_reg) * (h / r) ** 4
    w = np.minimum(w, float(lambda_pos))
    return np.where(fixed, 1.0, np.maximum(w, 1e-12))


def depth_terms(L, vertices, camera, rows, weight: float) -> PointConstraints:
    """``weight * sum_i (r_i · (L X - L X̄)_i)^2`` over ``rows``, as point constraints of the deformer.

    ``r_i`` is the unit ray of ``camera`` through vertex ``i`` of ``vertices`` (X̄). Added to ``E_reg``
    (``lambda_reg ||L X - L X̄||^2``) it makes the Laplacian coordinates stiffer along the camera's rays than
    across them: the depth of a correction, which this camera cannot see, has to be smooth (a depth the
    lips need, as a nodded head's, is a smooth field over the lip band and still comes through), while what
    the camera sees bends as before. Each term is one Laplacian row, a point constraint on the row's vertices
    with the rank-1 metric ``r_i r_iᵀ`` (``deform.PointConstraints``). They stay the same over a Refine and
    couple the coordinates, so ``LaplacianDeformer.with_terms`` folds them into one factor
    (``deform.CoupledDeformer``) and the moving silhouette constraints are added to it by Woodbury.

    Parameters
    ----------
    L : (V,V) sparse matrix
        The Laplacian of ``E_reg``.
    vertices : (V,3) float
        X̄, the captured mesh, scene units (its Laplacian coordinates are kept).
    camera : Camera
        The main view's camera.
    rows : (V,) bool
        Vertices whose Laplacian row gets a term (the free region).
    weight : float
        ``s`` of every term (``depth_reg * lambda_reg``).

    Returns
    -------
    PointConstraints
        ``rows.sum()`` constraints.
    """
    V = np.asarray(vertices, dtype=np.float64)
    idx = np.flatnonzero(rows)
    Lr = sp.csr_matrix(L)[idx]
    nnz = np.diff(Lr.indptr)
    k = max(int(nnz.max()) if len(nnz) else 1, 1)
    row = np.repeat(np.arange(len(idx)), nnz)
    col = np.arange(Lr.nnz) - Lr.indptr[row]
    vv = np.zeros((len(idx), k), np.int64)
    bb = np.zeros((len(idx), k))
    vv[row, col] = Lr.indices
    bb[row, col] = Lr.data
    vv[bb == 0] = idx[np.nonzero(bb == 0)[0]]  # padding: the row's own vertex, weight 0
    r = _unit_rays(camera, V[idx])
    return PointConstraints(vv, bb, Lr @ V, r[:, :, None] * r[:, None, :], float(weight))


def rest_depth_terms(vertices, rest_vertices, camera, rows, weight: float, *, mouth_width: float,
                     keep: float = REST_KEEP, radius: float = HEAD_RADIUS):
    """``weight * sum_i (f_i · (x_i - x̄_i))^2`` over ``rows``: the depth one view cannot see, from the rest pose.

    One camera constrains a silhouette vertex across its ray only; how far the correction goes along the ray
    is the prior's choice. The isotropic prior chooses none, right when the face is posed as the capture's
    error was made (at rest, or carried rigidly with the camera, as a helmet camera is). When the head has
    turned (a rig's nod, or head motion baked into the capture), an error of the face's own shape (lips
    apart along the face's up axis) has a share along the camera's rays, which the isotropic prior drops.
    Here ``f_i = R u_i``: ``u_i`` the main camera's ray through the rest vertex, ``R`` the head's turn from
    the rest pose to this frame (:func:`~facelab_addon.core.geometry.rigid.rigid_fit`, trimmed to the
    ``keep`` most rigid of the vertices within ``radius`` mouth widths of the lips). Unturned, ``f_i`` is the
    camera's own ray and the terms change nothing.

    Parameters
    ----------
    vertices : (V,3) float
        X̄, the captured mesh on this frame, scene units.
    rest_vertices : (V,3) float
        The same face at rest (without the head's turn), in the same space and units.
    camera : Camera
        The main view's camera.
    rows : (V,) bool
        Vertices that get a term (the free region).
    weight : float
        ``s`` of every term (scene units squared, as ``E_pos``).
    mouth_width : float
        Scene units (:func:`sketch_scale`).
    keep, radius : float
        See :data:`REST_KEEP`, :data:`HEAD_RADIUS`.

    Returns
    -------
    terms : PointConstraints or None
        ``rows.sum()`` constraints; None when the rest pose does not fit the frame rigidly (the median
        residual of the kept vertices over 0.1 mouth widths: not the same face, turned).
    turn_deg : float or None
        The angle of ``R``, degrees.

    Raises
    ------
    UsageError
        ``rest_vertices`` not of the shape of ``vertices``, or not finite.
    """
    V = np.asarray(vertices, dtype=np.float64)
    V0 = np.asarray(rest_vertices, dtype=np.float64)
    if V0.shape != V.shape or not np.isfinite(V0).all():
        raise UsageError(f"rest_vertices must be finite positions of the same {V.shape} shape as the mesh, "
                         f"got {V0.shape}; pass the face's rest pose (its Basis) in the same space.")
    idx = np.flatnonzero(rows)
    c = V[idx].mean(axis=0)
    near = np.linalg.norm(V - c, axis=1) <= radius * mouth_width
    near[idx] = False
    if near.sum() < 3:
        near = ~np.asarray(rows, bool)
    R, t = rigid_fit(V0[near], V[near], keep=keep)
    res = np.linalg.norm(V0[near] @ R.T + t - V[near], axis=1)
    if np.median(res) > 0.1 * mouth_width:
        return None, None  # the rest pose is not this face turned (another shape, another place): no prior
    f = _unit_rays(camera, V0[idx]) @ R.T
    turn = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    return PointConstraints(idx[:, None], np.ones((len(idx), 1)), V[idx], f[:, :, None] * f[:, None, :],
                            float(weight)), turn


def _unit_rays(camera, points) -> np.ndarray:
    """(N,3) unit directions from ``camera``'s centre through (N,3) ``points`` (scene units)."""
    r = np.asarray(points, dtype=np.float64) - camera.center
    return r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)
