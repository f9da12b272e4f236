"""Streaming Propagate in core: per-chunk lip corrections equal ``predict``, the streaming
compression keeps every vertex within the tolerance and does not depend on the chunking, and the
streaming suggestion picks exactly what ``suggest_frames`` picks on the whole shot."""

import numpy as np
import pytest

from facelab_addon.core.errors import FaceLabError, TooManyShapesError
from facelab_addon.core.geometry.compress import compress
from facelab_addon.core.lips.regressor import LipRegressor
from facelab_addon.core.lips.regressor.reduced import StreamingBasis
from facelab_addon.core.lips.suggest import SuggestScreen, suggest_frames
from facelab_addon.testing.subdivide import subdivide_midpoint

from .test_propagate import _sequence, grid, smooth_random_deformation


def fitted():
    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips).fit(np.stack([smooth_random_deformation(V, s) for s in range(4)]))
    return V, F, reg


def test_lip_corrections_of_used_vertices_equal_predict():
    V, F, reg = fitted()
    cap = _sequence(V, 9)
    pred = reg.predict(cap)
    iv = reg.interior_vertices
    want = pred[:, iv] - cap[:, iv]
    assert np.abs(want).max() > 1e-2  # a real correction
    # lip_corrections runs in float64, predict in float32 (test_propagate.f32_tol)
    np.testing.assert_allclose(reg.lip_corrections(cap), want, rtol=0, atol=1e-7 * reg.mouth_size)
    used = cap[:, reg.used_vertices].astype(np.float32)  # only the vertices a reader needs, float32
    got = np.concatenate([reg.lip_corrections(used[s : s + 4], used_only=True, first=s) for s in (0, 4, 8)])
    np.testing.assert_allclose(got, reg.predict(cap.astype(np.float32))[:, iv] - cap.astype(np.float32)[:, iv],
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(reg.mouth_features(used, used_only=True), reg.mouth_features(cap), atol=1e-5)
    with pytest.raises(FaceLabError, match="used vertices only"):
        reg.lip_corrections(cap[:, :-3], used_only=True)


def _low_rank_shot(T=300, n=200, rank=5, noise=1e-7, seed=0):
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((rank, n, 3)) * 1e-3
    W = np.cumsum(rng.standard_normal((T, rank)), axis=0) * 0.1
    return np.einsum("tk,knc->tnc", W, B) + rng.standard_normal((T, n, 3)) * noise


@pytest.mark.parametrize("chunks", [[300], [37] * 8 + [4], [1] * 300])
def test_streaming_basis_is_within_tolerance_and_independent_of_chunks(chunks):
    D = _low_rank_shot()
    tol = 1e-5
    sb = StreamingBasis(D.shape[1], tol)
    s = 0
    for c in chunks:
        sb.add(D[s : s + c])
        s += c
    B, W = sb.finish()
    R = np.einsum("tk,knc->tnc", W, B)
    assert np.sqrt(np.sum((R - D) ** 2, axis=2)).max() <= tol
    assert np.abs(W).max() == pytest.approx(1.0)
    assert len(B) == len(compress(D, tol)[0]) == 5  # as few shapes as the whole-shot SVD
    whole = StreamingBasis(D.shape[1], tol)
    whole.add(D)
    Bw, Ww = whole.finish()
    np.testing.assert_allclose(R, np.einsum("tk,knc->tnc", Ww, Bw), rtol=0, atol=1e-15)


def test_streaming_basis_zero_shot_and_refusal():
    sb = StreamingBasis(10, 1e-5)
    sb.add(np.zeros((7, 10, 3)))
    B, W = sb.finish()
    assert B.shape == (0, 10, 3) and W.shape == (7, 0)
    sb = StreamingBasis(50, 1e-5, max_rank=8)
    with pytest.raises(TooManyShapesError, match="more than 8 corrective shapes"):  # a FaceLabError
        sb.add(np.random.default_rng(1).standard_normal((20, 50, 3)))


def _screened(reg, feats, count, exclude, chunk, candidates):
    def features_of(idx):
        return feats[idx]

    screen = SuggestScreen(reg, len(feats), exclude=exclude, candidates=candidates)
    for s in range(0, len(feats), chunk):
        screen.add(s, feats[s : s + chunk])
    picks, scale, passes = [], None, 1
    while True:
        more, done, dirs, scale = screen.select(count - len(picks), features_of, scale)
        picks += more
        if done or len(picks) >= count:
            return picks, passes
        screen = SuggestScreen(reg, len(feats), exclude=list(exclude) + picks, directions=dirs,
                               candidates=candidates)
        for s in range(0, len(feats), chunk):
            screen.add(s, feats[s : s + chunk])
        passes += 1


def test_suggest_screen_picks_what_suggest_frames_picks():
    V, F, reg = fitted()
    cap = _sequence(V, 40, seed=11)
    cap = np.concatenate([np.repeat(cap[:1] * 1.0 + 0.3 * (cap[:1] - V), 30, axis=0), cap])  # a held pose
    feats = reg.mouth_features(cap)
    exclude = [3, 50]
    want = suggest_frames(None, 4, regressor=reg, features=feats, exclude=exclude)
    # the held pose fills the candidates of the first pass: later picks need more passes, and are exact
    got, passes = _screened(reg, feats, 4, exclude, chunk=7, candidates=8)
    assert got == list(want) and passes > 1
    got, passes = _screened(reg, feats, 4, exclude, chunk=64, candidates=48)
    assert got == list(want)


def test_midpoint_subdivision_keeps_the_surface_and_attributes():
    V, F, _, _ = grid()
    V2, F2, S = subdivide_midpoint(V, F)
    n_edges = len({tuple(sorted(e)) for f in F for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))})
    assert V2.shape == (len(V) + n_edges, 3) and F2.shape == (4 * len(F), 3)
    np.testing.assert_array_equal(V2[: len(V)], V)
    a = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    a2 = np.cross(V2[F2[:, 1]] - V2[F2[:, 0]], V2[F2[:, 2]] - V2[F2[:, 0]])
    np.testing.assert_allclose(a2.reshape(-1, 4, 3).sum(1), a, atol=1e-12)  # same area and orientation
    d = smooth_random_deformation(V, 3) - V
    mid = F2[3::4]  # (ab, bc, ca) of each input triangle
    np.testing.assert_allclose((S @ d)[mid[:, 0]], 0.5 * (d[F[:, 0]] + d[F[:, 1]]), atol=1e-15)
    np.testing.assert_allclose((S @ d)[mid[:, 1]], 0.5 * (d[F[:, 1]] + d[F[:, 2]]), atol=1e-15)


@pytest.mark.parametrize("center", ["rest", None])
def test_correct_chunk_scores_and_projections_without_forming_features(center):
    V, F, mouth, lips = grid(bumpy=True)
    reg = LipRegressor(V, F, mouth, lips, center=center)
    reg.fit(np.stack([smooth_random_deformation(V, s) for s in range(4)]))
    cap = _sequence(V, 12, seed=3)
    corr, score, sq = reg.correct_chunk(cap, first=0)
    np.testing.assert_allclose(corr, reg.lip_corrections(cap), rtol=0, atol=1e-12)
    Y = reg.mouth_features(cap)
    np.testing.assert_allclose(sq, np.sum(Y * Y, axis=1), rtol=1e-10)
    # ||y||² - ||U_Yᵀ y||² cancels for frames in the span: about 1e-6 instead of 1e-15 there
    np.testing.assert_allclose(score, reg.extrapolation(features=Y), rtol=1e-6, atol=2e-6)
    A = np.random.default_rng(0).standard_normal((Y.shape[1], 3))
    P, sq2 = reg.mouth_projections(cap, A)
    np.testing.assert_allclose(P, Y @ A, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sq2, sq, rtol=1e-12)


def test_suggest_screen_from_positions_and_scores():
    V, F, reg = fitted()
    cap = _sequence(V, 30, seed=13)
    feats = reg.mouth_features(cap)
    want = suggest_frames(None, 3, regressor=reg, features=feats, exclude=[4])
    a = SuggestScreen(reg, 30, exclude=[4])
    b = SuggestScreen(reg, 30, exclude=[4])
    for s in range(0, 30, 8):
        _, score, sq = reg.correct_chunk(cap[s : s + 8], first=s)
        a.add_scores(s, sq, score)
        b.add_frames(s, cap[s : s + 8])
    np.testing.assert_allclose(a.res, b.res, rtol=1e-6, atol=1e-9)
    for screen in (a, b):
        picks, done, _, _ = screen.select(3, lambda idx: feats[idx])
        assert done and picks == list(want)
