"""Welding a mesh split along its UV seams: coincident vertices that always move together become one.

Exporters and importers (Blender's glTF importer with its default *Merge Vertices* off, most game and
engine formats) split a mesh's vertices along UV seams and sharp edges: each seam vertex becomes two or
more coincident vertices and the surface falls into pieces. A Laplacian, a geodesic band or a deformation
gradient stops at such a seam, and a correction that moves one side of it and not its twin tears the
mesh open. :func:`weld` finds the coincident vertices and returns the faces re-indexed to one
representative per set, so the solvers see one surface; every per-vertex array computed on it is given
back to the duplicates with :meth:`Weld.spread`.

Only vertices that coincide in the rest pose **and** in every other pose given (shape keys, the frames a
step reads) are welded: a mouth modelled closed with its upper and lower lip vertices coincident at rest
(a lip cut) parts when the mouth opens, and welding it would glue the lips.

The tolerance is relative to the mesh (:func:`weld_tolerance`): ``rel_tol`` times the median edge length,
by default 1e-4. Split duplicates are copies of one position, so they coincide exactly; the tolerance only
absorbs float32 round-off (Blender stores positions in float32: 2^-24 ~ 6e-8 of a coordinate, i.e. below
1e-4 edge lengths for a vertex up to ~1,500 median edge lengths from the object's origin: a whole body
whose face has 2 mm edges) and stays far below anything modelled (1e-4 of a 2 mm edge is 0.2 um; Blender's
Merge by Distance defaults to 0.1 mm). Being relative, it is the same at any unit and object scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import connected_components

__all__ = ["Weld", "weld", "weld_tolerance", "DEFAULT_REL_TOL"]

#: Default tolerance of :func:`weld`, in median edge lengths (see the module docstring).
DEFAULT_REL_TOL = 1e-4


@dataclass(frozen=True)
class Weld:
    """Coincident vertices of a mesh and its faces re-indexed to one vertex per set.

    Attributes
    ----------
    representative : (V,) int64
        Each vertex's representative: the smallest index of its coincident set
        (``representative[i] == i`` for a representative and for every vertex without a twin).
    faces : (F,3) int64
        The input faces with every corner replaced by its representative (same order and count);
        the duplicates are used by no face. The input array itself when nothing was welded.
    """

    representative: np.ndarray
    faces: np.ndarray

    @property
    def n_duplicates(self) -> int:
        """Vertices welded onto another one (0: nothing welded)."""
        return int(np.count_nonzero(self.representative != np.arange(len(self.representative))))

    @property
    def duplicates(self) -> np.ndarray:
        """(D,) int64 ids of the vertices welded onto another one."""
        return np.flatnonzero(self.representative != np.arange(len(self.representative)))

    def spread(self, values):
        """``values`` (V, ...) with every duplicate given its representative's value.

        Masks, positions, offsets computed on the welded surface (where the duplicates take no part) are
        made whole. Returns ``values`` itself (not a copy) when nothing was welded.
        """
        if self.n_duplicates == 0:
            return values
        return np.asarray(values)[self.representative]

    @property
    def kept(self) -> np.ndarray:
        """(K,) int64 the representatives, ascending: the vertices of the welded mesh (:meth:`compact`)."""
        return np.flatnonzero(self.representative == np.arange(len(self.representative)))

    def compact(self, vertices):
        """The welded mesh without its duplicates: ``(vertices[kept], faces renumbered to kept)``.

        Parameters
        ----------
        vertices : (V, ...) array_like
            Positions (or any per-vertex values) of the input mesh.

        Returns
        -------
        vertices_kept : (K, ...) ndarray
        faces : (F,3) int64
            Indices into ``vertices_kept``.
        """
        keep = self.kept
        at = np.full(len(self.representative), -1, np.int64)
        at[keep] = np.arange(len(keep))
        return np.asarray(vertices)[keep], at[self.faces]

    def uncompact(self, values):
        """(K, ...) ``values`` of the compact mesh (:meth:`compact`) -> (V, ...): each vertex its representative's."""
        at = np.cumsum(self.representative == np.arange(len(self.representative))) - 1
        return np.asarray(values)[at[self.representative]]

    def expand(self, vertices) -> tuple:
        """The vertices ``vertices`` (k,) (representatives) together with their duplicates.

        Returns
        -------
        vertices_all : (k',) int64
            ``vertices`` and every vertex whose representative is among them, sorted; ``vertices``
            itself when nothing was welded.
        take : (k',) int64 or None
            Positions into ``vertices``: a value per vertex of ``vertices`` (``a``, (k, ...)) becomes one
            per vertex of ``vertices_all`` as ``a[take]``; None when nothing was welded (``a`` as it is).
        """
        vertices = np.asarray(vertices, dtype=np.int64)
        if self.n_duplicates == 0:
            return vertices, None
        at = np.full(len(self.representative), -1, np.int64)
        at[vertices] = np.arange(len(vertices))
        pos = at[self.representative]
        vertices_all = np.flatnonzero(pos >= 0)
        return vertices_all, pos[vertices_all]


def weld_tolerance(rest, faces, rel_tol: float = DEFAULT_REL_TOL) -> float:
    """``rel_tol`` times the median length of the mesh's edges (zero-length edges left out), scene units.

    Parameters
    ----------
    rest : (V,3) float
    faces : (F,3) int
    rel_tol : float

    Returns
    -------
    float
        0.0 for a mesh without edges of positive length.
    """
    V = np.asarray(rest, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if len(F) == 0:
        return 0.0
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    L = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    L = L[L > 0]
    return float(rel_tol * np.median(L)) if len(L) else 0.0


def weld(faces, rest, poses=(), *, rel_tol: float = DEFAULT_REL_TOL, tol: float | None = None) -> Weld:
    """Weld the vertices that coincide in the rest pose and in every pose of ``poses`` where they close a seam.

    Two coincident vertices are welded when (1) they are within the tolerance of each other in the rest
    pose and in every pose of ``poses``, and (2) they lie on one connected piece of the mesh, or on two
    pieces the welding sews together: pieces that come to share at least one edge, every edge they share
    having then exactly two triangles, one of each piece, traversing it in opposite directions (one
    consistently oriented surface, as on both sides of a UV seam; pieces are joined transitively). A separate
    part that merely touches the surface (eyelashes or an eye-occlusion shell glued to the lid's rim, which
    would make edges of three or four triangles; a part touching at isolated vertices) is not welded.

    Parameters
    ----------
    faces : (F,3) int array_like
        The mesh's triangles.
    rest : (V,3) float array_like
        Rest positions, scene units.
    poses : iterable of (V,3) float array_like
        Other positions of the same vertices (shape-key positions, evaluated frames), scene units. Read
        lazily and only when the rest pose has coincident vertices that close a seam, so a generator of
        expensive frames costs nothing on a mesh without them (ICT-FaceKit: its glued parts are rejected at
        rest).
    rel_tol : float
        Tolerance in median edge lengths (:func:`weld_tolerance`); ignored when ``tol`` is given.
    tol : float, optional
        Absolute tolerance, scene units.

    Returns
    -------
    Weld
        With ``representative`` the identity and ``faces`` the input array when nothing is welded.
    """
    from scipy.spatial import cKDTree

    F = np.asarray(faces, dtype=np.int64)
    V = np.asarray(rest, dtype=np.float64)
    n = len(V)
    ident = Weld(representative=np.arange(n, dtype=np.int64), faces=F)
    tol = weld_tolerance(V, F, rel_tol) if tol is None else float(tol)
    if n < 2 or tol <= 0 or len(F) == 0:
        return ident
    pairs = cKDTree(V).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return ident
    piece = connected_components(F, n)

    def sewn(pairs):  # the pairs on one piece or on pieces the welding sews together
        joined = _sewn_pieces(F, piece, _representatives(pairs, n), pairs)
        return pairs[joined[piece[pairs[:, 0]]] == joined[piece[pairs[:, 1]]]]

    pairs = sewn(pairs)  # first at rest: parts merely touching are never read in the poses
    if len(pairs) == 0:
        return ident
    for P in poses:  # a pair stays only while it coincides in every pose
        P = np.asarray(P, dtype=np.float64)
        if P.shape != V.shape:
            raise ValueError(f"a pose has shape {P.shape}, the rest pose {V.shape}")
        pairs = pairs[np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1) <= tol]
        if len(pairs) == 0:
            return ident
    pairs = sewn(pairs)  # again with the twins the poses left
    if len(pairs) == 0:
        return ident
    rep = _representatives(pairs, n)
    return Weld(representative=rep, faces=rep[F])


def _representatives(pairs, n) -> np.ndarray:
    """(n,) the smallest vertex of each set of vertices linked by ``pairs`` (k,2)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as cc

    G = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = cc(G, directed=False)
    first = np.full(lab.max() + 1, n, np.int64)
    np.minimum.at(first, lab, np.arange(n, dtype=np.int64))
    return first[lab]


def _sewn_pieces(F, piece, rep, pairs) -> np.ndarray:
    """(P,) label per mesh piece: pieces the tentative weld ``rep`` sews together share a label.

    Two pieces are sewn when, with ``rep`` applied, they share at least one edge and every edge they share has
    exactly two triangles, one of each, traversing it in opposite directions (see :func:`weld`).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as cc

    n_pieces = int(piece.max()) + 1
    welded = np.zeros(len(rep), bool)
    welded[rep[pairs.ravel()]] = True
    W = rep[F]
    half = np.concatenate([W[:, [0, 1]], W[:, [1, 2]], W[:, [2, 0]]])  # directed edges of the welded triangles
    owner = np.tile(piece[F[:, 0]], 3)
    on = welded[half].all(axis=1)  # only edges between welded vertices can join two pieces
    half, owner = half[on], owner[on]
    if len(half) == 0:
        return np.arange(n_pieces)
    _, edge = np.unique(np.sort(half, axis=1), axis=0, return_inverse=True)
    edge = edge.ravel()
    n_faces = np.bincount(edge)
    forward = np.bincount(edge, weights=half[:, 0] < half[:, 1])
    ep = np.unique(np.c_[edge, owner], axis=0)  # (edge, piece) incidences
    n_owners = np.bincount(ep[:, 0], minlength=len(n_faces))
    shared = n_owners[ep[:, 0]] >= 2
    ep = ep[shared]
    good_edge = (n_faces == 2) & (n_owners == 2) & (forward == 1)
    # every pair of pieces on a shared edge, with whether that edge sews them
    first = np.r_[0, np.flatnonzero(np.diff(ep[:, 0])) + 1]
    bounds = np.r_[first, len(ep)]
    pa, pb, ok = [], [], []
    for s, e in zip(bounds[:-1], bounds[1:]):
        owners = ep[s:e, 1]
        for i in range(len(owners)):
            for j in range(i + 1, len(owners)):
                pa.append(owners[i])
                pb.append(owners[j])
                ok.append(good_edge[ep[s, 0]])
    if not pa:
        return np.arange(n_pieces)
    pp = np.c_[pa, pb].astype(np.int64)
    ok = np.asarray(ok, bool)
    key = pp[:, 0] * n_pieces + pp[:, 1]
    bad = np.unique(key[~ok])
    sew = np.unique(key[ok & ~np.isin(key, bad)])
    G = coo_matrix((np.ones(len(sew)), (sew // n_pieces, sew % n_pieces)), shape=(n_pieces, n_pieces))
    return cc(G, directed=False)[1]
