"""Deformation transfer of an actor's shapes to a creature mesh.

Bhat et al. 2013, "High fidelity facial animation capture and retargeting
with contours", §5.1: the creature's blendshape rig is made by transferring
the actor's blendshapes with deformation transfer (Sumner and Popović 2004,
"Deformation transfer for triangle meshes"), so the two rigs are parallel and
the solved weights are copied; the per-frame correctives are transferred the
same way.

Method (Sumner & Popović §3-4, in the gradient-domain form of Botsch et al.
2006, "Deformation transfer for detail-preserving surface editing"):

* the source deformation of every source triangle is its deformation gradient
  ``S = D_d D_r^-1`` with the phantom fourth vertex (``core.geometry.gradients``);
* the target may sit anywhere, at another size or orientation: the
  similarity ``x -> s R x + t`` that best maps the corresponding source points
  onto the target (Umeyama) brings the target into the source's frame, the
  system below is built and solved there, and its displacements are mapped
  back (``s R``): in the target's frame the source gradients act as
  ``R S R^T`` and a source displacement as ``s R d`` (``R`` is a rotation,
  or a reflection for a mirror image of the source);
* every target triangle ``t`` takes the (placed) gradient of its corresponding
  source triangle ``c(t)`` (identity when it has none), and the target positions
  minimise ``sum_t area_t || grad_t(x) - S_c(t) ||^2`` over the target rest
  triangles: the Poisson system ``L x = D g`` of ``core.geometry.laplacian.poisson_operator``
  (``L`` is the target's cotangent Laplacian), factored once and solved for
  any number of shapes and frames;
* the system only knows gradients, so each connected piece of the target is
  placed by translation: its mean displacement equals the mean *hint*
  displacement of its vertices, the source displacement carried over by the
  correspondence (the same vertex for meshes that share topology), placed,
  and moved to the target vertex to first order with the local gradient,
  ``s R d + (F - I)(x_target - (s R x_source + t))``, which is exact for
  rigid motions and similarities and does not depend on the placement.

For meshes that share topology the correspondence is the identity (a vertex
map). For different topologies, :func:`triangle_correspondence_from_markers`
builds it as Sumner and Popović §5 do: fit the source onto the target with
marker point constraints and closest-point terms (the shared Laplacian solver
``core.geometry.deform.LaplacianDeformer``), then pair every target triangle with the
nearest compatible source triangle.

Units: positions in scene units; gradients are unitless.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..errors import FaceLabError, MeshError
from ..geometry.deform import LaplacianDeformer, PointConstraints
from ..geometry.gradients import shape_matrices
from ..geometry.inv3 import inv3
from ..geometry.laplacian import poisson_operator, uniform_laplacian
from ..geometry.linsolve import SPDFactor
from ..geometry.mesh import connected_components, face_normals, vertex_normals

__all__ = ["DeformationTransfer", "deformation_transfer", "triangle_correspondence_from_markers"]

_BLOCK = 16  # shapes per block of gradient targets (working memory ~ 9 x F x 8 B x 16)


def _check_mesh(V, F, name):
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise MeshError(f"The {name} must be a non-empty (V,3) array of vertices, got shape {V.shape}.")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0 or not np.issubdtype(F.dtype, np.integer):
        raise MeshError(f"The {name} faces must be an (F,3) integer array of triangles, got {F.shape}; triangulate first.")
    F = F.astype(np.int64)
    if F.min() < 0 or F.max() >= len(V):
        raise MeshError(f"The {name} faces refer to vertices outside 0..{len(V) - 1}; the mesh data is inconsistent.")
    if not np.isfinite(V).all():
        raise MeshError(f"The {name} has NaN or infinite coordinates; fix the mesh first.")
    return V, F


def _nondegenerate(V, F, rel=1e-12):
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    a2 = np.linalg.norm(np.cross(e1, e2), axis=1)
    scale = np.maximum(np.linalg.norm(e1, axis=1), np.linalg.norm(e2, axis=1))
    return a2 > rel * np.maximum(scale, 1e-300) ** 2


class DeformationTransfer:
    """Factor-once deformation transfer from a source mesh to a target mesh.

    Parameters
    ----------
    source_rest : (V,3) array_like
        Source (actor) rest positions, scene units.
    source_faces : (F_s,3) int array_like
        Source triangles.
    target_rest : (W,3) array_like
        Target (creature) rest positions, scene units (same units as the source).
    target_faces : (F_t,3) int array_like
        Target triangles.
    correspondence : (F_t,) int array_like, optional
        Source triangle of every target triangle, ``-1`` for target triangles
        that follow no source triangle (they keep their rest shape, up to the
        motion of their neighbours). Default: the identity, which needs the
        same triangles in the same order (meshes that share topology).
    backend : str
        ``SPDFactor`` backend.

    Attributes
    ----------
    placement : tuple (float, (3,3) ndarray, (3,) ndarray)
        ``(s, R, t)``: the similarity ``x -> s R x + t`` (unitless scale,
        (3,3) rotation or, for a mirror image, reflection; translation in
        scene units) that best maps the source points corresponding to the
        target vertices onto them.

    Notes
    -----
    The transfer is affine in the source gradients: for meshes that share
    topology and rest shape it reproduces the source exactly, and a copy of
    the source moved by a similarity ``P`` (``placement``) receives exactly
    ``s R d``. An identity deformation gives the target rest exactly, and a
    global similarity ``M`` of the source gives exactly the similarity
    ``P M P^-1`` of the target (``M`` itself when the target sits where the
    source does), every piece included. A general affine map ``A`` is reproduced
    (up to translation) where the target triangles are parallel to the
    source ones: the phantom vertex makes a source gradient equal ``A`` on its
    triangle's plane only. The gradients are not linear in the positions (the
    phantom normal), so transferring a sum of shapes differs slightly from
    the sum of the transferred shapes (about 1e-4 of the motion in the tests).
    Degenerate (zero-area) target triangles are left out of the system;
    degenerate source triangles transfer the identity.
    """

    def __init__(self, source_rest, source_faces, target_rest, target_faces, correspondence=None, *,
                 backend: str = "auto"):
        Vs, Fs = _check_mesh(source_rest, source_faces, "source (actor) mesh")
        Vt, Ft = _check_mesh(target_rest, target_faces, "target (creature) mesh")
        self.source_rest, self.source_faces = Vs, Fs
        self.target_rest, self.target_faces = Vt, Ft
        if correspondence is None:
            if Fs.shape != Ft.shape or not np.array_equal(Fs, Ft):
                raise FaceLabError(
                    f"The creature ({len(Vt)} vertices, {len(Ft)} triangles) does not share the actor's topology "
                    f"({len(Vs)} vertices, {len(Fs)} triangles), so there is no correspondence; give a triangle "
                    "correspondence (triangle_correspondence_from_markers with markers placed on both meshes) or "
                    "use a creature made from the actor's mesh."
                )
            corr = np.arange(len(Ft), dtype=np.int64)
        else:
            corr = np.asarray(correspondence).astype(np.int64).ravel()
            if corr.shape != (len(Ft),):
                raise FaceLabError(
                    f"The correspondence has {corr.size} entries but the creature has {len(Ft)} triangles; "
                    "rebuild it for this creature mesh."
                )
            if corr.max(initial=-1) >= len(Fs) or corr.min(initial=0) < -1:
                raise FaceLabError(
                    f"The correspondence refers to source triangles outside 0..{len(Fs) - 1}; rebuild it for this actor."
                )
            if not (corr >= 0).any():
                raise FaceLabError(
                    "The correspondence pairs no creature triangle with an actor triangle; place markers on both "
                    "meshes and rebuild it."
                )
        self.correspondence = corr
        self.same_topology = correspondence is None or (len(Vs) == len(Vt) and np.array_equal(corr, np.arange(len(Ft)))
                                                        and np.array_equal(Fs, Ft))

        # source rest inverses of the used source triangles (degenerate ones transfer the identity)
        used = np.unique(corr[corr >= 0])
        self._src_used = used
        Dr = shape_matrices(Vs, Fs[used])
        ok = _nondegenerate(Vs, Fs[used])
        inv = np.zeros_like(Dr)
        inv[ok] = inv3(Dr[ok])
        self._src_inv = inv
        self._src_ok = ok
        pos = -np.ones(len(Fs), np.int64)
        pos[used] = np.arange(len(used))
        self._tri_src = np.where(corr >= 0, pos[np.maximum(corr, 0)], -1)  # index into used, -1 = identity
        self._tri_src[(self._tri_src >= 0) & ~ok[np.maximum(self._tri_src, 0)]] = -1

        # hints: target vertex displacement from source vertex displacements, (W, V) sparse
        if self.same_topology:
            self._H = sp.identity(len(Vt), format="csr")
        else:
            ft = np.flatnonzero(corr >= 0)
            rows = np.repeat(Ft[ft], 3, axis=1).ravel()  # target vertex of each (tri corner, src corner)
            cols = np.tile(Fs[corr[ft]], (1, 3)).ravel()
            H = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(Vt), len(Vs))).tocsr()
            s = np.asarray(H.sum(axis=1)).ravel()
            H = sp.diags(np.divide(1.0, s, out=np.zeros_like(s), where=s > 0)) @ H
            # target vertices with no corresponding triangle: nearest hinted neighbour through the mesh
            self._H = self._spread_hints(H.tocsr(), s > 0, Ft)
        # placement of the target relative to the source: the similarity x -> s R x + t that best maps the
        # corresponding source points onto the target. The system is built and solved with the target brought
        # into the source's frame (Vp), and its displacements are mapped back (s R), so the transfer does not
        # depend on where, at which size or in which orientation the target was modelled.
        hinted = np.asarray(self._H.sum(axis=1)).ravel() > 0
        corresp = self._H @ Vs
        s_, R_, t_ = _placement(corresp[hinted], Vt[hinted])
        self.placement = (s_, R_, t_)
        Vp = (Vt - t_) @ R_ / s_  # (W,3) target rest in the source's frame
        self._offset = Vp - corresp  # (W,3) target minus corresponding source position, source frame

        # target Poisson system over its non-degenerate triangles
        tok = _nondegenerate(Vp, Ft)
        self._tgt_faces_idx = np.flatnonzero(tok)
        L, D = poisson_operator(Vp, Ft, self._tgt_faces_idx)
        self._L = L
        self._D = D
        n = len(Vt)
        in_tri = np.zeros(n, bool)
        in_tri[Ft[tok].ravel()] = True
        self._in_tri = in_tri
        comp = connected_components(Ft[tok], n)
        self._comp = comp
        # one pinned vertex per piece (its value is irrelevant: the piece is re-translated afterwards)
        labels, first = np.unique(comp[in_tri], return_index=True)
        pinned_idx = np.flatnonzero(in_tri)[first]
        pinned = ~in_tri.copy()
        pinned[pinned_idx] = True
        self._pinned = pinned
        self._free = np.flatnonzero(~pinned)
        self._piece_of = comp
        Lc = L.tocsr()
        Lrows = Lc[self._free]
        self._Lff = Lrows[:, self._free]
        self._Lfp = Lrows[:, self._pinned].tocsr()
        self.factor = SPDFactor(self._Lff, backend=backend, what="deformation-transfer Poisson system")
        self._Dfree = D.tocsr()[self._free]
        self._Lrest = (L @ Vp)[self._free]  # gradient of the rest shape (in-plane identity) pushed through D

        tf = Ft[tok]
        r = tf.ravel()
        c = np.repeat(np.arange(len(tf)), 3)
        Avg = sp.coo_matrix((np.ones(len(r)), (r, c)), shape=(n, len(tf))).tocsr()
        cnt_v = np.asarray(Avg.sum(axis=1)).ravel()
        self._avg = (sp.diags(np.divide(1.0, cnt_v, out=np.zeros_like(cnt_v), where=cnt_v > 0)) @ Avg).tocsr()
        # piece mean operator: (n_pieces, W) rows average the piece's vertices
        npieces = comp.max() + 1
        cnt = np.bincount(comp, minlength=npieces).astype(np.float64)
        self._piece_mean = sp.csr_matrix((1.0 / cnt[comp], (comp, np.arange(n))), shape=(npieces, n))

    @staticmethod
    def _spread_hints(H, has, F):
        if has.all():
            return H
        from ..geometry.mesh import vertex_adjacency

        A = vertex_adjacency(F, H.shape[0]).tocsr()
        H = H.tolil()
        known = has.copy()
        for _ in range(64):
            todo = np.flatnonzero(~known)
            if len(todo) == 0:
                break
            nb = A[todo] @ known.astype(np.float64)
            ready = todo[nb > 0]
            if len(ready) == 0:
                break
            Hc = H.tocsr()
            W = sp.diags(known.astype(np.float64))
            S = (A[ready] @ W) @ Hc
            cnt = np.asarray((A[ready] @ W).sum(axis=1)).ravel()
            S = sp.diags(1.0 / cnt) @ S
            H[ready] = S
            known[ready] = True
        return H.tocsr()

    # ------------------------------------------------------------------ core
    def source_gradients(self, deformed) -> np.ndarray:
        """Deformation gradients ``S`` of the used source triangles.

        Parameters
        ----------
        deformed : (V,3) or (B,V,3) array_like
            Deformed source positions, scene units.

        Returns
        -------
        (U,3,3) or (B,U,3,3) ndarray
            Unitless, for the source triangles the correspondence uses.
        """
        X = np.asarray(deformed, dtype=np.float64)
        Dd = shape_matrices(X, self.source_faces[self._src_used])
        return np.matmul(Dd, self._src_inv)

    def _solve_displacements(self, deformed, displacement):
        """Target displacements (B,W,3) for deformed source shapes (B,V,3) with source displacements."""
        B = deformed.shape[0]
        G = self.source_gradients(deformed)  # (B,U,3,3)
        G[:, ~self._src_ok] = np.eye(3)
        tri = self._tri_src[self._tgt_faces_idx]
        Ft = np.empty((B, len(tri), 3, 3))
        Ft[:, tri >= 0] = G[:, tri[tri >= 0]]
        Ft[:, tri < 0] = np.eye(3)
        n = len(tri)
        # g for coordinate c on triangle t is Ft[t, c, :] -> (3n, 3) per shape, shapes side by side
        g = Ft.transpose(1, 3, 0, 2).reshape(3 * n, B * 3)  # rows (t, axis j), cols (b, c)
        rhs = self._Dfree @ g - np.tile(self._Lrest, (1, B))
        # hint: source displacement of the corresponding point, carried to the (placed) target vertex to first
        # order with the local gradient (exact for affine deformations): d + (F_v - I)(x_t - x_s)
        Fv = np.stack([self._avg @ Ft[b].reshape(n, 9) for b in range(B)]).reshape(B, -1, 3, 3) - np.eye(3)
        Fv[:, ~self._in_tri] = 0.0
        hint = np.stack([self._H @ displacement[b] for b in range(B)])  # (B,W,3)
        hint += np.einsum("bwij,wj->bwi", Fv, self._offset)
        Y = np.zeros((B, len(self.target_rest), 3))
        Y[:, self._pinned] = hint[:, self._pinned]
        if self._Lfp.nnz:
            rhs = rhs - np.concatenate([self._Lfp @ Y[b, self._pinned] for b in range(B)], axis=1)
        Xf = self.factor.solve(rhs).reshape(len(self._free), B, 3)
        Y[:, self._free] = Xf.transpose(1, 0, 2)
        # place every piece: mean displacement = mean hint over its vertices
        for b in range(B):
            shift = self._piece_mean @ (hint[b] - Y[b])  # (pieces,3)
            Y[b] += shift[self._piece_of]
            Y[b, ~self._in_tri] = hint[b, ~self._in_tri]
        s_, R_, _ = self.placement
        return (s_ * Y) @ R_.T  # back to the target's frame

    def transfer_deltas(self, deltas) -> np.ndarray:
        """Transfer source shape deltas (blendshapes, correctives) to target deltas.

        Parameters
        ----------
        deltas : (V,3) or (S,V,3) array_like
            Source displacements from ``source_rest``, scene units.

        Returns
        -------
        (W,3) or (S,W,3) float64 ndarray
            Target displacements from ``target_rest``, scene units.
        """
        d = np.asarray(deltas, dtype=np.float64)
        one = d.ndim == 2
        d = d[None] if one else d
        if d.ndim != 3 or d.shape[1:] != self.source_rest.shape:
            raise FaceLabError(
                f"Expected source shapes of {len(self.source_rest)} vertices, got array of shape {np.shape(deltas)}; "
                "use shapes of the actor mesh the transfer was built for."
            )
        if not np.isfinite(d).all():
            raise FaceLabError("A source shape has NaN or infinite coordinates; fix the actor's shape keys.")
        out = np.empty((len(d),) + self.target_rest.shape)
        for s in range(0, len(d), _BLOCK):
            blk = d[s : s + _BLOCK]
            out[s : s + _BLOCK] = self._solve_displacements(self.source_rest + blk, blk)
        return out[0] if one else out

    def transfer(self, deformed) -> np.ndarray:
        """Transfer deformed source shapes to deformed target shapes.

        Parameters
        ----------
        deformed : (V,3) or (S,V,3) array_like
            Deformed source positions, scene units.

        Returns
        -------
        (W,3) or (S,W,3) float64 ndarray
            Deformed target positions, scene units.
        """
        X = np.asarray(deformed, dtype=np.float64)
        return self.target_rest + self.transfer_deltas(X - self.source_rest)

    def transfer_correctives(self, correctives, base=None) -> np.ndarray:
        """Transfer per-frame correctives (Bhat §5.1 "we retarget the correctives").

        Parameters
        ----------
        correctives : (V,3) or (T,V,3) array_like
            Source correctives ``dV``, scene units.
        base : (V,3) or (T,V,3) array_like, optional
            Source shapes the correctives sit on (the blendshape result of each
            frame, as deltas from ``source_rest``). Given: the target
            corrective is ``transfer(base + dV) - transfer(base)``, exact for the
            frame. Default: ``transfer_deltas(dV)`` (the corrective as a shape
            on the rest pose; equal to the former up to the small non-linearity
            of the phantom-vertex normals).

        Returns
        -------
        (W,3) or (T,W,3) float64 ndarray
            Target correctives, scene units.
        """
        C = np.asarray(correctives, dtype=np.float64)
        if base is None:
            return self.transfer_deltas(C)
        Bs = np.broadcast_to(np.asarray(base, dtype=np.float64), C.shape)
        one = C.ndim == 2
        C2, B2 = (C[None], Bs[None]) if one else (C, Bs)
        out = np.empty((len(C2),) + self.target_rest.shape)
        h = max(1, _BLOCK // 2)
        for s in range(0, len(C2), h):
            both = np.concatenate([B2[s : s + h] + C2[s : s + h], B2[s : s + h]])
            Y = self.transfer_deltas(both)
            k = len(both) // 2
            out[s : s + h] = Y[:k] - Y[k:]
        return out[0] if one else out


def deformation_transfer(source_rest, source_faces, source_deformed, target_rest, target_faces,
                         correspondence=None) -> np.ndarray:
    """One-shot deformation transfer (Sumner & Popović 2004; Bhat et al. 2013 §5.1).

    Parameters
    ----------
    source_rest : (V,3) array_like
        Source rest positions, scene units.
    source_faces : (F_s,3) int array_like
    source_deformed : (V,3) or (S,V,3) array_like
        Deformed source shapes (positions), scene units.
    target_rest : (W,3) array_like
    target_faces : (F_t,3) int array_like
    correspondence : (F_t,) int array_like, optional
        Source triangle per target triangle (``-1``: none); default identity
        (shared topology).

    Returns
    -------
    (W,3) or (S,W,3) float64 ndarray
        Deformed target positions, scene units.

    See Also
    --------
    DeformationTransfer : factor once, transfer many shapes and frames.
    """
    return DeformationTransfer(source_rest, source_faces, target_rest, target_faces, correspondence).transfer(
        source_deformed
    )


# --------------------------------------------------------------------------
# Correspondence for meshes of different topology (Sumner & Popović §5)
# --------------------------------------------------------------------------


def _similarity(P, Q, reflect: bool = False):
    """Least-squares similarity ``Q ~ s R P + t`` (Umeyama) of points P, Q (n,3); returns (s, R, t).

    ``R`` is the best rotation, or with ``reflect`` the best reflection (det -1).
    """
    mp, mq = P.mean(0), Q.mean(0)
    A, B = P - mp, Q - mq
    U, S, Vt = np.linalg.svd(B.T @ A)
    d = np.sign(np.linalg.det(U @ Vt))
    Dm = np.diag([1.0, 1.0, -d if reflect else d])
    R = U @ Dm @ Vt
    var = (A**2).sum()
    s = float((S * np.diag(Dm)).sum() / var) if var > 0 else 1.0
    return s, R, mq - s * R @ mp


def _placement(P, Q):
    """Similarity ``Q ~ s R P + t`` placing source points P (n,3) on target points Q (n,3); (s, R, t).

    ``R`` is a rotation, or a reflection when that fits clearly better (a mirrored copy: residual
    under a quarter of the rotation's). Falls back to a translation when the points do not span a
    plane (the rotation is not determined).
    """
    mp, mq = P.mean(0), Q.mean(0)
    A, B = P - mp, Q - mq
    S = np.linalg.svd(B.T @ A, compute_uv=False)
    if len(P) < 3 or not (A**2).sum() > 0 or S[1] <= 1e-9 * max(S[0], 1e-300):
        return 1.0, np.eye(3), mq - mp
    best = None
    for reflect in (False, True):
        sc, R, t = _similarity(P, Q, reflect)
        res = float(((B - sc * A @ R.T) ** 2).sum())
        if best is None or (sc > 0 and res < 0.25 * best[0]):
            best = (res, sc, R, t)
    return best[1:]


def _closest_points(P, V, F):
    import igl

    sq, idx, C = igl.point_mesh_squared_distance(np.ascontiguousarray(P), np.ascontiguousarray(V),
                                                 np.ascontiguousarray(F))
    return np.sqrt(np.maximum(sq, 0.0)), np.asarray(idx, dtype=np.int64).ravel(), C


def triangle_correspondence_from_markers(source_rest, source_faces, target_rest, target_faces, source_markers,
                                         target_markers, *, iterations: int = 4, max_distance=None,
                                         normal_dot: float = 0.3, source_groups=None, target_groups=None,
                                         return_fitted: bool = False):
    """Triangle correspondence between meshes of different topology from markers.

    Sumner & Popović 2004 §5: the source is deformed onto the target with the
    markers as point constraints and a smoothness term, then pulled towards
    the closest compatible target points with an increasing weight; every
    target triangle then takes the source triangle whose fitted centroid is
    nearest (among those with a normal within ``acos(normal_dot)``).

    Parameters
    ----------
    source_rest : (V,3) array_like
        Source (actor) rest positions, scene units.
    source_faces : (F_s,3) int array_like
    target_rest : (W,3) array_like
        Target (creature) rest positions, scene units (any units: a
        similarity aligns the markers first).
    target_faces : (F_t,3) int array_like
    source_markers : (m,) int array_like
        Source vertex of each marker.
    target_markers : (m,) int or (m,3) float array_like
        Target vertex (int) or target position (scene units) of each marker.
    iterations : int
        Closest-point rounds (weights 0.01, 0.1, 1, 10, ... of the Laplacian).
    max_distance : float, optional
        Closest points further than this (target units) are not used;
        default 5 % of the target's bounding-box diagonal.
    normal_dot : float
        Minimum cosine between source and target normals for closest points
        and for the final triangle pairing.
    source_groups, target_groups : (F_s,), (F_t,) int array_like, optional
        Labels of matching parts (for example materials: skin, teeth, eyes).
        Closest points and the pairing stay within the same label, which
        keeps layered parts (lips over teeth, lashes over eyes) apart.
    return_fitted : bool
        Also return the fitted source positions (target units).

    Returns
    -------
    (F_t,) int64 ndarray
        Source triangle of every target triangle; ``-1`` only for target
        triangles whose group has no source triangle.
    fitted : (V,3) ndarray
        Only with ``return_fitted``.

    Raises
    ------
    FaceLabError
        With fewer than 4 markers, mismatched marker counts or indices
        outside the meshes.
    """
    Vs, Fs = _check_mesh(source_rest, source_faces, "source (actor) mesh")
    Vt, Ft = _check_mesh(target_rest, target_faces, "target (creature) mesh")
    sm = np.asarray(source_markers).astype(np.int64).ravel()
    tm = np.asarray(target_markers)
    if np.issubdtype(tm.dtype, np.integer) and tm.ndim == 1:
        if tm.min(initial=0) < 0 or tm.max(initial=0) >= len(Vt):
            raise FaceLabError(f"Target marker vertices must be in 0..{len(Vt) - 1}; re-place the creature markers.")
        Q = Vt[tm]
    else:
        Q = np.asarray(tm, dtype=np.float64).reshape(-1, 3)
    if len(sm) != len(Q):
        raise FaceLabError(
            f"{len(sm)} actor markers but {len(Q)} creature markers; place the same markers, in the same order, "
            "on both meshes."
        )
    if len(sm) < 4:
        raise FaceLabError(
            f"Only {len(sm)} marker pairs; place at least 4 (better 10-20: eye and mouth corners, nose tip, chin, "
            "jaw line) on both meshes to build the correspondence."
        )
    if sm.min() < 0 or sm.max() >= len(Vs):
        raise FaceLabError(f"Source marker vertices must be in 0..{len(Vs) - 1}; re-place the actor markers.")
    if (source_groups is None) != (target_groups is None):
        raise FaceLabError("Give part labels for both meshes (source_groups and target_groups) or for neither.")
    sg = np.zeros(len(Fs), np.int64) if source_groups is None else np.asarray(source_groups).astype(np.int64).ravel()
    tg = np.zeros(len(Ft), np.int64) if target_groups is None else np.asarray(target_groups).astype(np.int64).ravel()
    if sg.shape != (len(Fs),) or tg.shape != (len(Ft),):
        raise FaceLabError(
            f"Part labels must have one entry per triangle ({len(Fs)} actor, {len(Ft)} creature), got "
            f"{sg.size} and {tg.size}; label the triangles again."
        )
    vlab = np.full(len(Vs), -1, np.int64)
    vlab[Fs.ravel()] = np.repeat(sg, 3)
    s, R, t = _similarity(Vs[sm], Q)
    X = s * Vs @ R.T + t
    diag = float(np.linalg.norm(np.ptp(Vt, axis=0)))
    dmax = 0.05 * diag if max_distance is None else float(max_distance)
    L = uniform_laplacian(Fs, len(Vs))
    marks = PointConstraints.points(sm, Q, strength=100.0)
    tn_face = face_normals(Vt, Ft)
    ref = X.copy()  # Laplacian coordinates of the aligned source are kept
    # 1: markers only (tiny anchor to the aligned source fixes the pieces without markers)
    X = LaplacianDeformer(L, lambda_reg=1.0, pos_weights=1e-3).solve(X, ref, marks)
    for k in range(int(iterations)):
        w = 0.01 * 10.0**k
        dist = np.full(len(X), np.inf)
        tri = np.zeros(len(X), np.int64)
        C = X.copy()
        for g in np.unique(vlab[vlab >= 0]):
            sel = vlab == g
            tids = np.flatnonzero(tg == g)
            if len(tids) == 0:
                continue
            d_, t_, c_ = _closest_points(X[sel], Vt, Ft[tids])
            dist[sel], tri[sel], C[sel] = d_, tids[t_], c_
        vn = vertex_normals(X, Fs)
        ok = (dist <= dmax) & (np.einsum("ij,ij->i", vn, tn_face[tri]) >= normal_dot)
        anchor = np.where(ok[:, None], C, X)
        wts = np.where(ok, w, 1e-3)
        X = LaplacianDeformer(L, lambda_reg=1.0, pos_weights=wts).solve(anchor, ref, marks)
    from scipy.spatial import cKDTree

    sc = X[Fs].mean(axis=1)
    sn = face_normals(X, Fs)
    tc = Vt[Ft].mean(axis=1)
    corr = -np.ones(len(Ft), np.int64)
    for g in np.unique(tg):
        ti = np.flatnonzero(tg == g)
        si = np.flatnonzero(sg == g)
        if len(si) == 0:
            continue
        k = min(16, len(si))
        _, nb = cKDTree(sc[si]).query(tc[ti], k=k)
        nb = si[nb.reshape(len(ti), -1)]
        compat = np.einsum("tkj,tj->tk", sn[nb], tn_face[ti]) >= normal_dot
        first = np.where(compat.any(axis=1), np.argmax(compat, axis=1), 0)
        corr[ti] = nb[np.arange(len(ti)), first]
    return (corr, X) if return_fitted else corr
