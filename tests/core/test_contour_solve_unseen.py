"""Contours must not make the face worse than markers alone, on a face and camera rig the defaults were not tuned on.

Issue 15 (Bhat et al. 2013 §4): the contour fit is tied to the markers-only fit away from the mouth and eyes
(``SolveParams.anchor_weight``) and the corrective is damped outside the contours' regions; checked
against the ground truth of a held-out ICT identity filmed by a held-out camera rig (``testing.solve_cases``).
"""

import numpy as np
import pytest

from facelab_addon.core.lips.mouth import find_mouth
from facelab_addon.core.solve.blendshape_solve import BlendshapeSolver, SolveParams, contour_region
from facelab_addon.core.solve.corrective import CorrectiveParams, OutOfSubspaceCorrective, lip_band
from facelab_addon.core.solve.matching import contour_curve_distance
from facelab_addon.core.solve.performance import PerformanceParams, solve_performance
from facelab_addon.testing.capture_sim import make_capture
from facelab_addon.testing.contour_truth import ict_contour_loops
from facelab_addon.testing.solve_cases import HELD_OUT_CASES, TUNING_CASES, identity_model, layout_cameras
from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP, inner_lip_mask


@pytest.fixture(scope="module")
def held_out(ict):
    """A held-out face (ICT identity006 at -1) seen by the held-out 'low' camera pair, 3 mm peak lip gap."""
    identity, amount, layout = HELD_OUT_CASES[1]
    model = identity_model(ict, identity, amount)
    cap = make_capture(model, n_frames=4, n_markers=80, noise_px=0.5, seed=3, lip_error_mm=3.0, curves=True,
                       cameras=layout_cameras(model, layout))
    loops = ict_contour_loops(model)
    face = model.part_vertex_mask("M_Face")
    mouth = find_mouth(model.neutral, model.faces, ~face, loop=ICT_MOUTH_LOOP)
    lip = inner_lip_mask(model.neutral, model.faces, ~face, mouth=mouth)
    return model, cap, loops, face, lip


def _errors(model, res, cap, face, lip):
    D = model.deltas(cap.names)
    fe, le = [], []
    for t in range(len(cap.truth)):
        X = model.neutral + np.einsum("s,svd->vd", res.weights[t], D)
        if res.correctives is not None:
            X = X + res.correctives[t]
        e = np.linalg.norm(X - cap.truth[t], axis=1) * 10.0  # cm -> mm
        fe.append(e[face].mean())
        le.append(e[lip].mean())
    return float(np.mean(fe)), float(np.mean(le))


def test_held_out_cases_are_not_the_tuning_cases():
    assert not {(i, c) for i, _, c in HELD_OUT_CASES} & {(i, c) for i, _, c in TUNING_CASES}
    assert not {c for _, _, c in HELD_OUT_CASES} & {c for _, _, c in TUNING_CASES}


@pytest.mark.slow
@pytest.mark.parametrize("clean", [False, True], ids=["noise0.5px", "clean"])
def test_contours_never_worsen_the_face_and_help_the_inner_lips_on_a_held_out_capture(held_out, clean):
    model, cap, loops, face, lip = held_out
    px = cap.markers_px_clean if clean else cap.markers_px
    D = model.deltas(cap.names)
    markers = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops)
    r_m = solve_performance(markers, None, px, None, None)
    solver = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops)
    corr = OutOfSubspaceCorrective(model.neutral, model.faces, cap.cameras, cap.markers, None, boundary=~face,
                                   region=contour_region(model.neutral, model.faces, loops))
    r_c = solve_performance(solver, corr, px, None, cap.curves)
    face_m, lip_m = _errors(model, r_m, cap, face, lip)
    face_c, lip_c = _errors(model, r_c, cap, face, lip)
    assert face_c <= face_m, (face_c, face_m)
    assert lip_c < 0.9 * lip_m, (lip_c, lip_m)
    # the previous defaults (no anchor, uniform damping) made this face worse than markers alone
    solver0 = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops,
                               params=SolveParams(anchor_weight=0.0))
    corr0 = OutOfSubspaceCorrective(model.neutral, model.faces, cap.cameras, cap.markers, None, boundary=~face)
    face_0, lip_0 = _errors(model, solve_performance(solver0, corr0, px, None, cap.curves), cap, face, lip)
    assert face_c < face_0 and lip_c < lip_0, (face_c, face_0, lip_c, lip_0)
    if clean:
        assert face_0 > face_m, (face_0, face_m)  # what issue 15 reported: contours made the face worse


@pytest.mark.slow
def test_a_strong_anchor_keeps_the_markers_only_face_outside_the_contour_regions(held_out):
    model, cap, loops, face, lip = held_out
    D = model.deltas(cap.names)
    t = int(np.argmax(cap.lip_error))
    mouth_curves = [c for c in cap.curves[t] if c.name.startswith("mouth")]
    region = contour_region(model.neutral, model.faces, loops)
    far = face & ~region
    w_m = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None).solve_frame(
        cap.markers_px[t], iterations=2).weights
    X_m = model.neutral + np.einsum("s,svd->vd", w_m, D)
    moved = {}
    for k in (0.0, 1e6):
        s = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops,
                             params=SolveParams(anchor_weight=k))
        X = s.vertices(s.solve_frame(cap.markers_px[t], None, mouth_curves).weights)
        moved[k] = float(np.linalg.norm(X - X_m, axis=1)[far].mean()) * 10.0  # mm
    assert moved[1e6] < 0.005, moved  # the face away from the mouth and eyes stays where the markers put it
    assert moved[0.0] > 10 * moved[1e6], moved  # without the anchor the out-of-span lip gap moves it


def test_contour_region_covers_the_lips_and_lids_but_not_the_chin_or_forehead(ict):
    loops = ict_contour_loops(ict)
    region = contour_region(ict.neutral, ict.faces, loops)
    for v in loops.mouth + [x for lp in loops.eyes.values() for x in lp]:
        assert region[np.asarray(v)].all()
    V = ict.neutral
    skin = ict.part_vertex_mask("M_Face")
    mouth_c = V[np.concatenate(loops.mouth)].mean(axis=0)
    chin = skin & (V[:, 1] < mouth_c[1] - 3.0)  # 3 cm below the mouth (ICT is in centimetres)
    forehead = skin & (V[:, 1] > mouth_c[1] + 11.5)  # the upper forehead (the eyes are 7 cm above the mouth)
    assert chin.sum() > 100 and forehead.sum() > 100
    assert not region[chin].any() and not region[forehead].any()
    # scale-free: the same region in metres
    assert (contour_region(V * 0.01, ict.faces, loops) == region).all()


def test_region_damping_applies_inside_the_contour_region_only(ict):
    """Truth inside the rig's span, 1 px marker noise: the corrective only fits noise. A larger damping
    outside the contour region keeps it out there; ``region_damping`` sets the damping inside."""
    names = ["jawOpen", "mouthSmile_L", "browInnerUp_L", "eyeBlink_L"]
    cap = make_capture(ict, names=names, n_frames=1, n_markers=60, noise_px=1.0, seed=4, curves=False)
    loops = ict_contour_loops(ict)
    face = ict.part_vertex_mask("M_Face")
    region = contour_region(ict.neutral, ict.faces, loops)
    s = BlendshapeSolver(ict.neutral, ict.deltas(names), ict.faces, cap.cameras, cap.markers, None)
    Vb = s.vertices(s.solve_frame(cap.markers_px[0], iterations=2).weights)
    err, inside = {}, {}
    for damping, region_damping in ((0.01, 0.01), (0.3, 0.01), (0.01, 0.3)):
        c = OutOfSubspaceCorrective(ict.neutral, ict.faces, cap.cameras, cap.markers, None, boundary=~face,
                                    params=CorrectiveParams(damping=damping, region_damping=region_damping),
                                    region=region)
        dV = c.solve(Vb, cap.markers_px[0])
        err[damping, region_damping] = float(np.linalg.norm(Vb + dV - cap.truth[0], axis=1)[face & ~region].mean())
        inside[damping, region_damping] = float(np.linalg.norm(dV, axis=1)[face & region].mean())
    assert err[0.3, 0.01] < err[0.01, 0.01], err  # outside: noise kept out
    assert inside[0.01, 0.3] < inside[0.01, 0.01], inside  # inside: the region's own damping


def _solve_lip_line(model, cap, loops, face, lip, **kw):
    """(lip line px RMS, face mm, inner-lip mm, result) of the default contour solve with ``kw`` for PerformanceParams."""
    D = model.deltas(cap.names)
    solver = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops)
    corr = OutOfSubspaceCorrective(model.neutral, model.faces, cap.cameras, cap.markers, None, boundary=~face,
                                   region=contour_region(model.neutral, model.faces, loops),
                                   lip_band=lip_band(model.faces, loops, len(model.neutral)))
    res = solve_performance(solver, corr, cap.markers_px, None, cap.curves, params=PerformanceParams(**kw))
    X = [model.neutral + np.einsum("s,svd->vd", res.weights[t], D) + res.correctives[t]
         for t in range(len(cap.truth))]
    px = np.concatenate([contour_curve_distance(X[t], cap.cameras, res.correspondences[t], cap.curves[t])
                         for t in range(len(cap.truth))])
    return (float(np.sqrt(np.mean(px ** 2))),) + _errors(model, res, cap, face, lip) + (res,)


@pytest.mark.slow
def test_the_lip_passes_put_the_visible_lip_line_under_a_pixel_on_a_held_out_low_rig(held_out):
    """The low rig (both cameras under the chin, held out): one corrective pass stops short of the lip curves
    (about 1.3 px RMS on these frames: the contour the rig mesh shows a steep camera can sit several edge rings
    from the truth's, and a damped least-squares pass removes only ~75 % of what the fit leaves). The default
    lip passes (match again on the corrected mesh, solve the lip band again with a heavier line weight) take it
    under 1 px while the face stays no worse than markers alone and the inner lips under 0.8x."""
    model, cap, loops, face, lip = held_out
    D = model.deltas(cap.names)
    markers = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops)
    face_m, lip_m = _errors(model, solve_performance(markers, None, cap.markers_px, None, None), cap, face, lip)
    one = _solve_lip_line(model, cap, loops, face, lip, lip_passes=0)
    new = _solve_lip_line(model, cap, loops, face, lip)
    assert one[0] > 1.0, one[:3]  # what issue 15's follow-up reported: the line stops short on this rig
    assert new[0] < 1.0, (new[:3], one[:3])
    assert new[1] <= face_m and new[2] < 0.8 * lip_m, (new[:3], face_m, lip_m)
    assert new[2] <= one[2], (new[:3], one[:3])  # the lips in 3D are no worse than after one pass


def test_the_lip_band_solve_moves_only_the_lips(held_out):
    """``lip_band_solve`` re-solves the band with the rest of the face held: outside the band ``ΔV`` is exactly
    the first pass's, inside it moves towards the tracked lip line."""
    model, cap, loops, face, lip = held_out
    D = model.deltas(cap.names)
    t = int(np.argmax(cap.lip_error))
    solver = BlendshapeSolver(model.neutral, D, model.faces, cap.cameras, cap.markers, None, loops=loops)
    band = lip_band(model.faces, loops, len(model.neutral))
    corr = OutOfSubspaceCorrective(model.neutral, model.faces, cap.cameras, cap.markers, None, boundary=~face,
                                   region=contour_region(model.neutral, model.faces, loops), lip_band=band)
    res = solver.solve_frame(cap.markers_px[t], None, cap.curves[t])
    Vb = solver.vertices(res.weights)
    cc = solver.match(res.weights, cap.curves[t], previous=res.correspondences)
    d1 = corr.solve(Vb, cap.markers_px[t], None, cc)
    cc2 = solver.match(res.weights, cap.curves[t], previous=cc, vertices=Vb + d1)
    d2 = corr.lip_band_solve(Vb, d1, cap.markers_px[t], None, cc2)
    assert np.array_equal(d2[~band], d1[~band])
    assert np.abs(d2[band] - d1[band]).max() > 1e-3 * float(model.scale)  # the lips did move (scene units)
    mouth = [c for c in cc2 if c.name.startswith("mouth")]
    rms = lambda d: float(np.sqrt(np.mean(contour_curve_distance(Vb + d, cap.cameras, mouth, cap.curves[t]) ** 2)))  # noqa: E731
    assert rms(d2) < 0.7 * rms(d1), (rms(d1), rms(d2))
    assert 200 < band.sum() < 0.2 * face.sum()  # the lips, not the face
    # the optional lip-line pass acts on the band too
    p = PerformanceParams()
    d3 = corr.lip_line_pass(Vb, d2, cap.markers_px[t], None, cc2, cap.curves[t], threshold_px=p.lip_line_threshold_px,
                            curve_threshold_px=p.lip_line_curve_px)
    assert np.array_equal(d3[~band], d1[~band]) and not np.array_equal(d3[band], d2[band])
