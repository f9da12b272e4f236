"""Regression propagation of lip corrections (Dinev et al. 2018 §4)."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from facelab_addon.core.errors import FaceLabError, MeshError, RegionError
from facelab_addon.core.geometry.gradients import deformation_gradients
from facelab_addon.core.geometry.laplacian import poisson_operator
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regions import faces_in_region, region_border
from facelab_addon.core.lips.suggest import suggest_frames

NX, NY = 24, 16
LIP_ROWS = (6, 9)  # lip region: rows 6..9, border rows 6 and 9


def grid(bumpy=False):
    from facelab_addon.testing.meshes import grid_mesh

    z = (lambda x, y: 0.8 * np.sin(0.3 * x) * np.cos(0.25 * y)) if bumpy else None
    V, F = grid_mesh(np.arange(NX, dtype=float), np.arange(NY, dtype=float), z)
    y = V[:, 1]
    lips = (y >= LIP_ROWS[0]) & (y <= LIP_ROWS[1])
    mouth = (y <= LIP_ROWS[0]) | (y >= LIP_ROWS[1])
    return V, F, faces_in_region(F, mouth), faces_in_region(F, lips)


def row_shift(V, f):
    """x += f(y): on this grid every triangle keeps its area, so gradients are linear in f."""
    out = V.copy()
    out[:, 0] += f(V[:, 1])
    return out


fA = lambda y: 0.3 * np.sin(0.4 * y)  # noqa: E731
fB = lambda y: 0.2 * (y / NY) ** 2 + 0.05 * y  # noqa: E731
fD = lambda y: 0.25 * np.cos(0.7 * y)  # noqa: E731  (not in span{fA, fB})


def lip_bump(V):
    """A capture error on the interior lip rows (z bump), zero on the border rows."""
    e = np.zeros_like(V)
    inner = (V[:, 1] > LIP_ROWS[0]) & (V[:, 1] < LIP_ROWS[1])
    e[inner, 2] = 0.3 * np.sin(np.pi * V[inner, 0] / (NX - 1))
    return e


def smooth_random_deformation(V, seed):
    rng = np.random.default_rng(seed)
    c = rng.standard_normal((4, 3)) * 0.3
    x, y = V[:, 0] / NX, V[:, 1] / NY
    basis = np.stack([np.sin(3 * x + 1), np.cos(2 * y), x * y, np.sin(2 * x) * np.cos(3 * y)], 1)
    return V + basis @ c


def f32_tol(reg):
    """What ``predict``'s float32 arithmetic may move a vertex: 1e-7 of the mouth's size.

    ``predict`` evaluates the fitted linear maps in float32 on changes from the rest pose and adds the rest's
    prediction in float64, so its rounding is relative to the mouth, not to the coordinates: measured up to
    1e-8 of the mouth's size here and 2.2e-5 mm on the 105k-vertex ICT face (``benchmarks/scale.py``).
    The bound, 5 nm on a 5 cm mouth, is 2,000x below the 0.01 mm storage tolerance yet far below any
    modelling error these tests look for (>= 1e-3 of the mouth). Float64 paths are still compared exactly.
    """
    return 1e-7 * reg.mouth_size


# ---------------------------------------------------------------- Poisson


def test_poisson_solve_from_own_gradients_reproduces_the_mesh():
    V, F, _, lips = grid(bumpy=True)
    D = smooth_random_deformation(V, 1)
    G = deformation_gradients(V, D, F[lips])
    L, Div = poisson_operator(V, F, lips)
    border = region_border(F, lips, len(V))
    inner = np.setdiff1d(np.unique(F[lips]), border)
    rhs = Div[inner] @ G.transpose(0, 2, 1).reshape(-1, 3) - L[inner][:, border] @ D[border]
    X = np.column_stack([spla.spsolve(L[inner][:, inner].tocsc(), rhs[:, c]) for c in range(3)])
    np.testing.assert_allclose(X, D[inner], atol=1e-10)
    # L is the cotangent Laplacian of the region: L @ rest = div of identity gradients, and L 1 = 0
    assert np.abs(L @ np.ones(len(V))).max() < 1e-12


def test_training_frames_are_reproduced_exactly_and_outside_is_untouched():
    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(3)])
    reg = LipRegressor(V, F, mouth, lips).fit(train)
    cap = train + np.stack([lip_bump(V)] * 3)
    out = reg.predict(cap)
    np.testing.assert_allclose(out, train, atol=f32_tol(reg))
    assert np.abs(out - cap).max() > 0.1  # the capture error was really removed
    # vertices outside the interior lip vertices are returned bit-for-bit, border included
    keep = np.setdiff1d(np.arange(len(V)), reg.interior_vertices)
    assert np.array_equal(out[:, keep], cap[:, keep])
    assert set(reg.border_vertices.tolist()) == set(np.flatnonzero(np.isin(V[:, 1], LIP_ROWS)).tolist())
    np.testing.assert_allclose(reg.extrapolation(train), 0.0, atol=1e-9)


@pytest.mark.parametrize(
    "kwargs, a, b",
    [({}, 0.3, 0.6), ({"patches": 1}, 0.3, 0.6), ({"patches": 1, "center": None}, 0.4, 0.6)],
    ids=["local-patches", "global", "paper-uncentred"],
)
def test_regression_is_exact_in_the_span_of_the_training_frames(kwargs, a, b):
    V, F, mouth, lips = grid()
    reg = LipRegressor(V, F, mouth, lips, **kwargs).fit([row_shift(V, fA), row_shift(V, fB)])
    # the uncentred paper model spans affine combinations (a + b = 1); the rest-centred one any
    truth = row_shift(V, lambda y: a * fA(y) + b * fB(y))
    cap = truth + lip_bump(V)
    np.testing.assert_allclose(reg.predict(cap)[0], truth, atol=f32_tol(reg))
    np.testing.assert_allclose(reg.predict_lip_gradients(cap)[0], deformation_gradients(V, truth, F[lips]), atol=1e-9)
    assert reg.extrapolation(cap)[0] < 1e-9
    # a frame outside the span is not reproduced (the test above can fail)
    other = row_shift(V, fD)
    assert np.abs(reg.predict(other + lip_bump(V))[0] - other).max() > 1e-3
    assert reg.extrapolation(other)[0] > 0.05


def test_extrapolation_is_scale_free_and_grows_outside_the_span():
    V, F, mouth, lips = grid()
    frames = [row_shift(V, fA), row_shift(V, fB)]
    e = []
    for s in (1.0, 100.0):
        reg = LipRegressor(V * s, F, mouth, lips).fit(np.stack(frames) * s)
        e.append(reg.extrapolation(np.stack([frames[0], row_shift(V, fD), row_shift(V, lambda y: 2 * fD(y))]) * s))
    np.testing.assert_allclose(e[0], e[1], rtol=1e-6, atol=1e-12)
    assert e[0][0] < 1e-9 and 0 < e[0][1] < e[0][2]


def test_incremental_add_equals_refit():
    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(4)])
    test = np.stack([smooth_random_deformation(V, s) for s in (10, 11)]) + lip_bump(V)
    full = LipRegressor(V, F, mouth, lips).fit(train)
    inc = LipRegressor(V, F, mouth, lips).fit(train[:1])
    inc.add(train[1]).add(train[2:])
    assert inc.k == full.k == 4
    np.testing.assert_allclose(inc.predict(test), full.predict(test), atol=1e-10)
    np.testing.assert_allclose(inc.extrapolation(test), full.extrapolation(test), atol=1e-10)
    # add() on an empty regressor is fit()
    np.testing.assert_allclose(LipRegressor(V, F, mouth, lips).add(train).predict(test), full.predict(test), atol=1e-10)


def test_chunks_in_place_and_solver_backends_agree():
    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(3)])
    cap = np.stack([smooth_random_deformation(V, s) + lip_bump(V) for s in range(5, 10)])
    reg = LipRegressor(V, F, mouth, lips).fit(train)
    ref = reg.predict(cap)
    np.testing.assert_allclose(reg.predict(cap, chunk=2), ref, atol=f32_tol(reg))  # other float32 rounding
    buf = cap.copy()
    assert reg.predict(buf, out=buf) is buf
    np.testing.assert_allclose(buf, ref, atol=f32_tol(reg))
    lu = LipRegressor(V, F, mouth, lips, backend="splu").fit(train)
    np.testing.assert_allclose(lu.predict(cap), ref, atol=f32_tol(reg))
    assert reg.predict(cap[0]).shape == (1,) + V.shape
    # ridge="loo" fits with the ridge it picks: the fixed-ridge fit with that value predicts the same
    loo = LipRegressor(V, F, mouth, lips, ridge="loo", patches=1).fit(train)
    (lam,) = loo.ridges_used
    assert lam > 0  # measured 1e-3: the leave-one-out error picks a ridge here, not the default 0
    np.testing.assert_allclose(loo.predict(cap), LipRegressor(V, F, mouth, lips, ridge=lam, patches=1)
                               .fit(train).predict(cap), atol=f32_tol(reg))


def test_suggest_frames_picks_extreme_and_new_poses():
    V, F, mouth, lips = grid()
    seq = np.stack([row_shift(V, lambda y, w=w: w * fA(y)) for w in (0.1, 0.2, 0.3, 0.4, 0.5)]
                   + [row_shift(V, lambda y, w=w: w * fB(y)) for w in (0.1, 0.2, 0.3)])
    kw = dict(rest_vertices=V, faces=F, mouth_faces=mouth)
    # most extreme pose first, then the largest pose outside its span; nothing else is new
    np.testing.assert_array_equal(suggest_frames(seq, 3, **kw), [4, 7])
    np.testing.assert_array_equal(suggest_frames(seq, 1, exclude=[4], **kw), [7])
    reg = LipRegressor(V, F, mouth, lips).fit(seq[4])
    np.testing.assert_array_equal(suggest_frames(seq, 1, regressor=reg), [7])
    assert np.argmax(reg.extrapolation(seq)) == 7
    with pytest.raises(FaceLabError, match="rest_vertices, faces and mouth_faces"):
        suggest_frames(seq, 1)


def test_errors_name_the_problem_and_the_fix():
    V, F, mouth, lips = grid()
    reg = LipRegressor(V, F, mouth, lips)
    with pytest.raises(FaceLabError, match="call fit"):
        reg.predict(V)
    with pytest.raises(FaceLabError, match="at least one frame"):
        reg.fit(np.zeros((0,) + V.shape))
    with pytest.raises(MeshError, match="topology differs"):
        reg.fit(V[None, :-1])
    bad = V.copy()
    bad[F[lips[0], 0], 2] = np.nan
    with pytest.raises(MeshError, match="NaN.*frames \\[1\\]"):
        reg.fit(np.stack([V, bad]))
    reg.fit(row_shift(V, fA)[None])
    with pytest.raises(MeshError, match="topology differs"):
        reg.predict(np.zeros((2, len(V) + 1, 3)))
    with pytest.raises(RegionError, match="inner-lip region is empty"):
        LipRegressor(V, F, mouth, [])
    with pytest.raises(RegionError, match="overlap"):
        LipRegressor(V, F, mouth, np.r_[lips, mouth[:3]])
    tet_v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) + 50.0
    tet_f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]) + len(V)
    with pytest.raises(RegionError, match="no border"):  # the lip region is a whole closed piece
        LipRegressor(np.r_[V, tet_v], np.r_[F, tet_f], mouth, np.arange(len(F), len(F) + 4))
    degen = V.copy()
    degen[F[lips[5], 1]] = degen[F[lips[5], 0]]
    with pytest.raises(MeshError, match="degenerate"):
        LipRegressor(degen, F, mouth, lips)


# ---------------------------------------------------------------- ICT-FaceKit


@pytest.fixture(scope="module")
def ict_regions(ict):
    """The ICT model and its Auto Regions: (model, mouth faces, lip faces, lip vertex mask)."""
    from facelab_addon.core.lips import regions

    mouth, lip = regions.auto_regions(ict.neutral, ict.faces)
    return ict, faces_in_region(ict.faces, mouth), faces_in_region(ict.faces, lip), lip


def test_ict_blend_of_training_poses_is_corrected(ict_regions):
    m, mf, lf, lip = ict_regions
    poses = [{"jawOpen": 0.4}, {"mouthSmile_L": 0.6, "mouthSmile_R": 0.6}, {"mouthPucker": 0.5},
             {"mouthPress_L": 0.5, "mouthPress_R": 0.5}]
    train = np.stack([m.pose(p) for p in poses])
    reg = LipRegressor(m.neutral, m.faces, mf, lf).fit(train)
    truth = m.pose({"jawOpen": 0.2, "mouthSmile_L": 0.3, "mouthSmile_R": 0.3})  # in span up to gradient nonlinearity
    err = np.zeros_like(truth)
    err[lip, 1] = 0.1 * np.sign(truth[lip, 1] - truth[lip, 1].mean())  # lips pulled 1 mm apart
    inner = np.setdiff1d(np.flatnonzero(lip), reg.border_vertices)
    err[np.setdiff1d(np.arange(len(truth)), inner)] = 0.0
    out = reg.predict(truth + err)[0]
    rms = lambda d: np.sqrt(np.mean(np.sum(d[lip] ** 2, axis=1)))  # noqa: E731
    assert rms(out - truth) < 0.03 * rms(err)
    e = reg.extrapolation(np.stack([truth, m.pose({"mouthFunnel": 0.6})]))
    assert e[0] < 0.1 < e[1]


# ---------------------------------------------------------------- dtype, in place, shared features


def _sequence(V, n, seed=5):
    return np.stack([smooth_random_deformation(V, seed + s) + lip_bump(V) for s in range(n)])


def test_float32_frames_are_read_without_upcasting_and_match_float64():
    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips).fit(np.stack([smooth_random_deformation(V, s) for s in range(3)]))
    cap32 = _sequence(V, 6).astype(np.float32)
    cap64 = cap32.astype(np.float64)  # the same positions
    ref = reg.predict(cap64, chunk=4)
    out = reg.predict(cap32, chunk=4)
    assert out.dtype == np.float64 and out.shape == cap32.shape
    # the same positions in either dtype give the same result: the changes from the rest are formed in float64
    np.testing.assert_array_equal(out, ref)
    # predict's float32 arithmetic against the float64 maps (lip_corrections) is a bound, not equality: float32
    # keeps 24 bits of each change from the rest pose, about 1e-8 of the mouth's size (f32_tol). The bound is
    # relative to the mouth, so it holds the same in another unit and far from the origin.
    for scale, shift in ((1.0, 0.0), (1000.0, 5e4)):  # e.g. millimetres, 50 m from the origin
        r = reg if scale == 1.0 else LipRegressor(V * scale + shift, F, mouth, lips).fit(
            np.stack([smooth_random_deformation(V, s) * scale + shift for s in range(3)]))
        c = cap64 * scale + shift
        f64 = c[:, r.interior_vertices] + r.lip_corrections(c)
        err = np.abs(r.predict(c)[:, r.interior_vertices] - f64).max()
        assert err <= f32_tol(r), (scale, err / r.mouth_size)
        assert np.abs(f64 - c[:, r.interior_vertices]).max() > 1e3 * f32_tol(r)  # a real correction
    # against the float64 originals: equal up to float32 rounding of the input
    np.testing.assert_allclose(reg.predict(_sequence(V, 6)), ref, rtol=0, atol=1e-5)
    np.testing.assert_allclose(reg.extrapolation(cap32), reg.extrapolation(cap64), rtol=0, atol=1e-12)
    np.testing.assert_allclose(reg.predict_lip_gradients(cap32), reg.predict_lip_gradients(cap64), atol=1e-12)
    # NaNs are still found, block by block, in the region actually read
    long = np.repeat(cap32[:1], 150, axis=0)
    long[[3, 140], F[lips[0], 0], 1] = np.nan
    with pytest.raises(MeshError, match="NaN.*frames \\[3, 140\\]"):
        reg.predict(long)
    # out given as another view of the input's buffer is in place too
    long = np.ascontiguousarray(cap32)
    res = reg.predict(long[1:4], out=long[1:4])
    np.testing.assert_allclose(long[1:4], out[1:4], rtol=0, atol=1e-5)
    assert np.shares_memory(res, long)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_predict_in_place_writes_only_the_interior_lip_vertices(dtype):
    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips).fit(np.stack([smooth_random_deformation(V, s) for s in range(3)]))
    cap = _sequence(V, 5).astype(dtype)
    orig = cap.copy()
    ref = reg.predict(orig)
    res = reg.predict(cap, out=cap, chunk=2)
    assert res is cap and res.dtype == dtype
    keep = np.setdiff1d(np.arange(len(V)), reg.interior_vertices)
    assert np.array_equal(cap[:, keep], orig[:, keep])  # untouched, border and mouth included
    # float32 frames: the written positions are rounded to float32 as well (half a unit in the last place)
    np.testing.assert_allclose(cap, ref, rtol=0, atol=f32_tol(reg) + (1e-6 if dtype == np.float32 else 0))
    assert np.abs(cap[:, reg.interior_vertices] - orig[:, reg.interior_vertices]).max() > 1e-3
    # another array as out receives the whole result, in its own dtype
    buf = np.zeros(orig.shape, np.float64)
    assert reg.predict(orig, out=buf) is buf
    np.testing.assert_allclose(buf, ref, atol=f32_tol(reg))
    with pytest.raises(FaceLabError, match="out has shape"):
        reg.predict(orig, out=buf[:2])


def test_mouth_features_are_shared_by_extrapolation_and_suggest_frames():
    V, F, mouth, lips = grid()
    seq = np.stack([row_shift(V, lambda y, w=w: w * fA(y)) for w in (0.1, 0.2, 0.3, 0.4, 0.5)]
                   + [row_shift(V, lambda y, w=w: w * fB(y)) for w in (0.1, 0.2, 0.3)]
                   + [row_shift(V, lambda y, w=w: w * fD(y) + 0.1 * fA(y)) for w in (0.2, 0.1)])
    reg = LipRegressor(V, F, mouth, lips).fit(seq[4])
    Y = reg.mouth_features(seq.astype(np.float32))
    assert Y.shape == (len(seq), 9 * len(reg.mouth_faces)) and Y.dtype == np.float64
    np.testing.assert_allclose(Y, reg.mouth_features(seq), atol=1e-5)  # float32 rounding of the positions
    Y = reg.mouth_features(seq)
    Y0 = Y.copy()
    np.testing.assert_allclose(reg.extrapolation(features=Y), reg.extrapolation(seq), rtol=0, atol=1e-14)
    for kw in (dict(), dict(exclude=[8]), dict(exclude=[4, 7])):
        ref = suggest_frames(seq, 4, regressor=reg, **kw)
        np.testing.assert_array_equal(suggest_frames(None, 4, regressor=reg, features=Y, **kw), ref)
        np.testing.assert_array_equal(Y, Y0)  # not modified without overwrite_features
        np.testing.assert_array_equal(suggest_frames(features=Y.copy(), count=4, regressor=reg,
                                                     overwrite_features=True, **kw), ref)
    np.testing.assert_array_equal(suggest_frames(seq, 4, regressor=reg), [8, 7])
    # the same through a float32 capture and a work array that is consumed (float32 rounding puts every
    # frame slightly outside the span, so only the first picks are meaningful)
    work = reg.mouth_features(seq.astype(np.float32))
    np.testing.assert_array_equal(suggest_frames(features=work, count=2, regressor=reg, overwrite_features=True),
                                  [8, 7])
    assert np.abs(work @ reg.training_span()).max() < 1e-10  # consumed: projected in place
    # without a regressor: features of a rest-centred regressor on the same mouth
    kw = dict(rest_vertices=V, faces=F, mouth_faces=mouth)
    for ex in ((), [4]):
        ref = suggest_frames(seq, 4, exclude=ex, **kw)
        np.testing.assert_array_equal(suggest_frames(features=Y, count=4, exclude=ex), ref)
        np.testing.assert_array_equal(suggest_frames(features=Y, count=4, exclude=ex, mouth_faces=mouth), ref)
    with pytest.raises(ValueError, match="not both"):
        suggest_frames(seq, 1, regressor=reg, features=Y)
    with pytest.raises(ValueError, match="neither"):
        reg.extrapolation()
    with pytest.raises(FaceLabError, match="expected \\(T, "):
        reg.extrapolation(features=Y[:, :-9])
    with pytest.raises(FaceLabError, match="mouth triangles"):
        suggest_frames(features=Y, count=1, mouth_faces=mouth[:-1])


def test_dense_poisson_maps_agree_with_the_sparse_solve(monkeypatch):
    """Small lip regions are predicted through dense maps K, H (prediction.dense_solution); large ones through
    the sparse back-substitution. Both give the same positions, and a refit rebuilds the dense maps."""
    import facelab_addon.core.lips.regressor.prediction as prop

    V, F, mouth, lips = grid(bumpy=True)
    train = np.stack([smooth_random_deformation(V, s) for s in range(3)])
    cap = np.stack([smooth_random_deformation(V, s) + lip_bump(V) for s in range(5, 10)])
    reg = LipRegressor(V, F, mouth, lips).fit(train)
    dense = reg.predict(cap)
    assert prop.dense_solution(reg.operators, reg.trained) is not None
    monkeypatch.setattr(prop, "_DENSE_MAX", 0)
    assert prop.dense_solution(reg.operators, reg.trained) is None
    sparse = reg.predict(cap)
    assert np.abs(sparse - cap).max() > 1e-3  # a real correction
    np.testing.assert_allclose(dense, sparse, rtol=0, atol=f32_tol(reg))  # float32 maps vs the float64 solve
    monkeypatch.setattr(prop, "_DENSE_MAX", 10**9)
    reg.add(cap[:1] + 0.01 * lip_bump(V))  # refit: new maps
    ref = LipRegressor(V, F, mouth, lips).fit(np.concatenate([train, cap[:1] + 0.01 * lip_bump(V)]))
    np.testing.assert_allclose(reg.predict(cap), ref.predict(cap), rtol=0, atol=f32_tol(reg))
