"""Mouth and inner-lip regions for lip-correction learning.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance
Capture", §4 and Fig. 2: the mesh is split into a *mouth region* whose capture
is trusted (blue) and an *inner-lip region* (red) that is predicted from it;
the rest (gray) is ignored. §6.2 notes that the regions should follow the
boundary between high- and low-confidence capture: too small a lip region
keeps badly captured corners, too large a one throws away useful input.

In FaceLab the regions are vertex groups (``FL_mouth``, ``FL_lips``) and a
triangle belongs to a region when all three of its vertices do
(:func:`faces_in_region`). :func:`auto_regions` proposes both regions as
geodesic bands (:mod:`facelab_addon.core.geometry.geodesic`) around the
*inner-lip contact loop* (the closed curve where the upper and lower lip
meet), which :func:`.lip_loop.inner_lip_loop` finds automatically or takes
from a selected edge loop. Positions and widths are in scene units.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components as _cc

from ..errors import MeshError, RegionError
from ..geometry.geodesic import geodesic_distance
from ..geometry.mesh import vertex_adjacency
from .lip_loop import region_mesh, inner_lip_loop, loop_width

__all__ = [
    "faces_in_region",
    "region_vertex_mask",
    "region_border",
    "validate_regions",
    "auto_regions",
    "inner_lip_vertices",
    "DEFAULT_LIP_WIDTH",
    "DEFAULT_MOUTH_WIDTH",
    "MIN_LIP_RINGS",
]

#: Default inner-lip band half-width, as a fraction of the mouth width (corner
#: to corner distance of the contact loop). A wider band (about each lip's height) lets
#: Refine remove an error spread further across the lips, but Propagate, which regresses
#: the whole deformation of the band and holds only its border, then needs more training
#: frames: see docs/sketch-refine.md and docs/benchmarks.md (``benchmarks/lip_band.py``).
DEFAULT_LIP_WIDTH = 0.12
#: The lip band is at least this many edge lengths (median at the contact loop) wide, so
#: on a coarse mesh its interior, which Refine moves, is still two edge rings deep.
MIN_LIP_RINGS = 3.0
#: Default width of the mouth band outside the lip band, as a fraction of the
#: mouth width. About 2 cm on ICT-FaceKit.
DEFAULT_MOUTH_WIDTH = 0.45


# --------------------------------------------------------------------------
# Regions as triangle sets
# --------------------------------------------------------------------------


def faces_in_region(faces, vertex_mask) -> np.ndarray:
    """Triangles whose three vertices are all in a vertex region.

    Parameters
    ----------
    faces : (F,3) int array_like
        Triangles.
    vertex_mask : (V,) bool array_like, or (k,) int array_like
        The region as a boolean mask over vertices, or as vertex indices
        (for example the members of a vertex group).

    Returns
    -------
    (n,) int64 ndarray
        Sorted indices of the triangles inside the region.
    """
    F = np.asarray(faces, dtype=np.int64)
    m = np.asarray(vertex_mask)
    if m.dtype != bool:
        idx = m.astype(np.int64).ravel()
        n = int(max(F.max(initial=-1), idx.max(initial=-1)) + 1)
        mask = np.zeros(n, dtype=bool)
        mask[idx] = True
        m = mask
    if F.size and F.max() >= len(m):
        raise MeshError(
            f"The region mask has {len(m)} entries but the faces use vertex {int(F.max())}; "
            "build the mask on the same mesh as the faces."
        )
    return np.flatnonzero(m[F].all(axis=1)).astype(np.int64)


def region_vertex_mask(faces, region_faces, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices used by the triangles ``faces[region_faces]``."""
    F = np.asarray(faces, dtype=np.int64)
    m = np.zeros(int(n_vertices), dtype=bool)
    m[F[np.asarray(region_faces, dtype=np.int64)].ravel()] = True
    return m


def region_border(faces, region_faces, n_vertices: int | None = None) -> np.ndarray:
    """Border vertices of a triangle region: used by a region and a non-region triangle.

    These are the vertices held fixed (Dirichlet) when the inner-lip region is
    rebuilt from predicted deformation gradients (Dinev et al. 2018, §4, last
    paragraph). Vertices on an open mesh boundary that touch only region
    triangles are not border vertices.

    Parameters
    ----------
    faces : (F,3) int array_like
        All triangles of the mesh.
    region_faces : (n,) int array_like
        Indices of the region's triangles.
    n_vertices : int, optional
        Vertex count ``V`` (default: ``faces.max() + 1``).

    Returns
    -------
    (b,) int64 ndarray
        Sorted vertex indices.
    """
    F = np.asarray(faces, dtype=np.int64)
    nv = int(F.max() + 1) if n_vertices is None else int(n_vertices)
    inside = np.zeros(len(F), dtype=bool)
    inside[np.asarray(region_faces, dtype=np.int64)] = True
    a = np.zeros(nv, dtype=bool)
    b = np.zeros(nv, dtype=bool)
    a[F[inside].ravel()] = True
    b[F[~inside].ravel()] = True
    return np.flatnonzero(a & b).astype(np.int64)


def validate_regions(faces, mouth_faces, lip_faces, n_vertices: int, vertices=None):
    """Check a mouth/lip region pair and return both as sorted unique int64 arrays.

    Parameters
    ----------
    faces : (F,3) int array_like
        Triangles of the mesh.
    mouth_faces, lip_faces : (m,), (n,) int array_like
        Triangle indices of the mouth (trusted) and inner-lip (predicted) regions.
    n_vertices : int
        Vertex count ``V``.
    vertices : (V,3) float, optional
        Rest positions: a borderless piece whose vertices all sit on other vertices is then named as a
        duplicate made in place (Shift+D) of those.

    Returns
    -------
    mouth_faces : (m,) int64 ndarray
    lip_faces : (n,) int64 ndarray

    Raises
    ------
    RegionError
        If a region is empty, indices are out of range, the regions share
        triangles, or a connected piece of the lip region has no border vertex
        (its position would be undetermined).
    """
    F = np.asarray(faces, dtype=np.int64)
    out = []
    for name, group, r in (("mouth", "FL_mouth", mouth_faces), ("inner-lip", "FL_lips", lip_faces)):
        r = np.unique(np.asarray(r, dtype=np.int64).ravel())
        if r.size == 0:
            raise RegionError(
                f"The {name} region is empty (no triangle has all three vertices in '{group}'); "
                "assign vertices to the group or run Auto Regions."
            )
        if r[0] < 0 or r[-1] >= len(F):
            raise RegionError(
                f"The {name} region refers to triangle {int(r[-1] if r[-1] >= len(F) else r[0])}, but the mesh has "
                f"{len(F)} triangles; rebuild the regions on this mesh (Auto Regions)."
            )
        out.append(r)
    mouth, lips = out
    both = np.intersect1d(mouth, lips)
    if both.size:
        raise RegionError(
            f"The mouth and inner-lip regions overlap in {both.size} triangles (first {both[:5].tolist()}); "
            "remove the shared vertices from one of 'FL_mouth'/'FL_lips' so only the border ring is shared."
        )
    border = region_border(F, lips, n_vertices)
    if border.size == 0:
        raise RegionError(
            "The inner-lip region has no border with the rest of the mesh, so its position is undetermined; "
            "make 'FL_lips' a band that does not cover a whole mesh piece (Auto Regions does this)."
        )
    # every connected piece of the lip region must touch the border
    LF = F[lips]
    used = np.unique(LF)
    remap = -np.ones(int(n_vertices), dtype=np.int64)
    remap[used] = np.arange(len(used))
    ncomp, lab = _cc(vertex_adjacency(remap[LF], len(used)), directed=False)
    has_border = np.zeros(ncomp, dtype=bool)
    has_border[lab[remap[border]]] = True
    if not has_border.all():
        bad = used[~has_border[lab]]
        twins = _coincident_twins(vertices, bad)
        if twins is not None:
            raise RegionError(
                f"{int((~has_border).sum())} piece(s) of the inner-lip region have no border vertex: their "
                f"{len(bad)} vertices (first {bad[:5].tolist()}) are duplicates lying exactly on other vertices "
                f"(first {twins[:5].tolist()}), faces duplicated in place (Shift+D with the move cancelled). "
                "Delete the duplicated faces, or select all and Merge by Distance, then run again."
            )
        raise RegionError(
            f"{int((~has_border).sum())} piece(s) of the inner-lip region have no border vertex "
            f"(first vertices {bad[:5].tolist()}); remove them from 'FL_lips' or connect them to the mouth region."
        )
    return mouth, lips


def _coincident_twins(vertices, ids):
    """(k,) for each vertex of ``ids`` a different vertex at the same position, or None when some has none."""
    if vertices is None:
        return None
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
        return None
    from scipy.spatial import cKDTree

    others = np.setdiff1d(np.arange(len(V)), ids)
    if not len(others):
        return None
    tol = 1e-6 * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    d, j = cKDTree(V[others]).query(V[ids], distance_upper_bound=max(tol, 1e-300))
    return others[j] if np.isfinite(d).all() else None


# --------------------------------------------------------------------------
# Geodesic bands
# --------------------------------------------------------------------------


def auto_regions(vertices, faces, loop=None, lip_width=None, mouth_width=None, *, min_rings: float = MIN_LIP_RINGS,
                 return_distance: bool = False, **find):
    """Propose the mouth (trusted) and inner-lip (predicted) regions.

    Both are geodesic bands around the inner-lip contact loop (Dinev et al.
    2018, Fig. 2): the lip region holds the vertices within ``lip_width`` of
    the loop (on both lips, including the inner lip surface that curls into
    the mouth); the mouth region holds the vertices between ``lip_width`` and
    ``lip_width + mouth_width`` on the face side (a mouth bag behind the lips
    is left out), plus the lip vertices on the shared border, so the triangles
    between the two bands belong to the mouth region.

    Parameters
    ----------
    vertices : (V,3) array_like
        Rest-pose positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        The inner-lip loop (for example a selected edge loop); found with
        :func:`inner_lip_loop` when omitted.
    lip_width : float, optional
        Geodesic half-width of the lip band, scene units. Default
        ``DEFAULT_LIP_WIDTH`` times the mouth width (corner to corner).
    mouth_width : float, optional
        Geodesic width of the mouth band, scene units. Default
        ``DEFAULT_MOUTH_WIDTH`` times the mouth width.
    min_rings : float
        The lip band is at least this many edge lengths wide (the median
        length of the edges at the loop, each loop vertex's edges weighted by
        the length of loop it stands for), whatever ``lip_width`` says, so a
        coarse mesh keeps a lip band with an interior.
    return_distance : bool
        Also return the (V,) geodesic distance to the loop and the loop.
    **find
        Keyword arguments of :func:`inner_lip_loop` for finding the loop
        (``max_gap``, ``rays`` through the sketch, ``toward`` the camera,
        ``gap_name``).

    Returns
    -------
    mouth_mask : (V,) bool ndarray
    lip_mask : (V,) bool ndarray
    distance : (V,) float64 ndarray, only if ``return_distance``
        Geodesic distance to the loop, scene units (``inf`` beyond the bands).
    loop : (L,) int64 ndarray, only if ``return_distance``

    Raises
    ------
    RegionError
        If the loop cannot be found or the widths are not positive.
    """
    V, F = region_mesh(vertices, faces)
    nv = len(V)
    loop = inner_lip_loop(V, F, loop, **find)
    W = loop_width(V, loop)
    lw = DEFAULT_LIP_WIDTH * W if lip_width is None else _width(lip_width, "lip")
    mw = DEFAULT_MOUTH_WIDTH * W if mouth_width is None else _width(mouth_width, "mouth")
    if not (lw > 0 and mw > 0 and np.isfinite(lw) and np.isfinite(mw)):
        raise RegionError(
            f"Region widths must be positive scene distances, got lip {lw} and mouth {mw}; fix the widths."
        )
    lw = max(lw, float(min_rings) * _loop_edge_length(V, F, loop))
    d = geodesic_distance(V, F, loop, limit=lw + mw)
    lip = d <= lw
    band = (d > lw) & np.isfinite(d)
    # keep the band on the face side: the largest piece once the lips are cut out
    A = vertex_adjacency(F, nv)
    keep = sp.diags((~lip).astype(np.float64))
    _, lab = _cc(keep @ A @ keep, directed=False)
    used = np.zeros(nv, dtype=bool)
    used[F.ravel()] = True
    counts = np.bincount(lab[used & ~lip], minlength=lab.max() + 1)
    face_side = lab == int(np.argmax(counts))
    mouth = band & face_side
    # share the border ring: lip vertices next to the mouth band
    shared = lip & (A @ mouth.astype(np.float64) > 0)
    mouth |= shared
    # a lip triangle with all three vertices shared would be in both regions
    for _ in range(10):
        both = lip[F].all(axis=1) & mouth[F].all(axis=1)
        if not both.any():
            break
        Fb = F[both]
        far = Fb[np.arange(len(Fb)), np.argmin(d[Fb], axis=1)]  # the vertex closest to the loop
        mouth[far] = False
    if not mouth.any() or not lip.any():
        raise RegionError(
            f"Auto Regions produced an empty {'mouth' if not mouth.any() else 'lip'} region (lip width {lw:.4g}, "
            f"mouth width {mw:.4g} scene units); increase the widths."
        )
    if return_distance:
        return mouth, lip, d, loop
    return mouth, lip


def _loop_edge_length(V, F, loop) -> float:
    """Edge length at the ``loop`` (scene units): the median length of the mesh edges with an end on it.

    Each loop vertex's edges count in proportion to the length of loop it stands for (half of its two loop
    edges), so a cluster of tiny edges where the loop turns round a mouth corner does not make a coarse mesh
    look fine.
    """
    loop = np.asarray(loop, dtype=np.int64)
    E = np.unique(np.sort(np.r_[F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1), axis=0)
    seg = np.linalg.norm(V[loop] - V[np.roll(loop, 1)], axis=1)
    w = np.zeros(len(V))
    w[loop] = 0.5 * (seg + np.roll(seg, -1))  # vertex k stands for half of edges (k-1, k) and (k, k+1)
    E = E[w[E].max(axis=1) > 0]
    if len(E) == 0:
        return 0.0
    L = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    o = np.argsort(L)
    c = np.cumsum(w[E].sum(axis=1)[o])
    return float(L[o][min(np.searchsorted(c, 0.5 * c[-1]), len(o) - 1)])


def _width(w, what):
    """A band width as a float (RegionError if it is not a number)."""
    try:
        return float(w)
    except (TypeError, ValueError):
        raise RegionError(f"The {what} width must be a distance in scene units, got {w!r}; fix the width.") from None


def inner_lip_vertices(vertices, faces, loop=None, lip_width=None) -> np.ndarray:
    """(V,) bool mask of the inner-lip region (the ``lip_mask`` of :func:`auto_regions`).

    Parameters
    ----------
    vertices : (V,3) array_like
        Rest-pose positions, scene units.
    faces : (F,3) int array_like
        Triangles.
    loop : (L,) int array_like, optional
        Inner-lip loop; found automatically when omitted.
    lip_width : float, optional
        Band half-width, scene units (default ``DEFAULT_LIP_WIDTH`` times the
        mouth width).

    Returns
    -------
    (V,) bool ndarray
    """
    V, F = region_mesh(vertices, faces)
    loop = inner_lip_loop(V, F, loop)
    lw = DEFAULT_LIP_WIDTH * loop_width(V, loop) if lip_width is None else _width(lip_width, "lip")
    if not (lw > 0 and np.isfinite(lw)):
        raise RegionError(f"The lip width must be a positive scene distance, got {lw}; fix the width.")
    return geodesic_distance(V, F, loop, limit=lw) <= lw
