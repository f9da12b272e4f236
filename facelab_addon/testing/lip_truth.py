"""The benchmark's ground-truth lip contact line, computed without the code it grades.

The artist-route benchmark (:mod:`facelab_addon.testing.route`) places its capture error around the line where
the lips meet and measures Refine on the skin near it. That line must not come from
:func:`facelab_addon.core.lips.lip_loop.inner_lip_loop` (Auto Regions' detector, the code under test): a truth
computed by the function it grades moves with it and hides its errors. This module finds the line from the face
model's own data with a different, simple rule (nothing here imports ``core.lips``):

* :func:`dense_truth_line` (a face model with a jaw-opening expression, e.g. ICT-FaceKit): the lips' contact is
  exactly where opening the jaw separates the surface. Pairs of skin vertices that are not mesh neighbours and
  whose distance grows under ``jawOpen`` by more than ``separation`` (15) times their rest distance are *contact
  pairs* (on ICT-FaceKit: the facing surfaces of the two lips, 0.1-3 mm apart at rest, pulled 1-2 cm apart; no
  other skin comes near that ratio once pairs within two mesh edges are left out). The ratio 15 keeps the mouth
  corners on the commissure: a lower ratio also counts the crease running on from it into the cheek (a few
  tenths of a millimetre wide) and moves the corners outward along it; a higher one up to 20 gives the same
  line. The vertex of a pair that the jaw moves more is on the lower lip. The mouth corners are the contact vertices farthest apart along the mouth's width (the
  principal axis of the contact vertices, across the jaw's motion). On each lip the line is the cheapest mesh
  path from corner to corner through that lip's contact vertices, an edge costing its length over the product of
  its ends' largest separation ratios: it follows the row where the lips are closest for how far they part.
* :func:`transferred_truth_line` (a :class:`~facelab_addon.testing.remeshed.RemeshedFace`, also with identity
  offsets added): the dense line of its source model carried through the remesh's known correspondence (each
  vertex's source triangle and barycentric weights, which place it on the source's rest surface and on one lip):
  the corners are the remeshed skin vertices nearest to the dense corners; on each lip the line is the mesh path
  between them over that lip's vertices that stays closest to the dense line (an edge costing its length times
  its ends' mean distance to the dense polyline). The correspondence does not depend on the actor, so the line's vertices are the same for every
  identity mix.
* :func:`truth_line` picks one of the two for a face.

Vertices at the same position (a mesh split along UV seams) are welded first; of coincident duplicates the line
always uses the lowest index (:func:`weld_map`). Positions are the face model's (any unit: every threshold is a
ratio or relative to the jaw's motion).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

__all__ = ["TruthLine", "truth_line", "dense_truth_line", "contact_pairs", "transferred_truth_line", "weld_map", "line_width",
           "lip_labels"]


@dataclass
class TruthLine:
    """A lip contact line: two mouth corners and a vertex chain over each lip between them.

    Attributes
    ----------
    corners : (2,) int
        The mouth corners' vertices, the first at the lower coordinate along the mouth's width axis.
    upper, lower : (U,) int, (L,) int
        Each lip's chain from ``corners[0]`` to ``corners[1]``, corners included.
    """

    corners: np.ndarray
    upper: np.ndarray
    lower: np.ndarray

    @property
    def loop(self) -> np.ndarray:
        """(N,) int: the closed loop, ordered: corner 0, the upper lip, corner 1, the lower lip back."""
        return np.r_[self.upper, self.lower[-2:0:-1]].astype(np.int64)


def weld_map(V) -> np.ndarray:
    """(V,) int: each vertex's representative, the lowest index among the vertices at exactly its position.

    Parameters
    ----------
    V : (V,3) float
        Positions (any unit).
    """
    V = np.ascontiguousarray(np.asarray(V, dtype=np.float64))
    _, inv = np.unique(V, axis=0, return_inverse=True)
    inv = inv.ravel()
    first = np.full(inv.max() + 1, len(V), dtype=np.int64)
    np.minimum.at(first, inv, np.arange(len(V)))
    return first[inv]


def _welded_edges(F, rep):
    """(E,2) unique edges of triangles ``F`` (F,3) between representatives ``rep`` (V,), degenerate ones dropped."""
    F = rep[np.asarray(F, dtype=np.int64)]
    E = np.sort(np.r_[F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1)
    E = E[E[:, 0] != E[:, 1]]
    return np.unique(E, axis=0)


def _graph(V, E, n, weight=None):
    """(n,n) symmetric CSR graph of edges ``E`` (E,2) weighted by ``weight`` (E,) (default: their lengths)."""
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) if weight is None else weight
    G = sp.coo_matrix((w, (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    return G + G.T


def contact_pairs(V, X, F, skin, separation: float = 15.0):
    """Pairs of skin vertices that an expression parts by more than ``separation`` times their rest distance.

    Parameters
    ----------
    V, X : (V,3) float
        Rest and expression positions (the same unit).
    F : (F,3) int
        Triangles.
    skin : (V,) bool
        The vertices that may be lips (e.g. ICT's ``M_Face``).
    separation : float
        The least ratio of the growth of a pair's distance to its rest distance.

    Returns
    -------
    pairs : (P,2) int
        Welded vertex ids (:func:`weld_map`), no pair within two mesh edges of each other, searched within a tenth of the expression's
        largest skin displacement.
    ratio : (P,) float
        ``|D_i - D_j| / |V_i - V_j|``, ``D = X - V``.
    """
    V, X = np.asarray(V, dtype=np.float64), np.asarray(X, dtype=np.float64)
    rep = weld_map(V)
    skin = np.asarray(skin, dtype=bool)
    keep = np.zeros(len(V), bool)
    keep[rep[skin]] = True
    keep &= rep == np.arange(len(V))
    D = X - V
    radius = 0.1 * float(np.linalg.norm(D[skin], axis=1).max())
    if radius <= 0:
        raise ValueError("the expression does not move the skin: it cannot show where the lips part")
    idx = np.flatnonzero(keep)
    pr = cKDTree(V[idx]).query_pairs(radius, output_type="ndarray")
    i, j = idx[pr[:, 0]], idx[pr[:, 1]]
    ratio = np.linalg.norm(D[i] - D[j], axis=1) / np.linalg.norm(V[i] - V[j], axis=1)
    ok = ratio > separation
    i, j, ratio = i[ok], j[ok], ratio[ok]
    # not across an edge or around one vertex (at the corner, the fan of tiny triangles where the lips join):
    # no pair within two edges of each other on the (welded) mesh
    E = _welded_edges(F, rep)
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(len(V),) * 2).tocsr()
    A = A + A.T
    A2 = (A + A @ A).tocsr()
    ok = np.asarray(A2[i, j]).ravel() == 0
    return np.c_[i, j][ok], ratio[ok]


def dense_truth_line(V, X, F, skin, separation: float = 15.0) -> TruthLine:
    """The lip contact line of a face from a jaw-opening expression (the module docstring's first rule).

    Parameters
    ----------
    V : (V,3) float
        Rest positions (any unit).
    X : (V,3) float
        The face with its jaw open (e.g. ICT's ``jawOpen``).
    F : (F,3) int
        Triangles.
    skin : (V,) bool
        The skin (the lips are on it).
    separation : float
        See :func:`contact_pairs`.

    Returns
    -------
    TruthLine
        Welded vertex ids (the lowest of coincident duplicates).

    Raises
    ------
    ValueError
        If no contact is found or a lip's contact does not join its corners.
    """
    V, X = np.asarray(V, dtype=np.float64), np.asarray(X, dtype=np.float64)
    pairs, ratio = contact_pairs(V, X, F, skin, separation)
    if len(pairs) < 4:
        raise ValueError(f"no lip contact: {len(pairs)} vertex pairs part by {separation}x their distance")
    n = len(V)
    D = X - V
    score = np.zeros(n)
    np.maximum.at(score, pairs[:, 0], ratio)
    np.maximum.at(score, pairs[:, 1], ratio)
    contact = np.flatnonzero(score > 0)
    # the jaw's direction of motion; the lower lip is the member of a pair it moves more along it
    u = D[contact].mean(axis=0)
    u /= np.linalg.norm(u)
    a, b = pairs[:, 0], pairs[:, 1]
    a_low = D[a] @ u > D[b] @ u
    low_vote = np.zeros(n)
    np.add.at(low_vote, np.where(a_low, a, b), ratio)
    np.add.at(low_vote, np.where(a_low, b, a), -ratio)
    # the corners: the contact's extremes along the mouth's width (its principal axis across the jaw's motion)
    P = V[contact] - V[contact].mean(axis=0)
    P -= np.outer(P @ u, u)
    width = np.linalg.svd(P, full_matrices=False)[2][0]
    s = P @ width
    corners = contact[[np.argmin(s), np.argmax(s)]]
    rep = weld_map(V)
    E = _welded_edges(F, rep)
    # an edge costs its length over the product of its ends' ratios; skin off the contact counts as ratio 1 (a
    # lip's contact may stop an edge short of the corner, which the other lip's contact holds)
    score = np.where(score > 0, score, 1.0)
    cost = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) / (score[E[:, 0]] * score[E[:, 1]])
    skin_w = np.zeros(n, bool)
    skin_w[rep[np.asarray(skin, dtype=bool)]] = True
    chains = []
    for lower in (False, True):
        on = skin_w.copy()
        on[contact[(low_vote[contact] > 0) != lower]] = False  # never over the other lip
        on[corners] = True
        sel = on[E].all(axis=1)
        G = _graph(V, E[sel], n, cost[sel])
        dist, pred = dijkstra(G, directed=False, indices=int(corners[0]), return_predecessors=True)
        if not np.isfinite(dist[corners[1]]):
            raise ValueError(f"the {'lower' if lower else 'upper'} lip's contact does not join the mouth corners")
        path = [int(corners[1])]
        while path[-1] != corners[0]:
            path.append(int(pred[path[-1]]))
        chains.append(np.asarray(path[::-1], dtype=np.int64))
    return TruthLine(corners=corners.astype(np.int64), upper=chains[0], lower=chains[1])


def lip_labels(V, F, line: TruthLine) -> np.ndarray:
    """(V,) +1 for vertices nearer (along the mesh) to the upper chain, -1 to the lower, 0 at the corners or cut off.

    Parameters
    ----------
    V : (V,3) float
    F : (F,3) int
    line : TruthLine
        On this mesh (welded ids). Coincident duplicates take their representative's label.
    """
    V = np.asarray(V, dtype=np.float64)
    rep = weld_map(V)
    G = _graph(V, _welded_edges(F, rep), len(V))
    up, lo = line.upper[1:-1], line.lower[1:-1]
    _, _, src = dijkstra(G, directed=False, indices=np.r_[up, lo], min_only=True, return_predecessors=True)
    lab = np.where(src < 0, 0.0, np.where(np.isin(src, up), 1.0, -1.0))[rep]
    lab[np.isin(rep, line.corners)] = 0.0
    return lab


def transferred_truth_line(face, source_line: TruthLine | None = None) -> TruthLine:
    """The dense source model's truth line carried to a remeshed face (the module docstring's second rule).

    Parameters
    ----------
    face : RemeshedFace
        With ``source`` (the dense model it samples), ``source_vertices`` (V,3) and ``barycentric`` (V,3).
    source_line : TruthLine, optional
        The dense line (default :func:`truth_line` of ``face.source``).

    Returns
    -------
    TruthLine
        Vertex ids of ``face`` (the lowest of coincident duplicates).
    """
    src = face.source
    Vs = np.asarray(src.neutral, dtype=np.float64)
    dense = truth_line(src) if source_line is None else source_line
    # the remeshed vertices where the source's rest surface has them: the same for any actor
    Q = np.einsum("vkc,vk->vc", Vs[np.asarray(face.source_vertices)], np.asarray(face.barycentric))
    rep = weld_map(np.asarray(face.neutral, dtype=np.float64))
    skin = np.asarray(face.part_vertex_mask("M_Face")) & (rep == np.arange(len(rep)))
    lab = lip_labels(Vs, src.faces, dense)
    side = np.einsum("vk,vk->v", lab[np.asarray(face.source_vertices)], np.asarray(face.barycentric))
    ids = np.flatnonzero(skin)
    corners = ids[cKDTree(Q[ids]).query(Vs[dense.corners])[1]]
    E = _welded_edges(face.faces, rep)
    length = np.linalg.norm(Q[E[:, 0]] - Q[E[:, 1]], axis=1)
    tiny = 1e-3 * float(np.median(length))
    chains = []
    for chain, sgn in ((dense.upper, 1.0), (dense.lower, -1.0)):
        # each vertex's distance to the dense chain's polyline (sampled at a tenth of its segments)
        t = np.linspace(0.0, 1.0, 10, endpoint=False)
        P = (Vs[chain[:-1], None] * (1 - t)[:, None] + Vs[chain[1:], None] * t[:, None]).reshape(-1, 3)
        d = cKDTree(np.r_[P, Vs[chain[-1:]]]).query(Q)[0]
        on = skin & (side * sgn >= 0)  # never over the other lip
        on[corners] = True
        sel = on[E].all(axis=1)
        cost = length * (0.5 * (d[E[:, 0]] + d[E[:, 1]]) + tiny)
        G = _graph(Q, E[sel], len(Q), cost[sel])
        dist, pred = dijkstra(G, directed=False, indices=int(corners[0]), return_predecessors=True)
        if not np.isfinite(dist[corners[1]]):
            raise ValueError("the remeshed face's lip does not join its mouth corners")
        path = [int(corners[1])]
        while path[-1] != corners[0]:
            path.append(int(pred[path[-1]]))
        chains.append(np.asarray(path[::-1], dtype=np.int64))
    return TruthLine(corners=corners.astype(np.int64), upper=chains[0], lower=chains[1])


def truth_line(face, expression: str = "jawOpen", skin: str = "M_Face") -> TruthLine:
    """The truth lip contact line of a face model.

    Parameters
    ----------
    face : ICTModel, RemeshedFace or alike
        A face with a ``truth`` (a :class:`TruthLine`: ``testing.makehuman.TransferredHead``) gets it; a face
        with a ``source`` model and ``source_vertices`` / ``barycentric`` (a remesh) gets its source's
        line transferred (:func:`transferred_truth_line`); a face split along seams (a ``base`` model and the
        ``source`` vertex of each split vertex: ``testing.split_seams.SplitFace``) gets its base's line at the
        first copy of each vertex; any other needs ``neutral``, ``faces``,
        ``expressions[expression]`` and ``part_vertex_mask(skin)`` (:func:`dense_truth_line`).
    expression : str
        The jaw-opening expression.
    skin : str
        The part the lips are on.

    Returns
    -------
    TruthLine
    """
    if isinstance(getattr(face, "truth", None), TruthLine):  # a face that carries its own (testing.makehuman)
        return face.truth
    if getattr(face, "source", None) is not None and hasattr(face, "barycentric"):
        return transferred_truth_line(face)
    if getattr(face, "base", None) is not None and getattr(face, "source", None) is not None:
        # a face split along seams (testing.split_seams.SplitFace): its source's line, at the first copy of each
        # vertex, so the split face's truth is the welded face's
        src = np.asarray(face.source)
        line = truth_line(face.base, expression, skin)
        first = np.full(int(src.max()) + 1, len(src), dtype=np.int64)
        np.minimum.at(first, src, np.arange(len(src), dtype=np.int64))
        return TruthLine(first[line.corners], first[line.upper], first[line.lower])
    if expression not in face.expressions:
        raise ValueError(f"the face has no {expression!r} expression to find its lips by; remesh a face that has one")
    return dense_truth_line(face.neutral, face.expressions[expression], face.faces, face.part_vertex_mask(skin))


def line_width(V, line: TruthLine) -> float:
    """The mouth width of a line: the distance between its corners, in the unit of ``V`` (V,3)."""
    V = np.asarray(V, dtype=np.float64)
    return float(np.linalg.norm(V[line.corners[1]] - V[line.corners[0]]))
