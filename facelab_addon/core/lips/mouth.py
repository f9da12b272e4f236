"""Find the mouth of a face mesh: the loop where the lips meet the mouth interior.

:func:`find_mouth` returns a :class:`Mouth`: the *mouth loop* (the border
between the free lip surface and the fixed mouth interior), the two mouth
corners, and for every free vertex near the loop its geodesic distance to the
loop, its nearest loop vertex (its *column*), its lip side (+1 upper, -1
lower) and the *lip tip* of its column (the vertex furthest into the mouth
opening). The tips form the line where the lips touch when the mouth is
closed, the inner-lip silhouette seen from the front (Dinev et al. 2018, §5).

* The loop is detected as the lowest closed border of the free triangles
  (not the largest one, which is the face's outer border), or taken from
  ``loop`` / ``near``.
* The corners are the loop vertices with the smallest and largest coordinate
  along ``lateral = up x forward`` (image left and right in a frontal view).
* Vertices within ``band_mm`` (geodesic, along edges of free triangles) of
  the loop get a column; the side of a loop vertex is +1 above the
  corner-to-corner line along ``up``, -1 below.

Conventions: vertices (V,3) float64 in scene units; ``units_per_mm`` scene
units per millimetre (0.1 for centimetres, 0.001 for metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from ..errors import FaceLabError
from ..geometry.axes import Y_UP, Z_FORWARD, unit_axis
from ..geometry.mesh import edge_faces, edge_length_graph, validate_mesh

__all__ = ["Mouth", "find_mouth"]


@dataclass
class Mouth:
    """Mouth structure of one mesh (see the module docstring).

    Attributes
    ----------
    loop : (K,) int64
        Mouth-loop vertex ids (border of the free lip surface at the mouth bag).
    corners : (2,) int64
        Loop vertices at the left and right mouth corner (smallest, largest
        ``lateral`` coordinate).
    center : (3,) float64
        Mean of the loop vertices, scene units.
    up, forward, lateral : (3,) float64
        Unit axes: face up, the direction the face looks, ``up x forward``.
    loop_distance : (V,) float64
        Geodesic distance (along edges of free triangles) to the loop, scene
        units; ``inf`` beyond ``band_mm`` or on fixed vertices.
    column : (V,) int64
        Nearest loop vertex id, ``-1`` where ``loop_distance`` is ``inf``.
    side : (V,) int8
        +1 upper lip, -1 lower lip, 0 outside the band.
    tip : (T,) int64
        Lip-tip vertex of every column (one per loop vertex that has a column).
    tip_depth : (V,) float64
        ``loop_distance`` of the tip of each vertex's column, scene units
        (``nan`` outside the band).
    lateral_t : (V,) float64
        Lateral position normalised so the corners are at -1 and +1.
    corner_lateral : (2,) float64
        Lateral coordinates (relative to ``center``) of the two corners,
        scene units.
    free_faces : (F,) bool
        Triangles with no fixed vertex.
    units_per_mm : float
        Scene units per millimetre.
    """

    loop: np.ndarray
    corners: np.ndarray
    center: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    lateral: np.ndarray
    loop_distance: np.ndarray
    column: np.ndarray
    side: np.ndarray
    tip: np.ndarray
    tip_depth: np.ndarray
    lateral_t: np.ndarray
    corner_lateral: np.ndarray
    free_faces: np.ndarray
    units_per_mm: float

    @property
    def width(self) -> float:
        """Corner-to-corner distance along ``lateral``, scene units."""
        return float(self.corner_lateral[1] - self.corner_lateral[0])

    def lateral_position(self, vertices) -> np.ndarray:
        """(V,) normalised lateral position of ``vertices`` (-1, +1 at the corners)."""
        lat = (np.asarray(vertices, dtype=np.float64) - self.center) @ self.lateral
        cl, cr = self.corner_lateral
        return (lat - 0.5 * (cl + cr)) / (0.5 * (cr - cl))


def _border_loops(F, n):
    """Connected components of the border edges of triangles ``F``: list of vertex-id arrays."""
    edges, ef = edge_faces(F)
    b = edges[(ef < 0).any(axis=1)]
    if len(b) == 0:
        return []
    A = sp.coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(n, n))
    _, lab = connected_components(A, directed=False)
    verts = np.unique(b)
    return [verts[lab[verts] == k] for k in np.unique(lab[verts])]


def find_mouth(
    vertices,
    faces,
    fixed=None,
    *,
    loop=None,
    near=None,
    up=Y_UP,
    forward=Z_FORWARD,
    band_mm: float = 25.0,
    units_per_mm: float = 0.1,
) -> Mouth:
    """Find the mouth loop, corners, lip columns, sides and lip tips.

    Parameters
    ----------
    vertices : (V,3) float
        Face mesh, scene units (any pose; the structure is topological except
        the tips and corners, which follow this pose).
    faces : (F,3) int
        Triangles.
    fixed : (V,) bool, optional
        Hidden vertices (mouth bag, teeth, gums, eyes, back of head). Free
        triangles are those with no fixed vertex. Required unless ``loop`` or
        ``near`` is given (a mesh whose mouth is a hole, without a mouth bag,
        may pass ``near`` and no ``fixed``).
    loop : (K,) int, optional
        Mouth-loop vertex ids (for ICT-FaceKit: ``ICT_MOUTH_LOOP``). Default:
        detected as the border loop of the free triangles nearest to ``near``,
        or, without ``near``, the lowest (along ``up``) border loop other than
        the largest one.
    near : (3,) float, optional
        A point near the mouth, scene units (for the loop detection).
    up, forward : (3,) float
        Face up axis and viewing direction of the face (ICT: +Y, +Z).
    band_mm : float
        Geodesic reach from the loop of the lip columns, millimetres.
    units_per_mm : float
        Scene units per millimetre (0.1 for centimetres).

    Returns
    -------
    Mouth

    Raises
    ------
    FaceLabError
        When no mouth loop can be found.
    """
    V, F = validate_mesh(vertices, faces)
    n = len(V)
    up = unit_axis(up, "up")
    forward = unit_axis(forward, "forward")
    lateral = unit_axis(np.cross(up, forward))
    up = unit_axis(np.cross(forward, lateral))  # orthogonalise
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, dtype=bool)
    if fixed.shape != (n,):
        raise FaceLabError(f"'fixed' must be a mask of {n} vertices, got {fixed.shape}.")
    free_faces = ~fixed[F].any(axis=1)
    Ff = F[free_faces]
    if loop is None and near is None and not fixed.any():
        raise FaceLabError(
            "Cannot tell the mouth from other openings: pass 'fixed' (mouth bag, teeth, gums, eyes: the hidden "
            "parts), the mouth loop vertex ids, or a point 'near' the mouth."
        )
    if loop is None:
        loops = [lp for lp in _border_loops(Ff, n) if len(lp) >= 8]
        if not loops:
            raise FaceLabError(
                "No mouth opening found: pass 'fixed' (the mouth bag, teeth and other hidden parts) or the mouth "
                "loop vertex ids."
            )
        if near is not None:
            p = np.asarray(near, dtype=np.float64).reshape(3)
            loop = min(loops, key=lambda lp: np.linalg.norm(V[lp].mean(0) - p))
        else:
            if len(loops) > 1:
                ext = [np.ptp(V[lp], axis=0).sum() for lp in loops]
                loops.pop(int(np.argmax(ext)))  # the outer border of the face
            loop = min(loops, key=lambda lp: float(V[lp].mean(0) @ up))
    loop = np.unique(np.asarray(loop, dtype=np.int64))
    if len(loop) < 4 or loop.min() < 0 or loop.max() >= n:
        raise FaceLabError("The mouth loop must have at least 4 valid vertex ids.")
    center = V[loop].mean(axis=0)
    lat = (V - center) @ lateral
    h = (V - center) @ up
    corners = np.array([loop[np.argmin(lat[loop])], loop[np.argmax(lat[loop])]])
    cl, cr = lat[corners]
    if cr - cl < 1e-9:
        raise FaceLabError("The mouth loop has no width along the lateral axis; check 'up' and 'forward'.")
    # side of each loop vertex: above / below the corner-to-corner line
    slope = (h[corners[1]] - h[corners[0]]) / (cr - cl)
    line_h = h[corners[0]] + slope * (lat - cl)
    loop_side = np.where(h[loop] >= line_h[loop], 1, -1).astype(np.int8)
    loop_side[np.isin(loop, corners)] = 1  # arbitrary; weights vanish at the corners

    G = edge_length_graph(V, Ff, min_length=1e-12)[0]
    limit = band_mm * units_per_mm
    dist, _, src = dijkstra(G, directed=False, indices=loop, return_predecessors=True, min_only=True, limit=limit)
    reach = np.isfinite(dist) & ~fixed
    dist = np.where(reach, dist, np.inf)
    column = np.where(reach, src, -1).astype(np.int64)
    side_of = np.zeros(n, np.int8)
    side_of[loop] = loop_side
    side = np.where(reach, side_of[np.maximum(column, 0)], 0).astype(np.int8)

    # tip of each column: the vertex furthest into the mouth opening
    idx = np.flatnonzero(reach)
    key = side[idx] * h[idx]  # upper: lowest h, lower: highest h
    order = np.lexsort((key, column[idx]))
    first = np.r_[True, column[idx][order][1:] != column[idx][order][:-1]]
    tip = idx[order][first]
    tip_of = -np.ones(n, np.int64)
    tip_of[column[tip]] = tip
    tip_depth = np.full(n, np.nan)
    tip_depth[idx] = dist[tip_of[column[idx]]]

    return Mouth(
        loop=loop,
        corners=corners,
        center=center,
        up=up,
        forward=forward,
        lateral=lateral,
        loop_distance=dist,
        column=column,
        side=side,
        tip=tip,
        tip_depth=tip_depth,
        lateral_t=(lat - 0.5 * (cl + cr)) / (0.5 * (cr - cl)),
        corner_lateral=np.array([cl, cr]),
        free_faces=free_faces,
        units_per_mm=float(units_per_mm),
    )
