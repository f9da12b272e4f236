"""The one constrained Laplacian-deformation least-squares solver.

Sketch refinement (Dinev et al. 2018 §5), Bhat et al.'s out-of-subspace
corrective (2013 §4.3) and retargeting all minimise the same energy with
different constraint terms::

    E(X) = lambda_reg * || L_r X - delta ||^2                (Laplacian coordinates)
         + sum_i w_i   * || x_i - a_i ||^2                   (position / anchor)
         + sum_c s_c   * || P_c (sum_j b_cj x_{v_cj} - q_c) ||^2   (point constraints)

subject to ``x_i = a_i`` for pinned vertices. ``X`` is ``(V,3)`` in scene
units. A point constraint ties a barycentric surface point to a target with a
3x3 metric ``P``: ``P = I`` is a 3D position, ``P = I - d d^T`` the distance to
a ray through ``q`` with unit direction ``d``, ``P = n n^T`` a plane.

The base matrix ``M = lambda_reg L_fᵀ L_f + diag(w_f)`` over the free
vertices does not depend on the constraints, so it is factored once in
``LaplacianDeformer.__init__``. Constraints are added exactly with the
Woodbury identity: only the columns ``M^-1 e_v`` of constrained vertices are
needed, and they are cached between calls (constraints that move from vertex
to vertex, like silhouettes, reuse most of them).

Constraint terms that stay the same over many solves but couple the three
coordinates (a metric ``P`` that is not a multiple of the identity on every free
vertex, such as an anisotropic stiffness) are folded into the factor instead:
:meth:`LaplacianDeformer.with_terms` returns a :class:`CoupledDeformer`, whose
``(3 n_free)`` system is factored once and which adds the moving constraints
the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from ..errors import FaceLabError, UsageError
from .linsolve import SPDFactor

__all__ = ["PointConstraints", "LaplacianDeformer", "CoupledDeformer"]


@dataclass
class PointConstraints:
    """A batch of ``c`` point constraints.

    Attributes
    ----------
    vertices : (c,k) int ndarray
        Vertices of each constrained surface point (``k=1`` for a vertex,
        ``k=3`` for a point inside a triangle).
    bary : (c,k) float ndarray
        Barycentric weights of the surface point.
    targets : (c,3) float ndarray
        Target point ``q`` (a point on the ray for ray constraints), scene units.
    metrics : (c,3,3) float ndarray
        ``P`` in ``||P (x - q)||^2``.
    strength : (c,) float ndarray
        Weight ``s_c`` of each constraint.
    """

    vertices: np.ndarray
    bary: np.ndarray
    targets: np.ndarray
    metrics: np.ndarray
    strength: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.vertices, dtype=np.int64)
        self.vertices = v.reshape(len(v), -1)
        c = len(self.vertices)
        self.bary = np.asarray(self.bary, dtype=np.float64).reshape(c, -1)
        self.targets = np.asarray(self.targets, dtype=np.float64).reshape(c, 3)
        self.metrics = np.asarray(self.metrics, dtype=np.float64).reshape(c, 3, 3)
        self.strength = np.broadcast_to(np.asarray(self.strength, dtype=np.float64), (c,)).copy()
        if self.bary.shape != self.vertices.shape:
            raise UsageError("bary must have the shape of vertices (c,k); give one weight per constrained vertex")
        if not (np.isfinite(self.targets).all() and np.isfinite(self.metrics).all()):
            raise FaceLabError("A constraint target is NaN or infinite; check the markers or strokes on this frame.")

    def __len__(self):
        return len(self.vertices)

    @classmethod
    def points(cls, vertices, targets, strength=1.0, bary=None):
        """Position constraints ``||x - q||^2`` (``P = I``); vertices (c,) or (c,k)."""
        v = np.asarray(vertices, dtype=np.int64)
        v = v.reshape(len(v), -1)
        b = np.ones(v.shape) if bary is None else bary
        return cls(v, b, targets, np.broadcast_to(np.eye(3), (len(v), 3, 3)), strength)

    @classmethod
    def rays(cls, vertices, origins, directions, strength=1.0, bary=None):
        """Point-to-ray distance constraints ``||(I - d dᵀ)(x - o)||^2``.

        Parameters
        ----------
        vertices : (c,) or (c,k) int
        origins, directions : (c,3) float
            Ray origins (scene units) and directions (normalised here).
        """
        v = np.asarray(vertices, dtype=np.int64)
        v = v.reshape(len(v), -1)
        d = np.asarray(directions, dtype=np.float64)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
        b = np.ones(v.shape) if bary is None else bary
        return cls(v, b, origins, P, strength)

    @staticmethod
    def concat(items):
        items = [c for c in items if c is not None and len(c)]
        if not items:
            return None
        k = max(c.vertices.shape[1] for c in items)

        def pad(a, fill):
            return np.pad(a, ((0, 0), (0, k - a.shape[1])), constant_values=fill)

        return PointConstraints(
            np.concatenate([pad(c.vertices, 0) for c in items]),
            np.concatenate([pad(c.bary, 0.0) for c in items]),
            np.concatenate([c.targets for c in items]),
            np.concatenate([c.metrics for c in items]),
            np.concatenate([c.strength for c in items]),
        )


class _ColumnCache:
    """Columns ``M^-1 e_k`` of a factored SPD system ``M`` (n x n), solved once each and kept.

    The columns are kept as the blocks the factor solved them in, ``(n, k_b)`` each, and never copied when
    more are added. A solve reads only what it needs from them: the principal block of ``M^-1`` on its
    unknowns (:meth:`principal`) and the product of its columns with a small matrix (:meth:`apply`).

    Parameters
    ----------
    factor : SPDFactor
        The factored ``M``.
    n : int
        Unknowns of ``M``.
    """

    def __init__(self, factor, n: int):
        self.factor = factor
        self.n = int(n)
        self.blocks = []  # (n, k_b) float64 arrays of columns
        self.block_of = -np.ones(self.n, np.int64)  # each unknown's block, or -1
        self.col_of = -np.ones(self.n, np.int64)  # its column in that block

    def __len__(self):
        return sum(b.shape[1] for b in self.blocks)

    def _ensure(self, ids):
        missing = np.unique(ids[self.block_of[ids] < 0])
        if len(missing):
            E = np.zeros((self.n, len(missing)))
            E[missing, np.arange(len(missing))] = 1.0
            self.blocks.append(self.factor.solve(E))
            self.block_of[missing] = len(self.blocks) - 1
            self.col_of[missing] = np.arange(len(missing))

    def _groups(self, ids):
        """Per block holding some of ``ids``: ``(block, positions in ids, columns in the block)``."""
        bo, co = self.block_of[ids], self.col_of[ids]
        if len(self.blocks) == 1:
            return [(self.blocks[0], slice(None), co)]
        out = []
        for b in np.unique(bo):
            sel = np.flatnonzero(bo == b)
            out.append((self.blocks[b], sel, co[sel]))
        return out

    def principal(self, ids) -> np.ndarray:
        """(u,u) ``(M^-1)[ids][:, ids]`` for unknowns ``ids`` (u,) int, solving the columns not kept yet.

        Entry ``[i, j]`` is read from the column of ``ids[i]``, as the rows ``(M^-1 e_(ids[i]))ᵀ`` give it.
        """
        ids = np.asarray(ids, dtype=np.int64)
        self._ensure(ids)
        Zuu = np.empty((len(ids), len(ids)))
        for block, sel, cols in self._groups(ids):
            Zuu[sel] = block[ids][:, cols].T
        return Zuu

    def apply(self, ids, W) -> np.ndarray:
        """``sum_j (M^-1 e_(ids[j])) W[j]``: (n,) for ``W`` (u,), (n, d) for ``W`` (u, d); ``ids`` (u,) int
        distinct unknowns (their columns solved here if not kept yet)."""
        ids = np.asarray(ids, dtype=np.int64)
        self._ensure(ids)
        W = np.asarray(W, dtype=np.float64)
        out = None
        for block, sel, cols in self._groups(ids):
            Wb = W[sel]
            k = block.shape[1]
            if 3 * len(cols) >= k:  # most of the block is used: one product over it, zero weights elsewhere
                full = np.zeros((k,) + W.shape[1:])
                full[cols] = Wb
                term = block @ full
            else:
                term = block[:, cols] @ Wb
            out = term if out is None else out + term
        return out


class LaplacianDeformer:
    """Factor-once solver for the constrained Laplacian deformation energy.

    Parameters
    ----------
    L : (V,V) sparse matrix
        Laplacian (see ``laplacian.py``).
    lambda_reg : float
        Weight of the Laplacian-coordinate term.
    pos_weights : (V,) float array_like or float
        Anchor weight ``w_i`` of every vertex (``lambda_pos``; the paper uses
        0.1, and 1 for vertices that must not move).
    pinned : (V,) bool array_like, optional
        Vertices held exactly at their anchor (Dirichlet); they are removed
        from the unknowns. Pinning everything far from the constraints makes
        the solve local and fast.
    backend : str
        ``SPDFactor`` backend.
    lazy : bool
        Factor ``M`` at its first use instead of now (a :meth:`with_terms` deformer factors its own system, so
        this one may never be needed; a singular ``M`` is then refused at the first solve).
    """

    def __init__(self, L, *, lambda_reg: float = 1.0, pos_weights=0.0, pinned=None, backend: str = "auto",
                 lazy: bool = False):
        L = sp.csr_matrix(L)
        n = L.shape[0]
        self.n = n
        self.lambda_reg = float(lambda_reg)
        if not (np.isfinite(self.lambda_reg) and self.lambda_reg >= 0):
            raise FaceLabError(f"lambda_reg must be a non-negative number, got {lambda_reg!r}; use 1.")
        w = np.broadcast_to(np.asarray(pos_weights, dtype=np.float64), (n,)).copy()
        if not (np.isfinite(w).all() and (w >= 0).all()):
            raise FaceLabError("pos_weights must be non-negative finite numbers; use 0 (no anchoring) or 1.")
        pinned = np.zeros(n, bool) if pinned is None else np.asarray(pinned)
        if pinned.shape != (n,) or pinned.dtype != bool:
            raise FaceLabError(f"pinned must be a ({n},) bool mask, got {pinned.dtype} {pinned.shape}; mark the "
                               "fixed vertices with True.")
        self.pinned = pinned
        self.free = np.flatnonzero(~pinned)
        if len(self.free) == 0:
            raise FaceLabError("Every vertex is fixed, so nothing can move; un-pin the region to deform.")
        self.pinned_idx = np.flatnonzero(pinned)
        self.free_of = -np.ones(n, np.int64)
        self.free_of[self.free] = np.arange(len(self.free))
        Lc = L.tocsc()
        Lf = Lc[:, self.free]
        rows = np.flatnonzero(np.diff(Lf.tocsr().indptr) > 0)  # rows that touch a free vertex
        self._rows = rows
        self._L_rows = L[rows]
        self._Lf = Lf.tocsr()[rows]
        self._Lp = Lc[:, self.pinned_idx].tocsr()[rows]
        self._w_f = w[self.free]
        M = self.lambda_reg * (self._Lf.T @ self._Lf) + sp.diags(self._w_f)
        self._M = M.tocsr()
        self.backend = backend
        self._factor = None
        self._columns = None
        if not lazy:
            self.factor  # noqa: B018  (factored now: a singular system is refused here)

    @property
    def factor(self) -> SPDFactor:
        """The factor of ``M`` (made at the first use with ``lazy``)."""
        if self._factor is None:
            self._factor = SPDFactor(self._M, backend=self.backend)
        return self._factor

    @property
    def columns(self) -> "_ColumnCache":
        """The columns ``M^-1 e_v`` of constrained free vertices, kept between calls."""
        if self._columns is None:
            self._columns = _ColumnCache(self.factor, len(self.free))
        return self._columns

    # ------------------------------------------------------------------ utils
    def with_terms(self, terms, anchor) -> "CoupledDeformer":
        """This energy plus the fixed point-constraint ``terms`` (PointConstraints or a list), factored once.

        ``anchor`` (V,3) gives the positions of pinned members of the terms (moved to their targets' side).
        """
        return CoupledDeformer(self, terms, anchor)

    def _terms(self, C: "PointConstraints", a):
        """Shared set-up of constraints: ``(H (c,3,3), b (c,k), fv (c,k) free ids or -1, q (c,3))``."""
        fv = self.free_of[C.vertices]  # (c,k), -1 for pinned
        b = np.where(fv >= 0, C.bary, 0.0)
        pinned_part = np.einsum("ck,ckd->cd", np.where(fv < 0, C.bary, 0.0), a[C.vertices])
        H = C.strength[:, None, None] * np.einsum("cji,cjk->cik", C.metrics, C.metrics)  # s PᵀP
        return H, b, fv, C.targets - pinned_part

    # ------------------------------------------------------------------ solve
    def solve(self, anchor, reference=None, constraints=None) -> np.ndarray:
        """Minimise the energy.

        Parameters
        ----------
        anchor : (V,3) float array_like
            Anchor positions ``a`` (also the positions of pinned vertices),
            scene units.
        reference : (V,3) float array_like, optional
            Shape whose Laplacian coordinates are preserved,
            ``delta = L @ reference`` (default: ``anchor``).
        constraints : PointConstraints or list of them, optional

        Returns
        -------
        (V,3) ndarray
            New positions, scene units; pinned vertices equal ``anchor``.
        """
        a = np.asarray(anchor, dtype=np.float64)
        if a.shape != (self.n, 3):
            raise FaceLabError(f"Expected {self.n} vertices, got {a.shape[0]}; the mesh topology changed.")
        return self.constrain(self.unconstrained(a, reference), a, constraints)

    def unconstrained(self, anchor, reference=None) -> np.ndarray:
        """(n_free,3) minimiser without point constraints (the part of :meth:`solve` that only depends on the
        anchor and the reference; compute it once when only the constraints change between calls)."""
        a = np.asarray(anchor, dtype=np.float64)
        ref = a if reference is None else np.asarray(reference, dtype=np.float64)
        delta = self._L_rows @ ref
        xp = a[self.pinned_idx]
        B = self.lambda_reg * (self._Lf.T @ (delta - self._Lp @ xp)) + self._w_f[:, None] * a[self.free]
        return self.factor.solve(B)

    def constrain(self, X0, anchor, constraints=None) -> np.ndarray:
        """(V,3) positions: the unconstrained minimiser ``X0`` (:meth:`unconstrained`) with ``constraints`` added
        exactly (Woodbury); pinned vertices at ``anchor``."""
        a = np.asarray(anchor, dtype=np.float64)
        if isinstance(constraints, (list, tuple)):
            constraints = PointConstraints.concat(constraints)
        X = X0
        if constraints is not None and len(constraints):
            X = self._apply_constraints(X0, a, constraints)
        out = a.copy()
        out[self.free] = X
        return out

    def _apply_constraints(self, X0, a, C: PointConstraints):
        H, b, fv, q = self._terms(C, a)  # pinned members moved to the target side
        member = (fv >= 0) & (b != 0)
        used = np.unique(fv[member])
        u = len(used)
        if u == 0:
            return X0
        # a free vertex with a zero weight is not in ``used``: point it at slot 0 (its b is 0, it adds nothing)
        pos = np.searchsorted(used, np.where(member, fv, used[0]))
        Zuu = self.columns.principal(used)  # (u, u) = principal block of M^-1, SPD
        low = _low_rank_rows(H, b, pos, q, 3 * u)
        if low is not None:
            return X0 + self.columns.apply(used, _low_rank_step(low, X0[used], Zuu))
        # Quadratic form in x_U (u*3): Q = sum_c kron(b_c b_cᵀ, H_c), r = sum_c b_c ⊗ H_c q_c
        Q = np.zeros((u, 3, u, 3))
        r = np.zeros((u, 3))
        Hq = np.einsum("cij,cj->ci", H, q)
        k = b.shape[1]
        for i in range(k):
            np.add.at(r, pos[:, i], b[:, i, None] * Hq)
            for j in range(k):
                np.add.at(Q, (pos[:, i], slice(None), pos[:, j]), (b[:, i] * b[:, j])[:, None, None] * H)
        Q2 = Q.reshape(3 * u, 3 * u)
        # Optimality: x_U = x0_U - (Zuu ⊗ I3)(Q x_U - r). Multiplying by (Zuu ⊗ I3)^-1 gives the
        # SPD system ((Zuu^-1 ⊗ I3) + Q) x_U = (Zuu^-1 ⊗ I3) x0_U + r, solved by Cholesky.
        Zc = scipy.linalg.cho_factor(Zuu, lower=True, check_finite=False)
        Zinv = scipy.linalg.cho_solve(Zc, np.eye(u), check_finite=False)
        lhs = Q.copy()
        lhs += Zinv[:, None, :, None] * np.eye(3)[None, :, None, :]
        rhs = (Zinv @ X0[used] + r).reshape(-1)
        xU = scipy.linalg.cho_solve(
            scipy.linalg.cho_factor(lhs.reshape(3 * u, 3 * u), lower=True, overwrite_a=True, check_finite=False),
            rhs,
            check_finite=False,
        )
        G = (Q2 @ xU - r.reshape(-1)).reshape(u, 3)
        return X0 - self.columns.apply(used, G)


class CoupledDeformer:
    """A :class:`LaplacianDeformer`'s energy plus fixed point-constraint terms, factored once.

    The terms (``PointConstraints``; any metrics, e.g. a stiffness along a camera's rays) couple the three
    coordinates, so the system is ``(3 n_free)`` square, unknowns ordered ``3 i + d``: ``M ⊗ I3 + AᵀA`` with
    ``A`` the terms' rows. Moving constraints are added by Woodbury as in the base deformer, with columns
    ``M^-1 e_(v,d)`` per used vertex and coordinate (cached). Made by :meth:`LaplacianDeformer.with_terms`.

    Parameters
    ----------
    base : LaplacianDeformer
    terms : PointConstraints or list of them
    anchor : (V,3) float
        Positions of the pinned vertices, scene units.
    """

    def __init__(self, base: LaplacianDeformer, terms, anchor):
        if isinstance(terms, (list, tuple)):
            terms = PointConstraints.concat(terms)
        a = np.asarray(anchor, dtype=np.float64)
        self.base = base
        nf = len(base.free)
        M3 = sp.kron(base._M, sp.identity(3), format="csr")
        self._g3 = np.zeros(3 * nf)
        if terms is not None and len(terms):
            H, b, fv, q = base._terms(terms, a)
            member = (fv >= 0) & (b != 0)
            low = _low_rank_rows(H, b, np.where(member, fv, 0), q, np.inf)
            if low is not None:
                rows, cols, coef, g, m = low
                A = _rows_matrix(rows, cols, coef, m, nf)
                M3 = M3 + (A.T @ A).tocsr()
                self._g3 = A.T @ g
        self.factor = SPDFactor(M3, backend=base.backend)
        # the columns M^-1 e_(v,d) of constrained unknowns 3 v + d, kept between calls
        self.columns = _ColumnCache(self.factor, 3 * nf)

    def unconstrained(self, anchor, reference=None) -> np.ndarray:
        """(n_free,3) minimiser with the fixed terms and no moving constraints."""
        b = self.base
        a = np.asarray(anchor, dtype=np.float64)
        ref = a if reference is None else np.asarray(reference, dtype=np.float64)
        delta = b._L_rows @ ref
        B = b.lambda_reg * (b._Lf.T @ (delta - b._Lp @ a[b.pinned_idx])) + b._w_f[:, None] * a[b.free]
        return self.factor.solve(B.reshape(-1) + self._g3).reshape(-1, 3)

    def constrain(self, X0, anchor, constraints=None) -> np.ndarray:
        """(V,3): ``X0`` (:meth:`unconstrained`) with ``constraints`` added exactly; pinned vertices at ``anchor``."""
        a = np.asarray(anchor, dtype=np.float64)
        if isinstance(constraints, (list, tuple)):
            constraints = PointConstraints.concat(constraints)
        X = X0
        if constraints is not None and len(constraints):
            H, b, fv, q = self.base._terms(constraints, a)
            member = (fv >= 0) & (b != 0)
            used = np.unique(fv[member])
            if len(used):
                pos = np.searchsorted(used, np.where(member, fv, used[0]))
                low = _low_rank_rows(H, b, pos, q, np.inf)
                if low is not None:
                    rows, cols, coef, g, m = low
                    u3 = (3 * used[:, None] + np.arange(3)).reshape(-1)
                    Zuu = self.columns.principal(u3)  # (3u, 3u)
                    A = _rows_matrix(rows, cols, coef, m, len(used))
                    K = np.eye(m) + A @ np.asarray(A @ Zuu).T
                    y = scipy.linalg.cho_solve(scipy.linalg.cho_factor(K, lower=True, overwrite_a=True,
                                                                       check_finite=False),
                                               g - A @ X0.reshape(-1)[u3], check_finite=False)
                    X = X0 + self.columns.apply(u3, A.T @ y).reshape(-1, 3)
        out = a.copy()
        out[self.base.free] = X
        return out


def _rows_matrix(rows, cols, coef, m: int, n_vertices: int):
    """(m, 3 n_vertices) sparse matrix of constraint rows (:func:`_low_rank_rows`), unknowns ordered ``3 i + d``."""
    c3 = (3 * np.asarray(cols)[:, None] + np.arange(3)).reshape(-1)
    return sp.csr_matrix((coef.reshape(-1), (np.repeat(rows, 3), c3)), shape=(m, 3 * n_vertices))


def _low_rank_rows(H, b, pos, q, n_unknowns: int):
    """The constraint terms as rows ``A x = g`` (``Q = AᵀA``, ``r = Aᵀg``), or None when there are not fewer
    rows than ``n_unknowns``.

    Each ``H_c`` (3x3, PSD) is factored as ``G_cᵀ G_c`` keeping only its non-zero eigenvalues (a ray or a
    pixel constraint has rank 2, a plane rank 1), so the rows are ``m = sum rank(H_c)``. Returns
    ``(rows (m*k,), cols (m*k,), coef (m*k,3), g (m,), m)``: row ``rows[i]`` has ``coef[i]`` on used vertex
    ``cols[i]``.
    """
    lam, U = np.linalg.eigh(H)  # ascending; (c,3), (c,3,3) eigenvectors in columns
    keep = lam > 1e-12 * np.maximum(lam[:, -1:], 1e-300)
    ci, ji = np.nonzero(keep)
    m = len(ci)
    if m >= n_unknowns or m == 0:
        return None
    G = np.sqrt(lam[ci, ji])[:, None] * U[ci, :, ji]  # (m,3)
    g = np.einsum("md,md->m", G, q[ci])
    k = b.shape[1]
    rows = np.repeat(np.arange(m), k)
    cols = pos[ci].reshape(-1)
    coef = b[ci].reshape(-1)[:, None] * np.repeat(G, k, axis=0)  # (m*k,3)
    return rows, cols, coef, g, m


def _low_rank_step(low, x0, Zuu) -> np.ndarray:
    """``Aᵀ y`` (u,3) with ``y = K⁻¹ (g - A x0)``, ``K = I + A (Zuu ⊗ I3) Aᵀ`` (m x m, SPD).

    The Woodbury identity on the constraint rows instead of the used vertices: with
    ``Q = AᵀA`` and ``r = Aᵀg`` the constrained free vertices are ``X0 + Zᵀ Aᵀ y``, the same minimiser as the
    (3u x 3u) system in ``_apply_constraints`` at the cost of an (m x m) one.
    """
    rows, cols, coef, g, m = low
    u = len(Zuu)
    K = np.eye(m)
    Ax0 = np.zeros(m)
    A = [sp.csr_matrix((coef[:, d], (rows, cols)), shape=(m, u)) for d in range(3)]
    for d in range(3):
        Ax0 += A[d] @ x0[:, d]
        K += A[d] @ np.asarray(A[d] @ Zuu).T  # A_d Zuu A_dᵀ (Zuu symmetric)
    y = scipy.linalg.cho_solve(scipy.linalg.cho_factor(K, lower=True, overwrite_a=True, check_finite=False),
                               g - Ax0, check_finite=False)
    return np.stack([A[d].T @ y for d in range(3)], axis=1)
