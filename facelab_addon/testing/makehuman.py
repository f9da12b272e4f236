"""A head that is not ICT-FaceKit: MakeHuman's base mesh, with ICT's mouth expressions by deformation transfer.

MakeHuman's base mesh (``makehuman/data/3dobjs/base.obj`` of github.com/makehumancommunity/makehuman, released
as CC0 in September 2020: see the file's header and the repository's ``LICENSE.ASSETS.md``) is a whole body in
decimetres, Y up, Z forward, all quads, with helper geometry (tights, skirt, hair, eyes, teeth, tongue, lashes,
joint cubes) as OBJ groups. :func:`makehuman_head` keeps the ``body`` group's polygons whose vertices are all
above a neck plane (:data:`NECK_BELOW_NOSE_CM` below the nose tip), drops every helper, and turns it into
centimetres. Its mouth is open by a millimetre or two into a mouth bag (no teeth): the inner-lip loop exists.

The head has no expressions of its own, so ICT-FaceKit's mouth expressions (:data:`EXPRESSIONS`) are carried
over by deformation transfer (:class:`facelab_addon.core.solve.deformation_transfer.DeformationTransfer`, the
triangle correspondence from :func:`~facelab_addon.core.solve.deformation_transfer.triangle_correspondence_from_markers`),
with markers found on both meshes by the same geometric rules (:func:`face_markers`: nose tip, nasion, the inner
lips' midpoints, the mouth corners, the chin); no vertex id of either mesh is used. The transferred shapes are the
truth of a performance on this head; its lip contact line (``truth``, which
:func:`facelab_addon.testing.lip_truth.truth_line` returns) comes from its own ``jawOpen`` by
:func:`jaw_split_truth_line`.

The mesh is not in the repository. :func:`makehuman_obj_path` reads it from the ``FACELAB_MAKEHUMAN_OBJ``
environment variable (:data:`HOW_TO` says how to get it); tests and benchmarks skip without it. The result quacks
like :class:`facelab_addon.core.capture.ict.ICTModel` where the scene builders read it (``neutral``, ``faces``,
``poly_verts``, ``poly_offsets``, ``expressions``, ``expression_names``, ``parts``, ``part_vertex_mask``,
``pose``, ``scale``). Positions are centimetres, Y up, Z forward (ICT's axes). Arrays are cached under
``FACELAB_CACHE_DIR`` (default ``~/.cache/facelab``).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from .remeshed import RemeshedFace

__all__ = ["ENV", "HOW_TO", "EXPRESSIONS", "NECK_BELOW_NOSE_CM", "TransferredHead", "makehuman_obj_path",
           "read_obj_groups", "face_markers", "jaw_split_truth_line", "makehuman_head"]

#: The environment variable holding the path of MakeHuman's ``base.obj``.
ENV = "FACELAB_MAKEHUMAN_OBJ"
#: How to get the mesh (the skip message of tests and benchmarks).
HOW_TO = (f"set {ENV} to MakeHuman's base mesh (CC0): e.g. `git clone --depth 1 "
          "https://github.com/makehumancommunity/makehuman` and use makehuman/data/3dobjs/base.obj")
#: The ICT-FaceKit expressions transferred (the route's five cyclic channels first).
EXPRESSIONS = ("jawOpen", "mouthClose", "mouthFunnel", "mouthSmile_L", "mouthSmile_R", "mouthPucker",
               "mouthPress_L", "mouthPress_R")
#: The neck plane: polygons with a vertex lower than this many centimetres below the nose tip are cut off.
NECK_BELOW_NOSE_CM = 11.0
_DM_TO_CM = 10.0


@dataclass
class TransferredHead:
    """A head mesh with transferred expressions (see the module docstring). V vertices, P polygons, F triangles."""

    neutral: np.ndarray  # (V,3) cm
    poly_verts: np.ndarray  # (C,)
    poly_offsets: np.ndarray  # (P+1,)
    expressions: dict  # name -> (V,3) cm
    markers: dict  # name -> vertex id (face_markers)
    parts: list = field(default_factory=lambda: ["M_Face"])
    scale: float = 1.0
    faces: np.ndarray = field(default=None)  # (F,3) fan triangulation
    truth: object = field(default=None, repr=False)  # its lip contact line (TruthLine), see jaw_split_truth_line

    def __post_init__(self):
        if self.faces is None:
            self.faces = _fan(self.poly_verts, self.poly_offsets)

    expression_names = RemeshedFace.expression_names
    pose = RemeshedFace.pose  # neutral plus weighted expression offsets, (V,3) cm

    def part_vertex_mask(self, *names):
        """(V,) bool: every vertex for ``"M_Face"`` (the head is all skin), none for any other part."""
        return np.full(len(self.neutral), "M_Face" in names)


def makehuman_obj_path() -> Path | None:
    """The MakeHuman ``base.obj`` named by :data:`ENV`, or None when unset or missing."""
    p = os.environ.get(ENV)
    return Path(p) if p and Path(p).is_file() else None


def read_obj_groups(path):
    """An OBJ's vertices and polygons with their ``g`` group.

    Returns ``(V (N,3), poly_verts (C,), poly_offsets (P+1,), groups (P,) str)`` in the file's units.
    """
    V, pv, off, groups = [], [], [0], []
    g = ""
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                V.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("g "):
                g = line[2:].strip()
            elif line.startswith("f "):
                pv += [int(t.split("/")[0]) - 1 for t in line.split()[1:]]
                off.append(len(pv))
                groups.append(g)
    return np.asarray(V, np.float64), np.asarray(pv, np.int64), np.asarray(off, np.int64), np.asarray(groups)


def _fan(pv, off):
    """(F,3) fan triangulation of polygons ``pv`` / ``off``."""
    tris = []
    for p in range(len(off) - 1):
        c = pv[off[p]:off[p + 1]]
        tris += [[c[0], c[i], c[i + 1]] for i in range(1, len(c) - 1)]
    return np.asarray(tris, dtype=np.int64)


def _edge_graph(V, F):
    E = np.unique(np.sort(np.r_[F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], axis=1), axis=0)
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    G = sp.coo_matrix((w, (E[:, 0], E[:, 1])), shape=(len(V),) * 2).tocsr()
    return G + G.T


def face_markers(V, F, cm: float = 1.0) -> dict:
    """Landmark vertices of a head found from its shape alone: the same rules on any mesh.

    Parameters
    ----------
    V : (V,3) float
        Rest positions, Y up, Z forward, the face's midline at x = 0; ``cm`` units per centimetre.
    F : (F,3) int
        Triangles of the skin (the lips' inner surfaces included).

    Returns
    -------
    dict
        ``nose_tip`` (the front-most vertex), ``nasion`` (the deepest midline vertex 1-5 cm above the nose tip),
        ``upper_lip`` / ``lower_lip`` (the closest pair of midline vertices 1-4.5 cm below the nose tip that are
        far apart along the mesh: the lips' contact), ``corner_r`` / ``corner_l`` (the extremes across the face of
        such contact pairs, x < 0 and x > 0), ``chin`` (the front-most midline vertex 1.5-5 cm below the lips).
    """
    V = np.asarray(V, np.float64)
    used = np.zeros(len(V), bool)
    used[np.asarray(F).ravel()] = True
    ids = np.flatnonzero(used)
    nose = ids[np.argmax(V[ids, 2])]
    ny, nz = V[nose, 1], V[nose, 2]
    mid = ids[np.abs(V[ids, 0]) < 0.3 * cm]
    up = mid[(V[mid, 1] > ny + 1 * cm) & (V[mid, 1] < ny + 5 * cm) & (V[mid, 2] > nz - 4 * cm)]
    nasion = up[np.argmin(V[up, 2])]
    G = _edge_graph(V, np.asarray(F))

    def far_pairs(cand, radius, x_ok=None):
        pr = cKDTree(V[cand]).query_pairs(radius, output_type="ndarray")
        if len(pr) == 0:
            return np.zeros((0, 2), np.int64), np.zeros(0)
        i, j = cand[pr[:, 0]], cand[pr[:, 1]]
        e = np.linalg.norm(V[i] - V[j], axis=1)
        src, inv = np.unique(i, return_inverse=True)
        D = dijkstra(G, directed=False, indices=src, limit=2.0 * cm)
        geo = D[inv, j]
        ok = geo > np.maximum(1.0 * cm, 4.0 * e)
        return np.c_[i, j][ok], e[ok]

    box = mid[(V[mid, 1] < ny - 1 * cm) & (V[mid, 1] > ny - 4.5 * cm) & (V[mid, 2] > nz - 3 * cm)]
    pairs, e = far_pairs(box, 0.4 * cm)
    if len(pairs) == 0:
        raise ValueError("no lip contact below the nose: the mouth is sealed or the head is not Y up, Z forward")
    a, b = pairs[np.argmin(e - 1e-3 * (V[pairs[:, 0], 2] + V[pairs[:, 1], 2]))]
    upper, lower = (a, b) if V[a, 1] > V[b, 1] else (b, a)
    ly, lz = 0.5 * (V[upper, 1] + V[lower, 1]), 0.5 * (V[upper, 2] + V[lower, 2])
    mouth = ids[(np.abs(V[ids, 1] - ly) < 1.0 * cm) & (V[ids, 2] > lz - 3 * cm) & (np.abs(V[ids, 0]) < 4 * cm)]
    mp, _ = far_pairs(mouth, 0.3 * cm)
    x = V[mp, 0].mean(axis=1)
    corner_r = mp[np.argmin(x)][np.argmin(V[mp[np.argmin(x)], 0])]
    corner_l = mp[np.argmax(x)][np.argmax(V[mp[np.argmax(x)], 0])]
    low = mid[(V[mid, 1] < ly - 1.5 * cm) & (V[mid, 1] > ly - 5 * cm)]
    chin = low[np.argmax(V[low, 2])]
    return dict(nose_tip=int(nose), nasion=int(nasion), upper_lip=int(upper), lower_lip=int(lower),
                corner_r=int(corner_r), corner_l=int(corner_l), chin=int(chin))


def jaw_split_truth_line(V, X, F, corners, separation: float = 8.0):
    """The lip contact line of a coarse head whose lips part short of their corners, from its jaw opening.

    :func:`facelab_addon.testing.lip_truth.dense_truth_line` takes the corners from the contact pairs and joins
    them by a mesh path; on a mesh with a few vertices per lip that stand a millimetre or two apart (MakeHuman's),
    the pairs found at ratio 15 stop a centimetre short of the commissures, and the lips join on the mesh only
    inside the cheeks, so a lower chain over the mesh runs over the upper lip. Here the corners are given
    (``face_markers``' commissures), the contact pairs (:func:`~facelab_addon.testing.lip_truth.contact_pairs`,
    ratio ``separation``) are searched within the mouth's width, and each lip's chain is its pairs' members
    ordered across the face (of a pair, the member the jaw moves more is on the lower lip): a chain of the lip's
    contact vertices, not a mesh path (the route's truth uses it for distances and lip sides only).

    Parameters
    ----------
    V, X : (V,3) float
        Rest and jaw-open positions (any unit), Y up, Z forward, the midline at x = 0.
    F : (F,3) int
    corners : (2,) int
        The mouth corners (right, left).
    separation : float
        The contact pairs' least ratio.

    Returns
    -------
    TruthLine
    """
    from .lip_truth import TruthLine, contact_pairs

    V, X = np.asarray(V, np.float64), np.asarray(X, np.float64)
    c = np.asarray(corners, np.int64)
    skin = np.abs(V[:, 0]) <= np.abs(V[c, 0]).max() * 1.01
    pairs, _ = contact_pairs(V, X, np.asarray(F), skin, separation)
    if len(pairs) < 4:
        raise ValueError(f"no lip contact: {len(pairs)} vertex pairs part by {separation}x their distance")
    move = np.linalg.norm(X - V, axis=1)
    a_low = move[pairs[:, 0]] > move[pairs[:, 1]]
    chains = []
    for m in (np.where(a_low, pairs[:, 1], pairs[:, 0]), np.where(a_low, pairs[:, 0], pairs[:, 1])):
        m = np.setdiff1d(m, c)
        chains.append(np.r_[c[0], m[np.argsort(V[m, 0])], c[1]].astype(np.int64))
    return TruthLine(corners=c, upper=chains[0], lower=chains[1])


def _head(path):
    """MakeHuman's body cut at the neck, helpers dropped, compacted, in cm: ``(V, poly_verts, poly_offsets)``."""
    V, pv, off, groups = read_obj_groups(path)
    V = V * _DM_TO_CM
    body = groups == "body"
    if not body.any():
        raise ValueError(f"{path} has no 'body' group: not MakeHuman's base.obj ({HOW_TO})")
    sizes = np.diff(off)
    poly = np.repeat(np.arange(len(sizes)), sizes)
    bv = np.unique(pv[np.repeat(body, sizes)])
    top = bv[V[bv, 1] > V[bv, 1].max() - 30.0]  # the top 30 cm of the body: the head (its nose is the front-most)
    nose_y = V[top[np.argmax(V[top, 2])], 1]
    low = np.zeros(len(sizes), bool)
    np.logical_or.at(low, poly, V[pv, 1] < nose_y - NECK_BELOW_NOSE_CM)
    keep = body & ~low
    corner = np.repeat(keep, sizes)
    pvk = pv[corner]
    used = np.unique(pvk)
    remap = -np.ones(len(V), np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[pvk], np.r_[0, np.cumsum(sizes[keep])].astype(np.int64)


def makehuman_head(path=None, ict=None, expressions=EXPRESSIONS, *, use_cache: bool = True) -> TransferredHead:
    """MakeHuman's head with ICT-FaceKit's ``expressions`` transferred (see the module docstring).

    Parameters
    ----------
    path : str or Path, optional
        MakeHuman's ``base.obj`` (default :func:`makehuman_obj_path`).
    ict : ICTModel, optional
        The source of the expressions (default ``load_ict()``), centimetres.
    expressions : sequence of str
        ICT expression names.
    use_cache : bool
        Read / write the arrays under ``FACELAB_CACHE_DIR``.

    Returns
    -------
    TransferredHead
        Centimetres, Y up, Z forward.

    Raises
    ------
    FileNotFoundError
        Without the OBJ (:data:`HOW_TO`).
    """
    from ..core.solve.deformation_transfer import DeformationTransfer, triangle_correspondence_from_markers

    path = Path(path) if path is not None else makehuman_obj_path()
    if path is None or not path.is_file():
        raise FileNotFoundError(f"MakeHuman's base mesh is not available: {HOW_TO}")
    names = list(expressions)
    raw = path.read_bytes()
    key = hashlib.sha1(raw + f"{NECK_BELOW_NOSE_CM}{names}v4".encode()).hexdigest()[:12]
    cache = Path(os.environ.get("FACELAB_CACHE_DIR", Path.home() / ".cache" / "facelab")) / f"makehuman_{key}.npz"
    if use_cache and cache.exists():
        from .lip_truth import TruthLine

        d = np.load(cache)
        return TransferredHead(neutral=d["neutral"], poly_verts=d["poly_verts"], poly_offsets=d["poly_offsets"],
                               expressions={n: d["expressions"][i] for i, n in enumerate(names)},
                               markers={k: int(v) for k, v in zip(d["marker_names"], d["marker_ids"])},
                               truth=TruthLine(d["truth_corners"], d["truth_upper"], d["truth_lower"]))
    if ict is None:
        from ..core.capture.ict import load_ict

        ict = load_ict()
    V, pv, off = _head(path)
    head = TransferredHead(neutral=V, poly_verts=pv, poly_offsets=off, expressions={}, markers={})
    # the source: ICT's skin (face and back of the head), compacted
    sf = ict.faces[ict.part_face_mask("M_Face", "M_BackHead")]
    su = np.unique(sf)
    sremap = -np.ones(len(ict.neutral), np.int64)
    sremap[su] = np.arange(len(su))
    Fs, Vs = sremap[sf], np.asarray(ict.neutral, np.float64)[su] / float(ict.scale)
    ms, mt = face_markers(Vs, Fs), face_markers(V, head.faces)
    order = list(ms)
    # the head is moved onto ICT's (markers' centroids together) for the transfer and the offsets are kept; the
    # transfer itself fits the head's placement (DeformationTransfer.placement), so this only keeps numbers small
    c = V[[mt[k] for k in order]].mean(axis=0) - Vs[[ms[k] for k in order]].mean(axis=0)
    corr = triangle_correspondence_from_markers(Vs, Fs, V - c, head.faces, [ms[k] for k in order],
                                                [mt[k] for k in order])
    dt = DeformationTransfer(Vs, Fs, V - c, head.faces, corr)
    X = np.stack([np.asarray(ict.expressions[n], np.float64)[su] / float(ict.scale) for n in names])
    out = dt.transfer(X) + c
    head.expressions = {n: out[i] for i, n in enumerate(names)}
    head.markers = mt
    head.truth = jaw_split_truth_line(V, head.expressions["jawOpen"], head.faces, [mt["corner_r"], mt["corner_l"]])
    if use_cache:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, neutral=V, poly_verts=pv, poly_offsets=off, expressions=out,
                 marker_names=np.array(order), marker_ids=np.array([mt[k] for k in order]),
                 truth_corners=head.truth.corners, truth_upper=head.truth.upper, truth_lower=head.truth.lower)
    return head
