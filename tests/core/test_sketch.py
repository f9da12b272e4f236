import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import CameraError, MeshError, SketchError, UsageError
from facelab_addon.core.geometry.polyline import resample_polyline
from facelab_addon.core.geometry.silhouette import (
    contour_distance,
    lip_side,
    silhouette_edges,
)
from facelab_addon.core.lips.refine_params import RefineParams
from facelab_addon.core.lips.sketch import refine_lips
from facelab_addon.core.lips.views import press_lips

from .lipmesh import front_camera, line_px, tube, two_lips


def free(V):
    """No hidden parts: both tubes may move (without ``fixed`` the smaller piece would be held)."""
    return np.zeros(len(V), bool)


def test_resample_polyline_spacing_and_ends():
    P = np.array([[0.0, 0], [10, 0], [10, 5]])
    S = resample_polyline(P, 1.0)
    np.testing.assert_allclose(S[0], P[0])
    np.testing.assert_allclose(S[-1], P[-1])
    assert len(S) == 16
    np.testing.assert_allclose(np.linalg.norm(np.diff(S, axis=0), axis=1), 1.0, atol=1e-12)


def test_press_lips_moves_crossing_stretch_to_midline():
    x = np.arange(0, 11.0)
    upper = np.c_[x, np.full_like(x, 10.0)]
    lower = np.c_[x, np.where(x < 5, 14.0, 6.0)]  # right half drawn above the upper lip
    U, L, pu, pl = press_lips(upper, lower)
    assert pu.sum() == 6 and pl.sum() == 6  # x = 5..10 (interp at 5 is already 6 < 10)
    np.testing.assert_allclose(U[pu, 1], 8.0)
    np.testing.assert_allclose(L[pl, 1], 8.0)
    np.testing.assert_allclose(U[~pu], upper[~pu])
    np.testing.assert_allclose(L[~pl], lower[~pl])


def test_analytic_mouth_silhouettes_and_sides():
    V, F, upper = two_lips(gap=0.4)
    cam = front_camera()
    E = silhouette_edges(V, F, cam)
    s = lip_side(V, F, cam, E.ravel()).reshape(-1, 2)
    assert (s[:, 0] == s[:, 1]).all()
    np.testing.assert_allclose(V[E[s[:, 0] == 1]][..., 1], 0.2, atol=1e-9)
    np.testing.assert_allclose(V[E[s[:, 0] == -1]][..., 1], -0.2, atol=1e-9)
    assert upper[E[s[:, 0] == 1]].all() and not upper[E[s[:, 0] == -1]].any()


def test_refine_moves_silhouettes_onto_sketch():
    V, F, upper = two_lips(gap=0.4)
    V_in = V.copy()
    cam = front_camera()
    X, info = refine_lips(V, F, cam, line_px(cam, 0.1), line_px(cam, -0.1),
                          RefineParams(prior="paper", reach_px=20, free_radius=0.1), return_info=True, fixed=free(V))
    np.testing.assert_array_equal(V, V_in)  # input untouched
    cu = contour_distance(X, F, cam, info["upper_samples"], +1)
    cl = contour_distance(X, F, cam, info["lower_samples"], -1)
    assert cu.mean() < 0.5 and cl.mean() < 0.5, (cu.mean(), cl.mean())  # target: 1 px
    # the mid-lip silhouette vertices moved by the drawn 0.1 (=13.3 px here), up to the
    # soft-constraint equilibrium (3 % short with the paper's weights)
    mid_u = np.flatnonzero((np.abs(V[:, 0]) < 1e-9) & upper & (np.abs(V[:, 1] - 0.2) < 1e-9))
    mid_l = np.flatnonzero((np.abs(V[:, 0]) < 1e-9) & ~upper & (np.abs(V[:, 1] + 0.2) < 1e-9))
    np.testing.assert_allclose((X - V)[mid_u, 1], -0.1, atol=0.004)
    np.testing.assert_allclose((X - V)[mid_l, 1], +0.1, atol=0.004)
    # Laplacian editing: the motion decays; the back of the tubes stays put
    far = np.abs(V[:, 1]) > 0.75
    assert np.abs(X - V)[far].max() < 0.01
    # nothing outside the free region moves at all
    assert (~info["region"]).any()
    assert np.abs(X - V)[~info["region"]].max() == 0.0


def test_lower_drawn_above_upper_presses_lips_together():
    V, F, upper = two_lips(gap=0.4)
    cam = front_camera()
    # crossed sketch: upper drawn at y=-0.05, lower at y=+0.05 -> both go to y=0
    X, info = refine_lips(V, F, cam, line_px(cam, -0.05), line_px(cam, 0.05),
                          RefineParams(iterations=10, prior="paper", crossings="press"), return_info=True,
                          fixed=free(V))
    mid = cam.project(np.array([[0.0, 0, 0]]))[0, 1]
    np.testing.assert_allclose(info["upper_samples"][:, 1], mid, atol=0.5)
    np.testing.assert_allclose(info["lower_samples"][:, 1], mid, atol=0.5)
    i_u = np.flatnonzero((np.abs(V[:, 0]) < 1e-9) & upper & (np.abs(V[:, 1] - 0.2) < 1e-9))
    i_l = np.flatnonzero((np.abs(V[:, 0]) < 1e-9) & ~upper & (np.abs(V[:, 1] + 0.2) < 1e-9))
    assert abs(X[i_u, 1] - X[i_l, 1]).max() < 0.015  # lips meet (they started 0.4 apart)


def test_crossing_drawing_is_followed_as_drawn_by_default():
    """The default reads a crossing as an overlap (one lip in front of the other): the contours are kept as drawn."""
    V, F, upper = two_lips(gap=0.4)
    cam = front_camera()
    up, lo = line_px(cam, -0.05), line_px(cam, 0.05)
    _, info = refine_lips(V, F, cam, up, lo, RefineParams(iterations=2, prior="paper"), return_info=True, fixed=free(V))
    np.testing.assert_allclose(info["upper_samples"][:, 1], up[0, 1], atol=0.5)
    np.testing.assert_allclose(info["lower_samples"][:, 1], lo[0, 1], atol=0.5)
    with pytest.raises(UsageError, match="crossings"):
        refine_lips(V, F, cam, up, lo, RefineParams(crossings="squash"))


def test_fixed_vertices_are_not_lip_candidates_and_barely_move():
    V, F, upper = two_lips(gap=0.4)
    cam = front_camera()
    fixed = ~upper  # the lower lip is "hidden": only the upper may be matched
    with pytest.raises(SketchError, match="lower-lip silhouette"):
        refine_lips(V, F, cam, line_px(cam, 0.1), line_px(cam, -0.1), fixed=fixed)
    # a lip region that leaves the lower lip out names itself in the refusal (and only then)
    with pytest.raises(SketchError, match=r"lower-lip silhouette.*Only the inside of the lip region \(FL_lips\)"):
        refine_lips(V, F, cam, line_px(cam, 0.1), line_px(cam, -0.1), fixed=free(V), lips=upper)
    with pytest.raises(SketchError, match="lower-lip silhouette") as e:
        refine_lips(V, F, cam, line_px(cam, 0.1), line_px(cam, -0.1), fixed=fixed)
    assert "FL_lips" not in str(e.value)
    # the left part of the upper lip fixed: free, its silhouette is matched and moves the full 0.1
    fixed = upper & (V[:, 0] < -0.5)
    up, lo = line_px(cam, 0.1), line_px(cam, -0.1)
    X0, loose = refine_lips(V, F, cam, up, lo, RefineParams(prior="paper"), return_info=True, fixed=free(V))
    X1, held = refine_lips(V, F, cam, up, lo, RefineParams(prior="paper"), fixed=fixed, return_info=True)
    ids = np.flatnonzero(fixed)
    assert np.isin(loose["matched_upper"], ids).any()  # measured 10 (the check below can fail)
    assert not np.isin(np.r_[held["matched_upper"], held["matched_lower"]], ids).any()
    d0, d1 = np.linalg.norm(X0 - V, axis=1)[fixed], np.linalg.norm(X1 - V, axis=1)[fixed]
    assert d1.mean() < 0.1 * d0.mean()  # measured 0.0003 vs 0.0094
    assert d1.max() < 0.5 * d0.max()  # measured 0.029 vs 0.098 (next to the free part, which pulls them)
    assert np.linalg.norm(X1 - V, axis=1)[upper & (V[:, 0] > 0.5)].max() > 0.09  # the free side still moves


def test_bad_input_messages():
    V, F, _ = two_lips()
    cam = front_camera()
    up, lo = line_px(cam, 0.1), line_px(cam, -0.1)
    with pytest.raises(SketchError, match="No lower-lip stroke"):
        refine_lips(V, F, cam, up, [], fixed=free(V))
    with pytest.raises(SketchError, match="leaves the camera frame"):
        refine_lips(V, F, cam, up + [0, 2000], lo, fixed=free(V))
    with pytest.raises(SketchError, match="NaN"):
        bad = up.copy()
        bad[3] = np.nan
        refine_lips(V, F, cam, bad, lo, fixed=free(V))
    Vn = V.copy()
    Vn[7] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        refine_lips(Vn, F, cam, up, lo, fixed=free(Vn))
    Fd = F.copy()
    Fd[0] = [0, 0, 1]
    with pytest.raises(MeshError, match="degenerate"):
        refine_lips(V, Fd, cam, up, lo, fixed=free(V))
    with pytest.raises(CameraError, match="No camera"):
        refine_lips(V, F, None, up, lo, fixed=free(V))
    # camera looking at the mouth from behind (on -z, looking at +z)
    back = Camera.look_at([0, 0, -20], [0, 0, 0], [0, 1, 0], 50, 36, 1920, 1080)
    with pytest.raises(CameraError, match="behind"):
        refine_lips(V, F, back, line_px(back, 0.1), line_px(back, -0.1), fixed=free(V))
    # face behind the camera: camera at +z looking away from the mouth
    away = Camera.look_at([0, 0, 20], [0, 0, 40], [0, 1, 0], 50, 36, 1920, 1080)
    with pytest.raises(CameraError, match="behind the camera"):
        refine_lips(V, F, away, np.array([[900.0, 500], [1000, 500]]), np.array([[900.0, 560], [1000, 560]]),
                    fixed=free(V))


def test_sketch_on_the_current_silhouette_barely_moves_the_mesh():
    # the sketch traces the mesh's own inner silhouettes (y = +-0.2, x in [-1.5, 1.5])
    V, F, _ = two_lips(gap=0.4)
    cam = front_camera()
    X = refine_lips(V, F, cam, line_px(cam, 0.2), line_px(cam, -0.2), RefineParams(prior="paper"), fixed=free(V))
    assert np.abs(X - V).max() < 0.004  # < 0.5 px; only the stroke ends pull at the lip ends
    # the literal per-pixel rays also pull along the contour (x), sliding the lips sideways
    Xp = refine_lips(V, F, cam, line_px(cam, 0.2), line_px(cam, -0.2),
                     RefineParams(silhouette_rays="pixel", prior="paper"), fixed=free(V))
    assert np.abs(Xp - V)[:, 0].max() > 5 * np.abs(X - V)[:, 0].max()


def test_press_lips_by_what_the_crossing_adds_to_the_captured_overlap():
    x = np.arange(0, 11.0)
    upper = np.c_[x, np.full_like(x, 10.0)]
    lower = np.c_[x, np.full_like(x, 6.0)]  # drawn 4 px above the upper lip everywhere
    overlap = np.where(x < 5, 0.0, np.where(x < 8, 2.0, 6.0))  # the capture: apart, 2 px and 6 px overlap
    U, L, pu, pl = press_lips(upper, lower, overlap, overlap)
    np.testing.assert_allclose(U[:, 1], np.where(x < 5, 8.0, np.where(x < 8, 9.0, 10.0)))
    np.testing.assert_allclose(L[:, 1], np.where(x < 5, 8.0, np.where(x < 8, 7.0, 6.0)))
    np.testing.assert_array_equal(pu, x < 8)
    np.testing.assert_array_equal(pl, x < 8)


def test_crossing_sketch_over_lips_that_already_overlap_is_taken_as_drawn():
    """Lips that overlap in the view (lower lip's silhouette 0.2 = 27 px above the upper's), captured 0.05 too
    high: the truth's crossing contours are followed as drawn, not pressed to their mid-line."""
    V, F, upper = two_lips(gap=-0.2)
    C = V.copy()
    C[:, 1] += 0.05
    cam = front_camera()
    X, info = refine_lips(C, F, cam, line_px(cam, -0.1), line_px(cam, 0.1), RefineParams(iterations=10),
                          return_info=True, fixed=free(V))
    mid = cam.project(np.array([[0.0, 0.0, 0.0]]))[0, 1]
    assert info["upper_samples"][:, 1].mean() > mid + 12 and info["lower_samples"][:, 1].mean() < mid - 12
    i_u = np.flatnonzero((np.abs(V[:, 0]) < 1e-9) & upper & (np.abs(V[:, 1] + 0.1) < 1e-9))
    i_l = np.flatnonzero((np.abs(V[:, 0]) < 1e-9) & ~upper & (np.abs(V[:, 1] - 0.1) < 1e-9))
    assert len(i_u) and len(i_l)
    # both lips go back down to the truth (pressed to the mid-line, the upper lip would go up and the lower
    # one down twice as far)
    np.testing.assert_allclose((X - C)[i_u, 1], -0.05, atol=0.005)
    np.testing.assert_allclose((X - C)[i_l, 1], -0.05, atol=0.015)


def test_strokes_shorter_than_the_mouth_do_not_slide_the_lips_sideways():
    """A coarse mouth (silhouette vertices 0.5 apart along the lips) with strokes ending at x = +-1.3, between
    the vertices at 1.0 and 1.5: the end pixels pick the vertices at +-1.5, beyond the strokes' ends. They are
    held to the strokes' tangent lines there, not pulled onto the end samples' rays, so nothing moves along the
    mouth (the end samples' rays pulled them 0.19 sideways, twice the 0.1 the lips close by)."""
    step = np.pi / 24
    Vu, Fu = tube(0.2 + 0.5, -np.pi / 2 - 4 * step, np.pi / 2, 0.5, nt=29, nx=9)
    Vl, Fl = tube(-0.2 - 0.5, -np.pi / 2, np.pi / 2 + 4 * step, 0.5, nt=29, nx=9)
    V, F = np.vstack([Vu, Vl]), np.vstack([Fu, Fl + len(Vu)])
    cam = front_camera()
    up, lo = line_px(cam, 0.1, -1.3, 1.3), line_px(cam, -0.1, -1.3, 1.3)
    X, info = refine_lips(V, F, cam, up, lo, RefineParams(prior="paper", reach_px=40, free_radius=0.2), fixed=free(V),
                          return_info=True)
    assert np.abs(V[info["matched_upper"], 0]).max() == 1.5  # the vertices beyond the ends are matched
    d = X - V
    assert np.abs(d[:, 1]).max() > 0.09  # the lips close to the strokes (0.1 each)
    assert np.abs(d[:, 0]).max() < 0.01, np.abs(d[:, 0]).max()  # measured 0.0036 (end rays: 0.1855)


def test_a_stroke_stopping_short_of_a_curved_lip_does_not_pull_the_lip_onto_its_extension():
    """A coarse mouth (silhouette vertices 1 apart along the lips) curving up toward its ends, ``y += 0.5 x^2``, with
    an error-free capture: the sketch is its silhouettes, the lower stroke drawn only to x = 0.6. The last samples
    pick the vertex at x = 1, 53 px beyond the stroke's end (10 % of the sketch's width), where the straight
    extension of the stroke's end passes 10 px below the curving lip. It gets no term from the stroke (views.END_REACH),
    so nothing moves; held to the end's tangent plane it was pulled 0.057 down (14 % of the 0.4 mouth opening)."""
    step = np.pi / 24
    Vu, Fu = tube(0.2 + 0.5, -np.pi / 2 - 4 * step, np.pi / 2, 0.5, nt=29, nx=5)
    Vl, Fl = tube(-0.2 - 0.5, -np.pi / 2, np.pi / 2 + 4 * step, 0.5, nt=29, nx=5)
    V, F = np.vstack([Vu, Vl]), np.vstack([Fu, Fl + len(Vu)])
    V[:, 1] += 0.5 * V[:, 0] ** 2
    cam = front_camera()

    def curve(y0, x0, x1):
        x = np.linspace(x0, x1, 200)
        return cam.project(np.c_[x, y0 + 0.5 * x**2, np.zeros_like(x)])

    X, info = refine_lips(V, F, cam, curve(0.2, -2, 2), curve(-0.2, -2, 0.6),
                          RefineParams(prior="paper", reach_px=40, free_radius=0.2), fixed=free(V), return_info=True)
    assert 1.0 in V[info["matched_lower"], 0]  # the vertex beyond the end is matched
    d = np.linalg.norm(X - V, axis=1)
    assert d.max() < 0.01, d.max()  # measured 0.0037 (tangent plane at the end: 0.0568 at x = 1)
