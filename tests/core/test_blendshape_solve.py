"""Blendshape fit and out-of-subspace corrective (Bhat et al. 2013 §4.1-4.3) against generated ground truth."""

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from facelab_addon.core.capture.markers import nearest_surface_points
from facelab_addon.core.errors import FaceLabError
from facelab_addon.core.solve.blendshape_solve import BlendshapeSolver, FrameResult, SolveParams
from facelab_addon.core.solve.bounded_lsq import box_least_squares
from facelab_addon.core.solve.corrective import CorrectiveParams, OutOfSubspaceCorrective
from facelab_addon.core.solve.matching import contour_curve_distance
from facelab_addon.core.solve.performance import solve_performance
from facelab_addon.testing.capture_sim import make_capture

NAMES = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthFunnel", "mouthPucker", "browInnerUp_L", "eyeBlink_L",
         "jawLeft", "mouthLowerDown_L"]


@pytest.fixture(scope="module")
def cap(ict):
    return make_capture(ict, names=NAMES, n_frames=4, n_markers=60, noise_px=0.5, seed=1, curves=False)


@pytest.fixture(scope="module")
def deltas(ict):
    return ict.deltas(NAMES)


def test_box_least_squares_matches_bvls_and_kkt():
    rng = np.random.default_rng(0)
    for trial in range(5):
        J = rng.normal(size=(40, 12))
        w_true = rng.uniform(-2.0, 2.0, 12)  # several outside the box
        r = J @ w_true + 0.1 * rng.normal(size=40)
        H, g = J.T @ J, J.T @ r
        w, _ = box_least_squares(H, g, -1.0, 1.0, w0=rng.uniform(-1, 1, 12))
        ref = lsq_linear(J, r, bounds=(-1.0, 1.0), method="bvls", tol=1e-14).x
        np.testing.assert_allclose(w, ref, atol=1e-9)
        grad = H @ w - g
        free = (w > -1 + 1e-12) & (w < 1 - 1e-12)
        assert np.abs(grad[free]).max(initial=0) < 1e-8
        assert (grad[w <= -1 + 1e-12] >= -1e-8).all() and (grad[w >= 1 - 1e-12] <= 1e-8).all()
        assert (np.abs(w) == 1.0).any()


def test_markers_give_back_the_true_weights_without_noise(ict, cap, deltas):
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None,
                              params=SolveParams(regularization=0.0))
    prev = None
    for t in range(len(cap.weights)):
        res = solver.solve_frame(cap.markers_px_clean[t], previous=prev, iterations=4)
        np.testing.assert_allclose(res.weights, cap.weights[t], atol=1e-6)
        assert res.info["marker_rms_px"] < 1e-5
        prev = res


def test_bundles_give_back_the_true_weights(ict, cap, deltas):
    X = cap.markers.evaluate(ict.neutral)
    bundles = nearest_surface_points(ict.neutral, ict.faces, X)
    np.testing.assert_allclose(bundles.evaluate(ict.neutral), X, atol=1e-9)
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, None, bundles,
                              params=SolveParams(regularization=0.0))
    B = bundles.evaluate(cap.truth[2])
    B[::7] = np.nan  # some bundles not reconstructed on this frame
    res = solver.solve_frame(None, B)
    np.testing.assert_allclose(res.weights, cap.weights[2], atol=1e-8)
    assert res.info["bundles_used"] == len(B) - len(B[::7])


def test_bounds_clip_and_the_solution_stays_optimal(ict, cap, deltas):
    w_true = cap.weights[1].copy()
    w_true[NAMES.index("jawOpen")] = 1.6
    w_true[NAMES.index("mouthSmile_L")] = -1.4
    V = ict.neutral + np.einsum("s,svd->vd", w_true, deltas)
    X = cap.markers.evaluate(V)
    px = np.stack([c.project(X) for c in cap.cameras])
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None,
                              params=SolveParams(regularization=0.0))
    res = solver.solve_frame(px, iterations=6)
    w = res.weights
    assert w[NAMES.index("jawOpen")] == 1.0 and w[NAMES.index("mouthSmile_L")] == -1.0
    assert (w >= -1.0).all() and (w <= 1.0).all()
    assert res.info["marker_rms_px"] > 1.0  # the truth is outside the box: it cannot be matched
    # optimal for the (converged) linearisation: the same as SciPy's bounded least squares
    J, r = solver.linear_system(w, px)
    ref = lsq_linear(J, r, bounds=(-1.0, 1.0), method="bvls", tol=1e-14).x
    np.testing.assert_allclose(w, ref, atol=1e-6)


def test_corrective_is_zero_when_constraints_hold_and_fits_them_when_not(ict, cap, deltas):
    face = ict.part_vertex_mask("M_Face")
    corr = OutOfSubspaceCorrective(ict.neutral, ict.faces, cap.cameras, cap.markers, None, boundary=~face)
    Vb = cap.truth[0]  # in the rig's span: the markers are met exactly
    d = corr.solve(Vb, cap.markers_px_clean[0])
    assert np.abs(d).max() < 1e-7  # scene units (cm): 1e-6 mm
    # a smooth out-of-subspace bump on the cheek: move the marker tracks, the corrective follows them
    c = ict.neutral[face].mean(axis=0) + np.array([3.0, -2.0, 2.0])
    bump = np.exp(-np.sum((Vb - c) ** 2, axis=1) / 4.0)[:, None] * np.array([0.0, 0.0, 0.3])
    bump[~face] = 0.0
    X = cap.markers.evaluate(Vb + bump)
    px = np.stack([cam.project(X) for cam in cap.cameras])
    strong = OutOfSubspaceCorrective(ict.neutral, ict.faces, cap.cameras, cap.markers, None, boundary=~face,
                                     params=CorrectiveParams(marker_weight=1e5))
    d = strong.solve(Vb, px)
    Y = cap.markers.evaluate(Vb + d)
    err = np.concatenate([np.linalg.norm(cam.project(Y) - px[i], axis=1) for i, cam in enumerate(cap.cameras)])
    before = np.concatenate([np.linalg.norm(cam.project(cap.markers.evaluate(Vb)) - px[i], axis=1)
                             for i, cam in enumerate(cap.cameras)])
    assert before.max() > 5.0 and err.max() < 0.05
    # the fixed boundary does not move at all
    assert np.abs(d[~face]).max() == 0.0
    assert np.abs(d[face]).max() > 0.05


def test_contours_recover_the_truth(ict, deltas):
    from facelab_addon.testing.contour_truth import ict_contour_loops

    cap = make_capture(ict, names=NAMES, n_frames=2, n_markers=40, noise_px=0.0, seed=2, curves=True)
    loops = ict_contour_loops(ict)
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None, loops=loops,
                              params=SolveParams(regularization=0.0))
    prev = None
    for t in range(2):
        # mouth curves: exact in the rig's span (the eyelid curves are lifted onto a fitted eyeball
        # sphere, an approximation of the lid margin: checked loosely below)
        mouth = [c for c in cap.curves[t] if c.name.startswith("mouth")]
        assert len(mouth) == 4
        res = solver.solve_frame(cap.markers_px_clean[t], None, mouth, previous=prev, iterations=3)
        prev = res
        assert len(res.correspondences) == 4
        np.testing.assert_allclose(res.weights, cap.weights[t], atol=2e-3)
        V = solver.vertices(res.weights)
        assert contour_curve_distance(V, cap.cameras, res.correspondences, cap.curves[t]).max() < 0.1
    res = solver.solve_frame(cap.markers_px_clean[1], None, cap.curves[1], previous=prev, iterations=3)
    assert len(res.correspondences) > 4  # eyelid 3D blocks may drop grazing points (contours.md)
    np.testing.assert_allclose(res.weights, cap.weights[1], atol=0.05)
    # the partial evaluation used for matching agrees with the full mesh where matching looks
    w = cap.weights[0]
    np.testing.assert_allclose(solver._partial_vertices(w)[solver._need], solver.vertices(w)[solver._need])


def test_solve_performance_skips_frames_without_data_and_counts_offscreen(ict, cap, deltas):
    mp = cap.markers_px_clean.copy()
    mp[1] = np.nan  # nothing tracked on frame 1
    mp[2, 0, :5] = [5000.0, 5000.0]  # 5 markers off-screen in camera 0
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None,
                              params=SolveParams(regularization=0.0))
    seen = []
    res = solve_performance(solver, None, mp, progress=lambda i, n: seen.append((i, n)))
    assert list(res.skipped) == [1] and "no tracked markers" in res.skipped[1]
    assert np.isnan(res.weights[1]).all()
    np.testing.assert_allclose(res.weights[[0, 2, 3]], cap.weights[[0, 2, 3]], atol=1e-6)
    assert res.info["offscreen_markers"] == {2: 5}
    assert seen == [(i, 4) for i in range(4)]
    assert res.correctives is None


def test_bad_input_messages(ict, cap, deltas):
    with pytest.raises(FaceLabError, match="calibration"):
        BlendshapeSolver(ict.neutral, deltas, ict.faces, [object()], cap.markers, None)
    with pytest.raises(FaceLabError, match="shape keys"):
        BlendshapeSolver(ict.neutral, np.zeros((0, len(ict.neutral), 3)), ict.faces, cap.cameras, cap.markers, None)
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None)
    with pytest.raises(FaceLabError, match="expected"):
        solver.solve_frame(cap.markers_px[0][:, :10])
    with pytest.raises(FaceLabError, match="contour loops"):
        solver.solve_frame(cap.markers_px[0], None, [object()])
    with pytest.raises(FaceLabError, match="nothing to fit"):
        solver.solve_frame(np.full_like(cap.markers_px[0], np.nan))
    assert isinstance(solver.solve_frame(cap.markers_px[0]), FrameResult)


def test_params_are_frozen_checked_and_reach_the_solvers(ict, cap, deltas):
    """The parameter objects refuse bad values with the fix named, cannot be changed after the fact, and the
    solver and corrective use the values they are given."""
    import dataclasses

    for make, match in ((lambda: SolveParams(anchor_weight=-1.0), "anchor_weight"),
                        (lambda: SolveParams(anchor_weight=np.nan), "anchor_weight"),
                        (lambda: CorrectiveParams(contour_metric="normal"), "contour_metric"),
                        (lambda: CorrectiveParams(region_damping=-0.1), "region_damping"),
                        (lambda: CorrectiveParams(lip_damping=np.inf), "lip_damping"),
                        (lambda: CorrectiveParams(lip_contour_weight=-8.0), "lip_contour_weight")):
        with pytest.raises(FaceLabError, match=match):
            make()
    with pytest.raises(dataclasses.FrozenInstanceError):
        SolveParams().marker_weight = 2.0
    fit = SolveParams(bounds=(0.0, 0.5), marker_weight=2.0, anchor_weight=0.0)
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None, params=fit)
    assert solver.params is fit and solver.marker_weight == 2.0 and solver.anchor_weight == 0.0
    np.testing.assert_array_equal(solver.lo, 0.0)
    np.testing.assert_array_equal(solver.hi, 0.5)
    w = solver.solve_frame(cap.markers_px[0]).weights
    assert w.min() >= 0.0 and w.max() <= 0.5 and np.isclose(w.max(), 0.5)  # the bounds given are the ones used
    corr = OutOfSubspaceCorrective(ict.neutral, ict.faces, cap.cameras, cap.markers, None,
                                   params=CorrectiveParams(damping=0.2, eyelid_weight=0.0))
    assert corr.damping == 0.2 and corr.eyelid_weight == 0.0 and corr.contour_weight == 0.5


def test_default_boundary_holds_the_border_and_parts_without_markers():
    from facelab_addon.core.capture.markers import SurfacePoints

    # a 4x4-vertex grid (border: 12 vertices, interior: 4) plus a separate triangle with no marker
    g = np.array([[x, y, 0.0] for y in range(4) for x in range(4)])
    F = []
    for y in range(3):
        for x in range(3):
            a = 4 * y + x
            F += [[a, a + 1, a + 5], [a, a + 5, a + 4]]
    V = np.vstack([g, [[10, 0, 0], [11, 0, 0], [10, 1, 0]]])
    F = np.array(F + [[16, 17, 18]])
    mk = SurfacePoints([[5, 6, 10]], [[1 / 3, 1 / 3, 1 / 3]])
    b = OutOfSubspaceCorrective.default_boundary(V, F, mk, None)
    interior = {5, 6, 9, 10}
    assert set(np.flatnonzero(~b)) == interior
    assert b[16:].all()


def test_contour_planes_contain_the_ray_and_the_curve_tangent():
    from facelab_addon.core.capture.camera import Camera
    from facelab_addon.core.solve.corrective import _contour_planes

    cam = Camera.look_at([0.0, -3.0, 20.0], [0.0, 0.0, 0.0], [0, 1, 0], 50, 36, 1080, 1920)
    # a 3D lip-like arc in front of the camera and its image
    t = np.linspace(-1.0, 1.0, 41)
    X = np.stack([2.0 * t, 0.5 * (1 - t**2), 0.3 * t**2], axis=1)
    o, d = cam.rays(cam.project(X))
    P = _contour_planes(d)
    n = np.linalg.eigh(P)[1][:, :, -1]  # unit normals (P = n n^T has the single eigenvalue 1)
    np.testing.assert_allclose(np.linalg.eigvalsh(P)[:, -1], 1.0, atol=1e-12)
    res = lambda Y: np.einsum("cij,cj->ci", P, Y - o)  # noqa: E731
    assert np.abs(res(X)).max() < 1e-9  # the curve's own 3D points lie on their planes
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    assert np.abs(res(X + 0.7 * dn)).max() < 1e-9  # any depth along the ray: no residual
    # a small slide along the curve: second order only; a shift along the plane normal: all of it
    tan = np.gradient(X, axis=0)
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    assert np.abs(res(X + 0.01 * tan)).max() < 1e-4
    np.testing.assert_allclose(np.linalg.norm(res(X + 0.05 * n), axis=1), 0.05, rtol=1e-9)


def test_damping_keeps_the_corrective_local_and_closer_to_the_truth(ict, cap, deltas):
    """A cheek bump seen by the markers: the damped corrective is nearer the truth, especially far from it."""
    face = ict.part_vertex_mask("M_Face")
    Vb = cap.truth[0]
    c = ict.neutral[face].mean(axis=0) + np.array([3.0, -2.0, 2.0])
    bump = np.exp(-np.sum((Vb - c) ** 2, axis=1) / 4.0)[:, None] * np.array([0.0, 0.0, 0.3])
    bump[~face] = 0.0
    X = cap.markers.evaluate(Vb + bump)
    px = np.stack([cam.project(X) for cam in cap.cameras])
    far = face & (np.linalg.norm(Vb - c, axis=1) > 6.0)  # cm: where the bump is < 1e-4 mm
    errs = {}
    for damping in (0.0, 0.01):
        corr = OutOfSubspaceCorrective(ict.neutral, ict.faces, cap.cameras, cap.markers, None, boundary=~face,
                                       params=CorrectiveParams(damping=damping))
        d = corr.solve(Vb, px)
        e = np.linalg.norm(Vb + d - (Vb + bump), axis=1)
        errs[damping] = (e[face].mean(), e[far].mean())
    assert errs[0.01][0] < 0.9 * errs[0.0][0]  # measured 0.0061 vs 0.0073 cm
    assert errs[0.01][1] < 0.1 * errs[0.0][1]  # far field: 5e-5 vs 2e-3 cm


def test_truth_is_a_fixed_point_of_the_corrective_with_eyelids(ict, deltas):
    """On an in-span, noise-free frame the corrective from the true weights barely moves the mesh.

    The 3D eyelid targets are lifted with the lids' current heights over the eyeball (unbiased); with the
    rest heights (the old lift) a blink leaves them up to ~1 mm off and the corrective follows them.
    """
    from facelab_addon.core.solve.matching import MatchParams, match_contours
    from facelab_addon.testing.contour_truth import ict_contour_loops

    cap = make_capture(ict, names=NAMES, n_frames=3, n_markers=60, noise_px=0.0, seed=1, curves=True)
    loops = ict_contour_loops(ict)
    face = ict.part_vertex_mask("M_Face")
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None, loops=loops)
    corr = OutOfSubspaceCorrective(ict.neutral, ict.faces, cap.cameras, cap.markers, None, boundary=~face)
    blink = NAMES.index("eyeBlink_L")
    t = int(np.argmax(cap.weights[:, blink]))
    assert cap.weights[t, blink] > 0.1
    V = cap.truth[t]
    cc = solver.match(cap.weights[t], cap.curves[t])
    assert any(c.camera < 0 for c in cc)
    eyel = [c for c in cc if c.camera < 0]
    assert max(np.abs(c.evaluate(V) - c.targets).max() for c in eyel) < 0.01  # cm: 0.1 mm
    d = corr.solve(V, cap.markers_px_clean[t], None, cc)
    good = np.linalg.norm(d, axis=1)[face]
    rest = match_contours(V, ict.faces, cap.cameras, cap.curves[t], loops, MatchParams(eyelid_height="rest"))
    d_rest = corr.solve(V, cap.markers_px_clean[t], None, rest)
    bad = np.linalg.norm(d_rest, axis=1)[face]
    assert good.max() < 0.002 and good.mean() < 1e-4  # cm (measured 3e-4, 1.5e-5)
    assert bad.max() > 10 * good.max()  # measured 0.042 cm


def test_huber_weights_of_lip_contour_points(ict, deltas):
    """min(1, k / e) on the 2D lip points (e = reprojection residual in px); eyelid points untouched."""
    from facelab_addon.testing.contour_truth import ict_contour_loops

    cap = make_capture(ict, names=NAMES, n_frames=2, n_markers=40, noise_px=0.0, seed=2, curves=True)
    loops = ict_contour_loops(ict)
    solver = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None, loops=loops,
                              params=SolveParams(contour_huber_px=1.0))
    w = cap.weights[0]
    cc = solver.match(w, cap.curves[0])
    shift = np.array([3.0, -4.0])  # 5 px
    i_shift = next(i for i, c in enumerate(cc) if c.name == "mouth_upper")
    cc[i_shift].pixels = cc[i_shift].pixels + shift
    pw = solver._robust_weights(w, cc)
    for i, (c, f) in enumerate(zip(cc, pw)):
        if not c.name.startswith("mouth"):
            assert f is None
        elif i == i_shift:
            np.testing.assert_allclose(f, 0.2, atol=0.02)  # residual 5 px (+ the truth's < 0.3 px)
        else:
            assert f.min() > 0.99 or np.all(f == 1.0)


def test_huber_keeps_in_span_fits_and_loosens_out_of_span_lips(ict, deltas):
    """In span (noise-free) the robust fit equals the plain one; with a lip gap the lips pull less."""
    from facelab_addon.testing.contour_truth import ict_contour_loops

    loops = ict_contour_loops(ict)
    for gap, same in ((0.0, True), (3.0, False)):
        cap = make_capture(ict, names=NAMES, n_frames=2, n_markers=40, noise_px=0.0, seed=2, curves=True,
                           lip_error_mm=gap)
        mouth = [c for c in cap.curves[1] if c.name.startswith("mouth")]
        ws, errs = [], []
        face = ict.part_vertex_mask("M_Face")
        for k in (None, 1.0):
            s = BlendshapeSolver(ict.neutral, deltas, ict.faces, cap.cameras, cap.markers, None, loops=loops,
                                 params=SolveParams(contour_huber_px=k, anchor_weight=0.0))
            # the Huber loss alone (clean markers would otherwise anchor the fit to the markers-only one, see
            # test_contour_solve_unseen.py)
            ws.append(s.solve_frame(cap.markers_px_clean[1], None, mouth, iterations=2).weights)
            errs.append(np.linalg.norm(s.vertices(ws[-1]) - cap.truth[1], axis=1)[face].mean())
        d = np.abs(ws[0] - ws[1]).max()
        if same:
            assert d < 1e-3, d
            seen = [i for i, n in enumerate(NAMES) if n != "eyeBlink_L"]  # no eyelid curve given here
            np.testing.assert_allclose(ws[1][seen], cap.weights[1][seen], atol=5e-3)
        else:
            assert d > 1e-3, d
            assert errs[1] < errs[0]  # face error vs truth: measured 0.135 vs 0.139 mm
