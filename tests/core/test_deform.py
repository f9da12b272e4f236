import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.geometry.deform import LaplacianDeformer, PointConstraints
from facelab_addon.core.geometry.laplacian import cotangent_laplacian, uniform_laplacian

from .test_laplacian import grid


def dense_reference(L, lam, w, pinned, anchor, ref, C):
    """Minimise the same energy by forming the full dense 3n system."""
    N = len(anchor)
    Ld = L.toarray()
    A = lam * np.kron(Ld.T @ Ld, np.eye(3)) + np.kron(np.diag(w), np.eye(3))
    b = lam * np.kron(Ld.T, np.eye(3)) @ (np.kron(Ld, np.eye(3)) @ ref.ravel()) + np.kron(np.diag(w), np.eye(3)) @ anchor.ravel()
    for c in range(len(C)):
        S = np.zeros((3, 3 * N))
        for v, bb in zip(C.vertices[c], C.bary[c]):
            S[:, 3 * v : 3 * v + 3] += bb * np.eye(3)
        H = C.strength[c] * C.metrics[c].T @ C.metrics[c]
        A += S.T @ H @ S
        b += S.T @ H @ C.targets[c]
    free = np.repeat(~pinned, 3)
    x = anchor.ravel().copy()
    x[free] = np.linalg.solve(A[np.ix_(free, free)], b[free] - A[np.ix_(free, ~free)] @ x[~free])
    return x.reshape(-1, 3)


@pytest.mark.parametrize("kind", ["uniform", "cotangent"])
def test_woodbury_solver_matches_dense_minimiser(kind):
    rng = np.random.default_rng(0)
    V, F, _ = grid(8, jitter=0.2)
    V[:, 2] = 0.1 * np.sin(V[:, 0])
    L = uniform_laplacian(F, len(V)) if kind == "uniform" else cotangent_laplacian(V, F)
    w = rng.uniform(0.05, 1, len(V))
    pinned = np.zeros(len(V), bool)
    pinned[:5] = True
    anchor = V + 0.05 * rng.standard_normal(V.shape)
    C = PointConstraints.concat(
        [
            PointConstraints.rays([10, 20, 20, 33], rng.standard_normal((4, 3)), rng.standard_normal((4, 3)), [1, 2, 3, 1]),
            PointConstraints.points([[40, 41, 49]], [[1, 2, 3]], 0.7, bary=[[0.2, 0.3, 0.5]]),
            PointConstraints.points([[2, 41, 49]], [[1, 2, 0]], 0.7, bary=[[0.2, 0.3, 0.5]]),  # touches a pinned vertex
        ]
    )
    D = LaplacianDeformer(L, lambda_reg=3.0, pos_weights=w, pinned=pinned)
    X = D.solve(anchor, V, C)
    np.testing.assert_allclose(X, dense_reference(L, 3.0, w, pinned, anchor, V, C), atol=1e-10)
    np.testing.assert_array_equal(X[pinned], anchor[pinned])
    # a second solve reuses cached columns and still agrees
    X2 = D.solve(anchor, V, [C])
    np.testing.assert_allclose(X2, X, atol=1e-12)


def test_no_constraints_returns_anchor_and_rigid_motion_is_free():
    V, F, _ = grid(6)
    L = uniform_laplacian(F, len(V))
    D = LaplacianDeformer(L, lambda_reg=3.0, pos_weights=0.1)
    np.testing.assert_allclose(D.solve(V), V, atol=1e-12)
    # anchors translated, reference unchanged: translation keeps Laplacian coordinates -> exact
    np.testing.assert_allclose(D.solve(V + [1, 2, 3], reference=V), V + [1, 2, 3], atol=1e-10)


def test_hard_point_constraint_is_met_with_large_weight():
    V, F, _ = grid(6)
    D = LaplacianDeformer(uniform_laplacian(F, len(V)), lambda_reg=1.0, pos_weights=0.1)
    X = D.solve(V, constraints=PointConstraints.points([14], [[2.0, 2.0, 1.0]], strength=1e8))
    np.testing.assert_allclose(X[14], [2, 2, 1], atol=1e-6)
    assert X[0, 2] < 0.2  # decays away from the handle


def test_ray_constraint_allows_sliding_along_the_ray():
    V, F, _ = grid(6)
    D = LaplacianDeformer(uniform_laplacian(F, len(V)), lambda_reg=1.0, pos_weights=0.1)
    # ray through the vertex itself, along z: already satisfied -> nothing moves
    X = D.solve(V, constraints=PointConstraints.rays([14], V[[14]] + [0, 0, 5], [[0, 0, 1]], strength=100))
    np.testing.assert_allclose(X, V, atol=1e-12)


def test_everything_pinned_is_an_error():
    V, F, _ = grid(4)
    with pytest.raises(FaceLabError, match="fixed"):
        LaplacianDeformer(uniform_laplacian(F, len(V)), pinned=np.ones(len(V), bool))


def test_zero_weight_member_that_is_the_largest_free_vertex_is_ignored():
    """A contour point at an edge's end has a zero weight on the other end; when that vertex is free, in no
    other row, and above every used vertex, it used to index past the used-vertex list."""
    rng = np.random.default_rng(1)
    V, F, _ = grid(6)
    L = uniform_laplacian(F, len(V))
    w = rng.uniform(0.1, 1, len(V))
    pinned = np.zeros(len(V), bool)
    pinned[:3] = True
    targets, bary = [[1.0, 2.0, 0.5], [2.0, 1.0, 0.2]], [[1.0, 0.0], [0.4, 0.6]]
    C = PointConstraints.points([[14, 35], [15, 16]], targets, 5.0, bary=bary)
    D = LaplacianDeformer(L, lambda_reg=2.0, pos_weights=w, pinned=pinned)
    X = D.solve(V, V, C)
    np.testing.assert_allclose(X, dense_reference(L, 2.0, w, pinned, V, V, C), atol=1e-10)
    same = PointConstraints.points([[14, 14], [15, 16]], targets, 5.0, bary=bary)
    np.testing.assert_allclose(X, D.solve(V, V, same), atol=1e-12)  # vertex 35 carries no weight
    assert np.linalg.norm(X[14] - V[14]) > 0.1


def test_constraint_rows_and_vertex_systems_give_the_same_minimiser(monkeypatch):
    """Few rank-2 constraints on many vertices take the (m x m) system on the constraint rows; many
    constraints on few vertices the (3u x 3u) one. Both are the same minimiser (and the dense one)."""
    import facelab_addon.core.geometry.deform as deform

    rng = np.random.default_rng(3)
    V, F, _ = grid(9, jitter=0.2)
    V[:, 2] = 0.1 * np.cos(V[:, 1])
    L = cotangent_laplacian(V, F)
    w = rng.uniform(0.05, 1, len(V))
    pinned = np.zeros(len(V), bool)
    pinned[:4] = True
    tri = rng.integers(0, len(V), (12, 3))
    d = rng.standard_normal((12, 3))
    C = PointConstraints.concat([
        PointConstraints.rays(tri[:, 0], V[tri[:, 0]] + rng.standard_normal((12, 3)), d, rng.uniform(1, 5, 12)),
        PointConstraints.points(tri, V[tri[:, 0]] + 0.1, 2.0, bary=rng.dirichlet([1, 1, 1], 12)),
    ])
    D = LaplacianDeformer(L, lambda_reg=2.0, pos_weights=w, pinned=pinned)
    calls = []
    real = deform._low_rank_rows
    monkeypatch.setattr(deform, "_low_rank_rows", lambda *a: calls.append(real(*a)) or calls[-1])
    X_rows = D.solve(V, V, C)
    assert calls[-1] is not None  # 12*2 + 12*3 rows < 3 * (about 48) unknowns
    monkeypatch.setattr(deform, "_low_rank_rows", lambda *a: None)
    X_vertices = D.solve(V, V, C)
    np.testing.assert_allclose(X_rows, X_vertices, atol=1e-10)
    np.testing.assert_allclose(X_rows, dense_reference(L, 2.0, w, pinned, V, V, C), atol=1e-10)


def _coupled_case(seed):
    """A bent 8x8 grid: ``(rng, V, L (uniform), w, pinned (first 5), anchor, r (V,3) unit directions)``."""
    rng = np.random.default_rng(seed)
    V, F, _ = grid(8, jitter=0.2)
    V[:, 2] = 0.1 * np.sin(V[:, 0])
    L = uniform_laplacian(F, len(V))
    w = rng.uniform(0.05, 1, len(V))
    pinned = np.zeros(len(V), bool)
    pinned[:5] = True
    anchor = V + 0.05 * rng.standard_normal(V.shape)
    r = rng.standard_normal((len(V), 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    return rng, V, L, w, pinned, anchor, r


def test_coupled_deformer_with_fixed_anisotropic_terms_matches_dense_minimiser():
    """Fixed terms that couple the coordinates (rank-1 stiffness along rays, on single vertices and on
    Laplacian-like rows touching pinned vertices) folded into the factor, moving constraints added by
    Woodbury: the same minimiser as the dense 3n system with every term in it."""
    rng, V, L, w, pinned, anchor, r = _coupled_case(1)
    fixed_terms = PointConstraints.concat([
        PointConstraints(np.arange(len(V)), np.ones((len(V), 1)), anchor, r[:, :, None] * r[:, None, :], 2.0),
        PointConstraints([[1, 6, 7], [30, 31, 39]], [[1.0, -0.5, -0.5], [1.0, -0.5, -0.5]], np.zeros((2, 3)),
                         r[[6, 30], :, None] * r[[6, 30], None, :], 5.0),  # the first touches pinned vertex 1
    ])
    moving = [PointConstraints.rays([10, 20, 33], rng.standard_normal((3, 3)), rng.standard_normal((3, 3)), [1, 2, 3]),
              PointConstraints.points([[40, 41, 49]], [[1, 2, 3]], 0.7, bary=[[0.2, 0.3, 0.5]])]
    D = LaplacianDeformer(L, lambda_reg=3.0, pos_weights=w, pinned=pinned)
    Dc = D.with_terms(fixed_terms, anchor)
    X0 = Dc.unconstrained(anchor, V)
    for cons in (moving, moving[:1]):  # the second call reuses cached columns
        X = Dc.constrain(X0, anchor, cons)
        ref = dense_reference(L, 3.0, w, pinned, anchor, V, PointConstraints.concat([fixed_terms] + cons))
        np.testing.assert_allclose(X, ref, atol=1e-10)
    np.testing.assert_allclose(Dc.constrain(X0, anchor), dense_reference(L, 3.0, w, pinned, anchor, V, fixed_terms),
                               atol=1e-10)
    # the terms change the result (the test can fail): without them the base deformer's minimiser differs
    assert np.abs(D.solve(anchor, V, moving) - Dc.constrain(X0, anchor, moving)).max() > 1e-3


def test_a_lazy_deformer_factors_at_first_use_and_solves_the_same():
    """``lazy=True``: no factor until a solve needs one (a coupled deformer made from it factors only its own
    system), then the very same minimiser as the eager deformer; a singular system is refused at that solve."""
    rng, V, L, w, pinned, anchor, r = _coupled_case(2)
    terms = PointConstraints(np.arange(len(V)), np.ones((len(V), 1)), anchor, r[:, :, None] * r[:, None, :], 2.0)
    moving = [PointConstraints.rays([10, 20, 33], rng.standard_normal((3, 3)), rng.standard_normal((3, 3)), [1, 2, 3])]
    eager = LaplacianDeformer(L, lambda_reg=3.0, pos_weights=w, pinned=pinned)
    lazy = LaplacianDeformer(L, lambda_reg=3.0, pos_weights=w, pinned=pinned, lazy=True)
    assert eager._factor is not None and lazy._factor is None
    Xc = lazy.with_terms(terms, anchor)
    Yc = Xc.constrain(Xc.unconstrained(anchor, V), anchor, moving)
    assert lazy._factor is None  # the coupled solve never needed the base factor
    Ye = eager.with_terms(terms, anchor)
    assert np.array_equal(Yc, Ye.constrain(Ye.unconstrained(anchor, V), anchor, moving))
    assert np.array_equal(lazy.solve(anchor, V, moving), eager.solve(anchor, V, moving))
    assert lazy._factor is not None
    with pytest.raises(FaceLabError, match="singular"):
        LaplacianDeformer(L, lambda_reg=0.0, pos_weights=0.0)  # eager: refused when made
    free_floating = LaplacianDeformer(L, lambda_reg=0.0, pos_weights=0.0, lazy=True)
    with pytest.raises(FaceLabError, match="singular"):
        free_floating.solve(anchor)  # lazy: refused at the first solve


def sparse_reference(L, lam, w, pinned, anchor, ref, C):
    """Minimise the same energy by a direct sparse solve of the full constrained 3n system (scipy spsolve)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    N = len(anchor)
    I3 = sp.identity(3)
    A = lam * sp.kron(L.T @ L, I3) + sp.kron(sp.diags(w), I3)
    b = lam * (sp.kron(L.T @ L, I3) @ ref.ravel()) + sp.kron(sp.diags(w), I3) @ anchor.ravel()
    rows, cols, vals = [], [], []
    for c in range(len(C)):
        # S (3, 3N) picks the constrained surface point; H = s P^T P
        S = sp.csr_matrix((np.repeat(C.bary[c], 3), (np.tile(np.arange(3), C.vertices.shape[1]),
                                                     (3 * C.vertices[c][:, None] + np.arange(3)).ravel())),
                          shape=(3, 3 * N))
        H = C.strength[c] * C.metrics[c].T @ C.metrics[c]
        T = (S.T @ sp.csr_matrix(H) @ S).tocoo()
        rows.append(T.row), cols.append(T.col), vals.append(T.data)
        b += S.T @ (H @ C.targets[c])
    A = (A + sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(3 * N, 3 * N))).tocsc()
    free = np.flatnonzero(np.repeat(~pinned, 3))
    held = np.flatnonzero(np.repeat(pinned, 3))
    x = anchor.ravel().copy()
    x[free] = spla.spsolve(A[free][:, free], b[free] - A[free][:, held] @ x[held])
    return x.reshape(-1, 3)


def test_kept_columns_grow_in_blocks_and_solves_match_a_direct_sparse_solve():
    """Constraint sets that move from vertex to vertex, as the silhouettes do between solves: each solve adds
    the columns it lacks as a new block (the kept ones are not copied) and reads only the part it uses; every
    result, of the base and of the coupled deformer, is the direct sparse solve's."""
    rng = np.random.default_rng(5)
    V, F, _ = grid(10, jitter=0.2)
    V[:, 2] = 0.1 * np.sin(V[:, 0] + V[:, 1])
    L = cotangent_laplacian(V, F)
    w = rng.uniform(0.05, 1, len(V))
    pinned = np.zeros(len(V), bool)
    pinned[:6] = True
    anchor = V + 0.03 * rng.standard_normal(V.shape)

    def rays(vs):
        vs = np.asarray(vs)
        return PointConstraints.rays(vs, V[vs] + 0.2 * rng.standard_normal((len(vs), 3)),
                                     rng.standard_normal((len(vs), 3)), rng.uniform(1, 4, len(vs)))

    first = np.arange(20, 60, 2)  # 20 vertices
    sets = [
        [rays(first)],
        [rays(np.r_[first[:15], 61, 63, 65, 67, 69])],  # 15 kept, 5 new: a second block
        [rays(first[:3]), PointConstraints.points([[70, 71, 81]], [[0.5, 0.5, 0.1]], 2.0, bary=[[0.2, 0.3, 0.5]])],
        [rays(np.r_[first[::2], 61, 65])],  # across both blocks
    ]
    D = LaplacianDeformer(L, lambda_reg=3.0, pos_weights=w, pinned=pinned)
    r = rng.standard_normal((len(V), 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    terms = PointConstraints(np.arange(len(V)), np.ones((len(V), 1)), anchor, r[:, :, None] * r[:, None, :], 2.0)
    Dc = D.with_terms(terms, anchor)
    X0 = Dc.unconstrained(anchor, V)
    blocks, blocks_c = [], []
    for cons in sets:
        C = PointConstraints.concat(cons)
        X = D.solve(anchor, V, cons)
        np.testing.assert_allclose(X, sparse_reference(L, 3.0, w, pinned, anchor, V, C), rtol=0, atol=1e-10)
        Xc = Dc.constrain(X0, anchor, cons)
        ref_c = sparse_reference(L, 3.0, w, pinned, anchor, V, PointConstraints.concat([terms, C]))
        np.testing.assert_allclose(Xc, ref_c, rtol=0, atol=1e-10)
        assert np.abs(X - anchor).max() > 1e-2  # the constraints move the mesh: the comparison can fail
        # the blocks kept so far are the same arrays (grown by appending, never re-copied)
        assert all(a is b for a, b in zip(blocks, D.columns.blocks))
        assert all(a is b for a, b in zip(blocks_c, Dc.columns.blocks))
        blocks, blocks_c = list(D.columns.blocks), list(Dc.columns.blocks)
    used = np.unique(np.concatenate([PointConstraints.concat(c).vertices[PointConstraints.concat(c).bary != 0]
                                     for c in sets]))
    assert not pinned[used].any()
    assert len(D.columns) == len(used) and len(D.columns.blocks) == 3  # each column solved once
    assert len(Dc.columns) == 3 * len(used)
