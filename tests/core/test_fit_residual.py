"""Reconstruct's default: bounded blendshape fit + noise-aware natural-neighbour residual (core.lgi.fit_residual)."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from facelab_addon.core.errors import BundleError, DatasetError
from facelab_addon.core.lgi.binding import bind_points
from facelab_addon.core.lgi.fit_residual import FitResidual, estimate_noise
from facelab_addon.core.lgi.natural_neighbor import surface_points

from .test_geometric_indexing import dataset, face_model, plane


@pytest.fixture(scope="module")
def toy():
    V, F = plane()
    W, X = dataset(V)
    rng = np.random.default_rng(0)
    pts = np.array([[0.12 + 0.25 * i, 0.12 + 0.25 * j] for i in range(4) for j in range(4)])
    pts += 0.03 * rng.standard_normal(pts.shape)
    bf, bb, _ = bind_points(V, F, np.c_[pts, np.zeros(len(pts))])
    rec = FitResidual(V, F, X, bf, bb, uvs=V[:, :2])
    p0 = surface_points(V, F, bf, bb)
    A = (surface_points(X, F, bf, bb) - p0).reshape(len(X), -1).T
    return dict(V=V, F=F, X=X, bf=bf, bb=bb, rec=rec, p0=p0, A=A)


def hard_fit(toy, q):
    w = lsq_linear(toy["A"], (q - toy["p0"]).ravel(), bounds=(0, 1), method="bvls").x
    return toy["V"] + np.tensordot(w, toy["X"] - toy["V"], axes=1)


def poses(n, seed):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        w = np.zeros(6)
        a, b = rng.choice(6, 2, replace=False)
        w[[a, b]] = rng.uniform(0.3, 0.8, 2)
        out.append(w)
    return out


def test_dataset_shapes_and_the_neutral_are_reproduced(toy):
    rec, X, F = toy["rec"], toy["X"], toy["F"]
    P = surface_points(X, F, toy["bf"], toy["bb"])
    for k in range(len(X)):
        np.testing.assert_allclose(rec.reconstruct(P[k]), X[k], atol=1e-5)
    np.testing.assert_allclose(rec.reconstruct(toy["p0"]), toy["V"], atol=1e-9)


def test_clean_bundles_are_interpolated_and_the_fit_weights_are_bounded(toy):
    V, F = toy["V"], toy["F"]
    # without the learned gain the whole residual is stitched: exactly through the bundles
    rec = FitResidual(V, F, toy["X"], toy["bf"], toy["bb"], uvs=V[:, :2], learn_gain=False)
    assert (rec.gain[rec.falloff_weights > 0] == 1).all()
    q = surface_points(face_model(V, np.full(6, 1.3)), F, toy["bf"], toy["bb"])  # beyond the dataset
    X = rec.reconstruct(q)
    w = rec.last["weights"]
    assert w.min() >= 0 and w.max() <= 1 and rec.last["residual"] > 1e-3
    np.testing.assert_allclose(surface_points(X, F, toy["bf"], toy["bb"]), q, atol=1e-9)
    np.testing.assert_allclose(rec.fit_weights(q), w, atol=1e-9)


def test_learned_gain_reduces_the_held_out_error(toy):
    V, F, rec = toy["V"], toy["F"], toy["rec"]
    plain = FitResidual(V, F, toy["X"], toy["bf"], toy["bb"], uvs=V[:, :2], learn_gain=False)
    g = rec.gain[rec.falloff_weights > 0]
    assert 0 <= g.min() and g.max() <= 1 and 0.2 < g.mean() < 1
    e_g, e_p = [], []
    for w in poses(12, 21):
        x = face_model(V, w)
        q = surface_points(x, F, toy["bf"], toy["bb"])
        e_g.append(np.linalg.norm(rec.reconstruct(q) - x, axis=1).mean())
        e_p.append(np.linalg.norm(plain.reconstruct(q) - x, axis=1).mean())
    print("held-out mean error, learned gain %.3g, whole residual %.3g" % (np.mean(e_g), np.mean(e_p)))
    assert np.mean(e_g) < np.mean(e_p)


def test_noise_is_filtered_and_never_worse_than_the_bounded_fit(toy):
    rec, V, F = toy["rec"], toy["V"], toy["F"]
    rng = np.random.default_rng(8)
    sigma = 0.002  # scene units; the motions are about 0.05: 4 % noise, 16 bundles for 17 shapes
    e_rec, e_fit, e_exact = [], [], []
    for w in poses(12, 9):
        x = face_model(V, w)
        q = surface_points(x, F, toy["bf"], toy["bb"]) + sigma * rng.standard_normal((len(toy["bf"]), 3))
        e_rec.append(np.linalg.norm(rec.reconstruct(q, noise=sigma) - x, axis=1).mean())
        e_exact.append(np.linalg.norm(rec.reconstruct(q) - x, axis=1).mean())
        e_fit.append(np.linalg.norm(hard_fit(toy, q) - x, axis=1).mean())
    # so noisy that the residual cannot be told from the noise: the default falls back to the bounded fit
    assert np.mean(e_rec) <= 1.02 * np.mean(e_fit), (np.mean(e_rec), np.mean(e_fit))
    assert np.mean(e_rec) < 0.9 * np.mean(e_exact)  # exact interpolation passes the noise through
    # bundles that are pure noise around the neutral: the residual is filtered out entirely
    q = toy["p0"] + sigma * rng.standard_normal(toy["p0"].shape)
    rec.reconstruct(q, noise=sigma)
    assert rec.last["lambda"] > 10


def test_the_residual_fades_far_from_the_bundles():
    V, F = plane(25)
    _, X = dataset(V)
    # bundles only in the lower-left quarter: the top-right corner is more than 2.5 spacings away
    pts = np.array([[0.05 + 0.1 * i, 0.05 + 0.1 * j, 0.0] for i in range(4) for j in range(4)])
    bf, bb, _ = bind_points(V, F, pts)
    rec = FitResidual(V, F, X, bf, bb, uvs=V[:, :2])
    far = (V[:, 0] > 0.8) & (V[:, 1] > 0.8)
    assert (rec.falloff_weights[far] == 0).all() and rec.falloff_weights[(V[:, 0] < 0.3) & (V[:, 1] < 0.3)].min() == 1
    assert (rec.residual_weights[far] == 0).all()
    x = face_model(V, np.array([0.5, 0, 0, 0.7, 0, 0]))
    q = surface_points(x, F, bf, bb)
    Xr = rec.reconstruct(q)
    w = rec.last["weights"]
    np.testing.assert_allclose(Xr[far], (V + np.tensordot(w, X - V, axes=1))[far], atol=1e-12)


def test_noise_estimate_from_jitter_and_sequences(toy):
    rec, V, F = toy["rec"], toy["V"], toy["F"]
    T = 60
    s = 0.5 + 0.3 * np.sin(np.linspace(0, 3, T))
    truth = np.stack([face_model(V, np.array([1, 0, 0, 0, 0.6, 0]) * st) for st in s])
    Qc = surface_points(truth, F, toy["bf"], toy["bb"])
    sigma = 0.002
    Q = Qc + sigma * np.random.default_rng(3).standard_normal(Qc.shape)
    assert estimate_noise(Q) == pytest.approx(sigma, rel=0.15)
    assert estimate_noise(Qc) < 0.1 * sigma
    assert estimate_noise(Q[:2]) == 0.0
    Q[7, 3] = np.nan
    out, skipped = rec.reconstruct_sequence(Q)  # noise estimated
    assert skipped == [7] and np.isnan(out[7]).all()
    assert rec.last_sequence["noise"] == pytest.approx(sigma, rel=0.15)
    ok = [t for t in range(T) if t != 7]
    e_auto = np.linalg.norm(out[ok] - truth[ok], axis=2).mean()
    exact, _ = rec.reconstruct_sequence(Q, noise=0.0)
    e_exact = np.linalg.norm(exact[ok] - truth[ok], axis=2).mean()
    smooth, _ = rec.reconstruct_sequence(Q, smooth=5)
    e_smooth = np.linalg.norm(smooth[ok] - truth[ok], axis=2).mean()
    assert e_auto < 0.9 * e_exact and e_smooth < e_auto, (e_auto, e_exact, e_smooth)
    # without noise every frame matches the single-frame reconstruction
    clean, _ = rec.reconstruct_sequence(Qc[:5], noise=0.0)
    np.testing.assert_allclose(clean[3], rec.reconstruct(Qc[3]), atol=1e-12)


def test_bad_input_is_refused(toy):
    V, F, X, bf, bb, rec = toy["V"], toy["F"], toy["X"], toy["bf"], toy["bb"], toy["rec"]
    with pytest.raises(DatasetError, match=r"\(S,V,3\)"):
        FitResidual(V, F, X[:, :-1], bf, bb)
    bad = X.copy()
    bad[2, 5] = np.nan
    with pytest.raises(DatasetError, match="NaN"):
        FitResidual(V, F, bad, bf, bb)
    with pytest.raises(DatasetError, match="at least 4 dataset shapes"):
        FitResidual(V, F, X[:3], bf, bb)
    with pytest.raises(DatasetError, match="duplicates.*remove one"):
        FitResidual(V, F, np.concatenate([X, X[2:3]]), bf, bb)
    with pytest.raises(DatasetError, match="equals the neutral"):
        FitResidual(V, F, np.concatenate([X, V[None]]), bf, bb)
    Xs = X.copy()
    still = (V[:, 0] < 0.2) & (V[:, 1] > 0.8)
    Xs[:, still] = V[still]
    corner = np.flatnonzero(still[F].all(1))[0]
    with pytest.raises(BundleError, match="not moved by any dataset shape"):
        FitResidual(V, F, Xs, np.r_[bf, corner], np.vstack([bb, [1 / 3] * 3]))
    with pytest.raises(BundleError, match="re-bind"):
        FitResidual(V, F, X, [0, len(F) + 4], np.full((2, 3), 1 / 3))
    with pytest.raises(BundleError, match=r"\(16,3\)"):
        rec.reconstruct(np.zeros((3, 3)))
    q = toy["p0"].copy()
    q[4] = np.nan
    with pytest.raises(BundleError, match="NaN"):
        rec.reconstruct(q)
    with pytest.raises(BundleError, match="noise"):
        rec.reconstruct(toy["p0"], noise=-1.0)


def _ratios_to_the_bounded_fit(rec, x0, shapes, truth, F, bf, bb, skin, lips):
    """``(sigma, skin target, skin ratio, inner-lip ratio)`` at no noise and at 0.2 mm (ICT centimetres): ``rec``'s
    mean error on the held-out ``truth`` (T,V,3) over that of the bounded blendshape fit (``lsq_linear``, weights
    in [0,1]) from the same bundles."""
    Q = surface_points(truth, F, bf, bb)
    D = shapes - x0
    out = []
    for sigma, target in ((0.0, 0.9), (0.02, 1.0)):
        QQ = Q + sigma * np.random.default_rng(5).standard_normal(Q.shape)
        e_rec, e_fit = [], []
        for k in range(len(truth)):
            wf = lsq_linear(rec.A, (QQ[k] - rec.p0).ravel(), bounds=(0, 1), method="bvls").x
            e_fit.append(np.linalg.norm(x0 + np.tensordot(wf, D, axes=1) - truth[k], axis=1))
            e_rec.append(np.linalg.norm(rec.reconstruct(QQ[k], noise=sigma) - truth[k], axis=1))
        e_rec, e_fit = np.array(e_rec), np.array(e_fit)
        out.append((sigma, target, e_rec[:, skin].mean() / e_fit[:, skin].mean(),
                    e_rec[:, lips].mean() / e_fit[:, lips].mean()))
    return out


@pytest.mark.slow
def test_ict_beats_the_bounded_fit_on_another_actor_and_layout(ict):
    # issue 15's targets on a case the method was not designed on: an ICT identity, 120 random bundles
    from facelab_addon.testing import datasets as ds
    from facelab_addon.testing.recon_cases import ict_identity, random_bundle_layout
    from facelab_addon.testing.synthetic import inner_lip_mask

    actor = ict_identity(ict, seed=1)
    data = ds.ict_dataset(actor)
    F, x0 = actor.faces, actor.neutral
    bf, bb = random_bundle_layout(actor, 120, seed=4)
    rec = FitResidual(x0, F, data.shapes, bf, bb, uvs=ds.ict_triangle_uvs(actor))
    skin = actor.part_vertex_mask("M_Face")
    lips = inner_lip_mask(x0, F, ~skin)
    H = ds.held_out_weights(10, seed=31)
    truth = np.stack([data.generator(w) for w in H])
    ratios = _ratios_to_the_bounded_fit(rec, x0, data.shapes, truth, F, bf, bb, skin, lips)
    for sigma, target, ratio, lip_ratio in ratios:  # centimetres: 0.2 mm
        print(f"noise {sigma * 10:.1f} mm: skin ratio {ratio:.3f}, inner-lip ratio {lip_ratio:.3f}")
        assert ratio <= target, (sigma, ratio)
        assert lip_ratio <= 1.0, (sigma, lip_ratio)  # measured 0.82, 0.97 clean; 0.96, 0.99 with 0.2 mm


@pytest.mark.slow
def test_ict_inner_lips_never_worse_than_the_bounded_fit_with_sparse_bundles(ict):
    # issue 15: the sparse 60-bundle layout on another identity, where the inner lips (far from every bundle) were
    # 0.5 % above the bounded fit, clean (the residual leaked onto them through a gain learned by chance) and with
    # 0.2 mm noise (the weight prior shrank the weights of shapes the bundles see weakly)
    from facelab_addon.testing import datasets as ds
    from facelab_addon.testing.recon_cases import ict_identity
    from facelab_addon.testing.synthetic import inner_lip_mask

    actor = ict_identity(ict, seed=2)
    data = ds.ict_dataset(actor, generator=ds.ICTShapeGenerator(actor, inbetween_bulge=0.1, combination_bulge=0.2))
    F, x0 = actor.faces, actor.neutral
    bf, bb = ds.ict_bundle_layout(actor, 60, seed=0)
    rec = FitResidual(x0, F, data.shapes, bf, bb, uvs=ds.ict_triangle_uvs(actor))
    skin = actor.part_vertex_mask("M_Face")
    lips = inner_lip_mask(x0, F, ~skin)
    H = ds.held_out_weights(20, seed=23)
    truth = np.stack([data.generator(w) for w in H])
    ratios = _ratios_to_the_bounded_fit(rec, x0, data.shapes, truth, F, bf, bb, skin, lips)
    for sigma, target, ratio, lip_ratio in ratios:  # centimetres: 0.2 mm
        print(f"noise {sigma * 10:.1f} mm: skin ratio {ratio:.4f}, inner-lip ratio {lip_ratio:.4f}")
        assert ratio <= target, (sigma, ratio)
        assert lip_ratio <= 1.0, (sigma, lip_ratio)  # before issue 15's fix: 1.005 clean, 1.006 with 0.2 mm
