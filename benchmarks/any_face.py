"""Benchmark: the artist route through the operators on ICT-FaceKit and on a face that is not ICT's topology.

Faces: the ICT-FaceKit head (26,719 vertices, triangles and quads) and ``testing.remeshed.remeshed_ict``
(ICT decimated to about 11,000 vertices, mostly quads, mirror-symmetric; every expression transferred
barycentrically, so the truth stays known; teeth, gums and eyes as separate parts). Each is put in a
Z-up scene (``testing.route.build_route_scene``) under a head + jaw armature, performing five mouth
expressions over 40 frames, with a keyed ``CaptureError`` key that pulls the inner lips apart (up to
1.25 mm per lip, more as the jaw closes, crossing when it opens): the capture. A frontal camera looks
at the mouth from 40 cm; for two-view refinement the scene also has the lower camera of a helmet rig (35° below
the mouth, looking up at it: it sees how far the lips sit forward) and a witness camera 35° to the side
(``testing.route.CAMERAS``).

The route, as an artist runs it, through the operators: ``facelab.auto_regions`` (automatic: no
selection, no painting), on k = 10 training frames a Grease Pencil sketch of the truth's inner-lip
silhouettes (``testing.route.sketch_truth``) and ``facelab.refine_lips``, then ``facelab.propagate``
over the 40 frames and ``facelab.bake`` to a PC2 file.

Reported per face and case (metres at rest; centimetres; millimetres; metres with the armature
posed: head turned 20°, jaw 5°; metres at rest and posed with two views, the main camera and the lower one,
and at rest with the main and the side camera):

* Refine on the training frames: image-space contour error (px, before -> after) and the 3D
  inner-lip RMS cut (target >= 50 % with one view, >= 70 % with two views; every camera sketched on the
  frame is a view of the one Refine Lips solve);
* how much of the Refine correction Propagate's regression reproduces on its own training frames;
* Propagate on the 30 held-out frames: inner-lip RMS as a share of the capture's (target <= 50 %);
* Auto Regions: how much of the capture error lies in ``FL_lips`` (and in the trusted ``FL_mouth``);
* the inner-lip RMS error along the main camera's rays (``depth_rms_mm_before`` / ``_after``: what one view
  cannot see);
* the most a Refine that moves only the inside of ``FL_lips`` could cut (its border and everything outside keep
  the capture's error: ``best_possible_cut_pct``);
* the largest movement outside ``FL_mouth`` and ``FL_lips``, on held-out frames (Propagate) and on
  training frames (Refine) (target <= 0.01 mm);
* seconds per step.

``--errors``: so Refine's defaults are not fitted to one capture error, metres at rest, one view and + the lower
camera, for each capture error model of ``testing.route.ERRORS`` (wide: today's 8 mm lip gap; narrow: 3 mm, at the
lip contact; corners: the mouth corners pulled in; roll: the lips' red part rolled in, mostly depth) and the wide one
with a hand's 1.5 px sketch jitter (``testing.route.jitter_stroke``), Refine Lips with each prior (band, smooth,
paper; set in the shot's Refine settings, which the operator reads) and the held-out Propagate; JSON with the
runs, a ``table`` (face x error x views x prior) and ``mean_by_prior``. No bake, no picture. About 5-6 minutes.

``--face makehuman``: instead of the two ICT faces, MakeHuman's CC0 head (``testing.makehuman``: its own topology,
ICT's mouth shapes carried over by deformation transfer; read from ``FACELAB_MAKEHUMAN_OBJ``, skipped without it).
``--train``: other training frames. A Refine Lips refusal is recorded in the run (``refusal``, ``error``).

Usage: ``PYTHONPATH=. python benchmarks/any_face.py [--quick | --views | --errors [--error-models corners,wide] [--priors band]]
[--face makehuman] [--train 2,6,10] [--png docs/images/any_face.png]``.
Prints one JSON object on stdout (save it as ``benchmarks/results/any_face.json``; the ``--views`` comparison,
metres, at rest and posed, one view / + lower camera / + side camera, printed as JSON);
Blender's own output goes to stderr. About 8-12 minutes on 2 shared cores (``--quick``: metres, unposed, one view and
two with the lower camera, about 3).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _harness import blender_session, json_stdout, log, since  # noqa: E402

FRAMES = np.arange(1, 41)
TRAIN = list(range(2, 41, 4))  # k = 10
#: (units, armature posed, the cameras sketched besides the main one). Two views: the main camera and the lower
#: camera of a helmet rig (``Camera.below``, 35 degrees below the mouth looking up: depth), or a witness camera 35
#: degrees to the side (``Camera.side``: little depth); see ``testing.route.CAMERAS``.
CASES = [("m", False, ()), ("cm", False, ()), ("mm", False, ()), ("m", True, ()),
         ("m", False, ("Camera.below",)), ("m", True, ("Camera.below",)), ("m", False, ("Camera.side",))]
QUICK = [("m", False, ()), ("m", False, ("Camera.below",))]
VIEWS = [("m", False, ()), ("m", True, ()), ("m", False, ("Camera.below",)), ("m", True, ("Camera.below",)),
         ("m", False, ("Camera.side",)), ("m", True, ("Camera.side",))]
#: The --errors mode: (capture error model of ``testing.route.ERRORS``, sketch noise in px), each in metres at rest,
#: one view and + the lower camera, with each of Refine's priors.
ERROR_CASES = [("wide", 0.0), ("narrow", 0.0), ("corners", 0.0), ("roll", 0.0), ("wide", 1.5)]
ERROR_VIEWS = [(), ("Camera.below",)]
PRIORS = ["band", "smooth", "paper"]


def _rms(a):
    return float(np.sqrt(np.mean(np.asarray(a, dtype=np.float64) ** 2)))


def run_route(face, units, posed, tmp, log, extra=(), *, error="wide", noise_px=0.0, prior=None, bake=True, seed=0,
              scene_kw=None):
    """The route on ``face`` (see the module docstring); ``seed``: the sketch jitter's; ``scene_kw``: more keyword
    arguments of ``testing.route.build_route_scene`` (cameras, an imported mesh: ``benchmarks/route_sweep.py``)."""
    import bpy

    from facelab_addon.blender import caches
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
    from facelab_addon.core.geometry.silhouette import contour_distance
    from facelab_addon.core.lips.regressor import LipRegressor
    from facelab_addon.core.lips.regions import faces_in_region
    from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP
    from facelab_addon.pipeline.propagate import training_input
    from facelab_addon.testing.route import build_route_scene, sketch_truth

    views = 1 + len(extra)
    out = dict(units=units, armature_posed=posed, views=views, cameras=["Camera", *extra])
    if prior is not None:  # the --errors mode: the capture error's model, the sketch noise, Refine's prior
        out.update(error_model=error, sketch_noise_px=noise_px, prior=prior)
    t = {}
    t0 = time.perf_counter()
    rs = build_route_scene(face, units=units, armature=True, pose=posed, frames=FRAMES, error=error,
                           **(scene_kw or {}))
    t["build_scene"] = time.perf_counter() - t0
    scene, obj = rs.scene, rs.obj
    scene.facelab.face = obj
    if prior is not None:  # through the shot's Refine settings, which the operator reads
        from facelab_addon.pipeline.refine import RefineSettings
        from facelab_addon.pipeline.shot_settings import ensure_initialized, entry_for, scene_settings

        ensure_initialized(scene, entry_for(RefineSettings))
        scene.facelab_refine.prior = prior
        assert scene_settings(scene, RefineSettings).prior == prior
    mm = rs.mm_per_unit
    out["vertices"] = len(obj.data.vertices)
    out["quads"] = int(sum(len(p.vertices) == 4 for p in obj.data.polygons))
    tris = mesh_triangles(obj.data)
    captured = caches.evaluate_frames(obj, list(FRAMES)).astype(np.float64)  # FaceLab keys muted (none yet)
    truth = rs.evaluated_truth(FRAMES)

    # Auto Regions, automatic
    t0 = time.perf_counter()
    res = bpy.ops.facelab.auto_regions()
    t["auto_regions"] = time.perf_counter() - t0
    if res != {"FINISHED"}:
        out["error"] = "Auto Regions failed"
        return out, None
    mouth, lips = vertex_group_mask(obj, MOUTH_GROUP), vertex_group_mask(obj, LIPS_GROUP)
    # does FL_lips cover what the capture gets wrong (and the trusted FL_mouth stay clear of it)?
    e = np.linalg.norm(rs.error, axis=1)
    out["auto_regions"] = dict(mouth_vertices=int(mouth.sum()), lip_vertices=int(lips.sum()),
                               capture_error_in_lips_pct=round(100 * float(e[lips].sum() / e.sum()), 1),
                               capture_error_in_mouth_only_pct=round(100 * float(e[mouth & ~lips].sum() / e.sum()),
                                                                     1))

    # sketch and Refine the training frames (one view; or two: every camera sketched on the frame is a view)
    cam0 = rs.cameras[0]
    px_before, px_after, sk = [], [], {}
    t0 = time.perf_counter()
    for f in TRAIN:
        for name in extra:  # every camera sketched on the frame is a view of the same Refine Lips solve
            sketch_truth(rs, f, next(c for c in rs.cameras if c.name == name), noise_px=noise_px, seed=seed)
        gp, up, lo = sketch_truth(rs, f, cam0, noise_px=noise_px, seed=seed)
        sk[f] = (up, lo)
        scene.facelab.sketch = gp
        scene.frame_set(f)
        bpy.context.view_layer.objects.active = obj
        try:
            res = bpy.ops.facelab.refine_lips()
        except RuntimeError as exc:  # the operator refused (its report), e.g. a sketch it reads as mis-drawn
            res, out["refusal"] = None, str(exc).strip()
        if res != {"FINISHED"}:
            out["error"] = f"Refine Lips failed on frame {f}"
            return out, None
    t["refine_10_frames"] = time.perf_counter() - t0
    refined = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=()).astype(np.float64)
    it = np.searchsorted(FRAMES, TRAIN)
    M = np.array(obj.matrix_world)
    cam = camera_from_blender(scene, cam0)
    for k, f in enumerate(TRAIN):
        up, lo = sk[f]
        for X, acc in ((captured[it[k]], px_before), (refined[k], px_after)):
            Xw = X @ M[:3, :3].T + M[:3, 3]
            d = np.r_[contour_distance(Xw, tris, cam, up, +1, candidates=rs.inner_lips),
                      contour_distance(Xw, tris, cam, lo, -1, candidates=rs.inner_lips)]
            acc.append(float(np.mean(d[np.isfinite(d)])))
    il = rs.inner_lips
    e_cap = np.linalg.norm(captured[it] - truth[it], axis=2)[:, il] * mm
    e_ref = np.linalg.norm(refined - truth[it], axis=2)[:, il] * mm
    rkey = "refine_one_view" if views == 1 else "refine_two_views"
    out[rkey] = dict(contour_px_before=round(float(np.mean(px_before)), 2),
                                  contour_px_after=round(float(np.mean(px_after)), 2),
                                  inner_lip_rms_mm_before=round(_rms(e_cap), 4),
                                  inner_lip_rms_mm_after=round(_rms(e_ref), 4),
                                  rms_cut_pct=round(100 * (1 - _rms(e_ref) / _rms(e_cap)), 1),
                     target_cut_pct=50 if views == 1 else 70)
    moved = np.linalg.norm(refined - captured[it], axis=2) * mm
    out[rkey]["max_move_outside_lips_mm"] = round(float(moved[:, ~lips].max()), 4)
    # the most any Refine that moves only the inside of FL_lips could cut: its held border and everything
    # outside keep the capture's error
    inside = lips[tris].all(axis=1)
    free = np.zeros(len(lips), bool)
    free[tris[inside].ravel()] = True
    free[tris[~inside].ravel()] = False
    held = np.sum(e_cap[:, ~free[il]] ** 2) / np.sum(e_cap**2)
    out[rkey]["best_possible_cut_pct"] = round(100 * (1 - float(np.sqrt(held))), 1)
    # the error along the main camera's rays (the depth one view cannot see), before and after
    Tw = truth[it][:, il] @ M[:3, :3].T + M[:3, 3]
    ray = Tw - cam.center
    ray /= np.linalg.norm(ray, axis=2, keepdims=True)
    for key, X in (("before", captured[it]), ("after", refined)):
        dz = np.einsum("tvc,tvc->tv", (X[:, il] - truth[it][:, il]) @ M[:3, :3].T, ray) * mm / float(np.cbrt(
            abs(np.linalg.det(M[:3, :3]))))
        out[rkey][f"depth_rms_mm_{key}"] = round(_rms(dz), 4)

    # how much of the Refine correction the regression reproduces on its own training frames
    mf, lf = faces_in_region(tris, mouth), faces_in_region(tris, lips)
    reg = LipRegressor(_rest(obj), tris, mf, lf)
    reg.fit(training_input(captured[it], refined, reg.interior_vertices))
    pred = reg.predict(captured[it])
    lv = reg.lip_vertices
    want = refined[:, lv] - captured[it][:, lv]
    miss = pred[:, lv] - refined[:, lv]
    out["propagate_reproduces_refine_pct"] = round(100 * (1 - _rms(miss) / max(_rms(want), 1e-30)), 2)

    # Propagate, Bake
    t0 = time.perf_counter()
    res = bpy.ops.facelab.propagate(frame_start=int(FRAMES[0]), frame_end=int(FRAMES[-1]), suggestions=0)
    t["propagate"] = time.perf_counter() - t0
    if res != {"FINISHED"}:
        out["error"] = "Propagate failed"
        return out, None
    final = caches.evaluate_frames(obj, list(FRAMES), mute_shape_keys_prefix=()).astype(np.float64)
    held = ~np.isin(FRAMES, TRAIN)
    e_c = np.linalg.norm(captured[held] - truth[held], axis=2)[:, il] * mm
    e_p = np.linalg.norm(final[held] - truth[held], axis=2)[:, il] * mm
    out["propagate_held_out"] = dict(frames=int(held.sum()), training_frames=len(TRAIN),
                                     inner_lip_rms_mm_capture=round(_rms(e_c), 4),
                                     inner_lip_rms_mm_after=round(_rms(e_p), 4),
                                     after_pct_of_capture=round(100 * _rms(e_p) / _rms(e_c), 1), target_pct=50)
    outside = ~(mouth | lips)
    mv = np.linalg.norm(final - captured, axis=2)[:, outside] * mm
    out["max_move_outside_mouth_area_mm"] = dict(
        held_out_frames=round(float(mv[held].max()), 5), training_frames=round(float(mv[~held].max()), 5),
        target=0.01, ok=bool(mv.max() <= 0.01))
    if bake:
        t0 = time.perf_counter()
        path = str(Path(tmp) / f"{obj.name}_{units}_{int(posed)}.pc2")
        res = bpy.ops.facelab.bake(filepath=path, format="PC2", overwrite=True)
        t["bake"] = time.perf_counter() - t0
        out["bake"] = dict(ok=res == {"FINISHED"} and os.path.exists(path),
                           mb=round(os.path.getsize(path) / 1e6, 2) if os.path.exists(path) else None)
    out["seconds"] = {k: round(v, 2) for k, v in t.items()}
    per_frame = dict(capture=np.sqrt(np.mean((np.linalg.norm(captured - truth, axis=2)[:, il] * mm) ** 2, axis=1)),
                     after=np.sqrt(np.mean((np.linalg.norm(final - truth, axis=2)[:, il] * mm) ** 2, axis=1)))
    pic = dict(per_frame=per_frame, V=rs.neutral, F=tris, mouth=mouth, lips=lips, loop=rs.loop, skin=rs.face_mask)
    tag = f" error={error} noise={noise_px} prior={prior}" if prior is not None else ""
    log(f"{units} posed={posed} cameras={out['cameras']}{tag}: refine cut {out[rkey]['rms_cut_pct']} %, held-out "
        f"{out['propagate_held_out']['after_pct_of_capture']} %, outside {out['max_move_outside_mouth_area_mm']}")
    return out, pic


def _rest(obj):
    from facelab_addon.blender.shapekeys import rest_vertices

    return rest_vertices(obj)


def views_panel(ax, faces):
    """Bar chart: Refine's 3D inner-lip RMS cut per face, camera set, at rest and posed (metres runs)."""
    sets = [("Camera",), ("Camera", "Camera.below"), ("Camera", "Camera.side")]
    labels = ["main camera", "+ lower camera (35° below)", "+ side camera (35°)"]
    colours = ["tab:gray", "tab:blue", "tab:orange"]
    groups = [(f, posed) for f in faces for posed in (False, True)]
    width = 0.8 / len(sets)
    for k, (cams, lab, col) in enumerate(zip(sets, labels, colours)):
        xs, ys = [], []
        for g, (face, posed) in enumerate(groups):
            for r in faces[face]["runs"]:
                if r.get("units") == "m" and r.get("armature_posed") == posed and tuple(r.get("cameras", ())) == cams:
                    res = r.get("refine_one_view" if len(cams) == 1 else "refine_two_views")
                    if res:
                        xs.append(g + (k - 1) * width)
                        ys.append(res["rms_cut_pct"])
        ax.bar(xs, ys, width, color=col, label=lab)
        if k == 0:  # what a perfect solve of the inside of FL_lips would cut (its border held)
            for g, (face, posed) in enumerate(groups):
                best = [r["refine_one_view"].get("best_possible_cut_pct") for r in faces[face]["runs"]
                        if r.get("refine_one_view") and r.get("armature_posed") == posed and r.get("units") == "m"]
                if best and best[0] is not None:
                    ax.plot([g - 0.45, g + 0.45], [best[0]] * 2, "k-", lw=1.2,
                            label="best possible (FL_lips border held)" if g == 0 else None)
        for x, y in zip(xs, ys):
            ax.text(x, y + 0.8, f"{y:.0f}", ha="center", fontsize=7)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels([f"{f.split(' (')[0]}\n{'head nodded 20°' if p else 'at rest'}" for f, p in groups], fontsize=8)
    ax.axhline(70, color="k", ls=":", lw=0.8)
    ax.text(len(groups) - 0.5, 71, "two-view target", ha="right", fontsize=7)
    ax.set_ylabel("Refine: 3D inner-lip RMS cut, %")
    ax.set_ylim(0, 80)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title("Refine from one and two cameras (10 sketched frames)", fontsize=10)


def picture(path, pics, faces=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    three = bool(faces) and any(len(r.get("cameras", ())) > 1 for f in faces.values() for r in f["runs"])
    fig, ax = plt.subplots(2, 3 if three else 2, figsize=(18 if three else 12, 8), squeeze=False)
    if three:
        gs = ax[0, 2].get_gridspec()
        ax[0, 2].remove()
        ax[1, 2].remove()
        views_panel(fig.add_subplot(gs[:, 2]), faces)
    for col, (name, p) in enumerate(pics.items()):
        a = ax[0, col]
        a.plot(FRAMES, p["per_frame"]["capture"], "-", color="0.5", label="capture")
        a.plot(FRAMES, p["per_frame"]["after"], "-", color="tab:blue", label="FaceLab (Propagate)")
        it = np.searchsorted(FRAMES, TRAIN)
        a.plot(TRAIN, p["per_frame"]["after"][it], "o", color="tab:orange", label="sketched + Refine")
        a.set_title(f"{name}: inner-lip error per frame (k = {len(TRAIN)})", fontsize=10)
        a.set_xlabel("frame")
        a.set_ylabel("RMS mm")
        a.legend(fontsize=8)
        # the regions Auto Regions found, front view of the rest mesh around the mouth
        b = ax[1, col]
        V, F = p["V"], p["F"]
        c = V[p["loop"]].mean(axis=0)
        w = np.ptp(V[p["loop"], 0])
        sel = (np.abs(V[F, 0] - c[0]) < 1.2 * w).all(1) & (np.abs(V[F, 2] - c[2]) < 0.8 * w).all(1)
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        sel &= (n[:, 1] < 0) & p["skin"][F].all(1)  # skin facing the front camera (-y)
        Fs = F[sel]
        col_f = np.where(p["lips"][Fs].all(1), 2, np.where(p["mouth"][Fs].all(1), 1, 0))
        cm = matplotlib.colors.ListedColormap(["0.85", "tab:blue", "tab:red"])
        b.tripcolor(V[:, 0], V[:, 2], Fs, facecolors=col_f, cmap=cm, edgecolors="0.3", linewidth=0.15,
                    vmin=0, vmax=2)
        b.plot(V[p["loop"], 0], V[p["loop"], 2], ".", color="yellow", ms=2)
        b.set_xlim(c[0] - 1.2 * w, c[0] + 1.2 * w)
        b.set_ylim(c[2] - 0.8 * w, c[2] + 0.8 * w)
        b.set_aspect("equal")
        b.set_axis_off()
        b.set_title(f"{name}: Auto Regions\n(blue FL_mouth, red FL_lips, yellow: the truth's lip contact line)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def errors_case(face, error, noise_px, log):
    """The route on ``face`` with one capture error model (``testing.route.ERRORS``) and sketch noise: metres, at
    rest, under the armature; one scene, Auto Regions once, the sketches drawn once; for each view set of
    :data:`ERROR_VIEWS` and each prior of :data:`PRIORS` (set in the shot's Refine settings, which the operator
    reads), FaceLab's keys removed, Refine Lips on the training frames and Propagate, through the operators.
    Returns the table rows."""
    import bpy

    from facelab_addon.blender import caches
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
    from facelab_addon.blender.shapekeys import remove_keys
    from facelab_addon.core.geometry.silhouette import contour_distance
    from facelab_addon.names import LIPS_GROUP, MOUTH_GROUP, PREFIX
    from facelab_addon.pipeline.refine import RefineSettings
    from facelab_addon.testing.route import build_route_scene, sketch_truth
    from facelab_addon.pipeline.shot_settings import ensure_initialized, entry_for, scene_settings

    rs = build_route_scene(face, units="m", armature=True, frames=FRAMES, error=error)
    scene, obj = rs.scene, rs.obj
    scene.facelab.face = obj
    ensure_initialized(scene, entry_for(RefineSettings))
    mm, il = rs.mm_per_unit, rs.inner_lips
    tris = mesh_triangles(obj.data)
    captured = caches.evaluate_frames(obj, list(FRAMES)).astype(np.float64)
    truth = rs.evaluated_truth(FRAMES)
    base = dict(error=error, noise_px=noise_px)
    if bpy.ops.facelab.auto_regions() != {"FINISHED"}:
        return [dict(base, failed="Auto Regions failed")]
    lips, mouth = vertex_group_mask(obj, LIPS_GROUP), vertex_group_mask(obj, MOUTH_GROUP)
    it = np.searchsorted(FRAMES, TRAIN)
    held = ~np.isin(FRAMES, TRAIN)
    err = lambda X, i: np.linalg.norm(X - truth[i], axis=2)[:, il] * mm  # noqa: E731
    cap_train, cap_held = _rms(err(captured[it], it)), _rms(err(captured[held], held))
    M = np.array(obj.matrix_world)
    cam0 = rs.cameras[0]
    cam = camera_from_blender(scene, cam0)
    rows, sk = [], {}
    for extra in ERROR_VIEWS:
        for f in TRAIN:  # the main camera's sketches once; a second camera's added for the two-view runs
            for name in extra:
                sketch_truth(rs, f, next(c for c in rs.cameras if c.name == name), noise_px=noise_px)
            if f not in sk:
                sk[f] = sketch_truth(rs, f, cam0, noise_px=noise_px)
        for prior in PRIORS:
            remove_keys(obj, PREFIX)  # back to the capture
            obj.facelab.training_frames.clear()
            scene.facelab_refine.prior = prior
            assert scene_settings(scene, RefineSettings).prior == prior
            row = dict(base, views=1 + len(extra), prior=prior)
            t0 = time.perf_counter()
            for f in TRAIN:
                scene.facelab.sketch = sk[f][0]
                scene.frame_set(f)
                bpy.context.view_layer.objects.active = obj
                if bpy.ops.facelab.refine_lips() != {"FINISHED"}:
                    row["failed"] = f"Refine Lips failed on frame {f}"
                    break
            if "failed" in row:
                rows.append(row)
                continue
            refined = caches.evaluate_frames(obj, TRAIN, mute_shape_keys_prefix=()).astype(np.float64)
            px = []
            for k, f in enumerate(TRAIN):
                Xw = refined[k] @ M[:3, :3].T + M[:3, 3]
                d = np.r_[contour_distance(Xw, tris, cam, sk[f][1], +1, candidates=il),
                          contour_distance(Xw, tris, cam, sk[f][2], -1, candidates=il)]
                px.append(float(np.mean(d[np.isfinite(d)])))
            res = bpy.ops.facelab.propagate(frame_start=int(FRAMES[0]), frame_end=int(FRAMES[-1]), suggestions=0)
            if res != {"FINISHED"}:
                rows.append(dict(row, failed="Propagate failed"))
                continue
            final = caches.evaluate_frames(obj, list(FRAMES), mute_shape_keys_prefix=()).astype(np.float64)
            moved = np.linalg.norm(final - captured, axis=2)[:, ~(mouth | lips)].max() * mm
            row.update(inner_lip_rms_mm_capture=round(cap_train, 4),
                       refine_cut_pct=round(100 * (1 - _rms(err(refined, it)) / cap_train), 1),
                       contour_px_after=round(float(np.mean(px)), 2),
                       held_out_pct_of_capture=round(100 * _rms(err(final[held], held)) / cap_held, 1),
                       max_move_outside_mouth_area_mm=round(float(moved), 5),
                       seconds=round(time.perf_counter() - t0, 2))
            log(f"errors: {error} noise={noise_px} views={row['views']} prior={prior}: refine cut "
                f"{row['refine_cut_pct']} %, held-out {row['held_out_pct_of_capture']} %")
            rows.append(row)
    return rows


def errors_mode(faces, log, error_models=None):
    """Every (face, capture error model and sketch noise, views, prior) of :data:`ERROR_CASES`, :data:`ERROR_VIEWS`,
    :data:`PRIORS`: ``{"table": [...], "mean_by_prior": {...}}``. ``error_models``: only these (names of
    ``testing.route.ERRORS``; default all)."""
    table = []
    for name, face in faces.items():
        for error, noise in ERROR_CASES:
            if error_models is not None and error not in error_models:
                continue
            table += [dict(face=name, **r) for r in errors_case(face, error, noise, log)]
    mean = {}
    for views in (1, 2):
        for prior in PRIORS:
            rows = [t for t in table if t.get("views") == views and t.get("prior") == prior and "failed" not in t]
            if rows:
                mean[f"{views}view_{prior}"] = dict(
                    refine_cut_pct=round(float(np.mean([t["refine_cut_pct"] for t in rows])), 1),
                    held_out_pct_of_capture=round(float(np.mean([t["held_out_pct_of_capture"] for t in rows])), 1),
                    worst_refine_cut_pct=min(t["refine_cut_pct"] for t in rows),
                    worst_held_out_pct=max(t["held_out_pct_of_capture"] for t in rows), runs=len(rows))
    return dict(table=table, mean_by_prior=mean)


def errors_picture(path, table, faces):
    """Top: each capture error model on each face (front view of the mouth, colour: error size in mm; roll's is
    mostly depth). Bottom: Refine's 3D inner-lip RMS cut per face, error model, views and prior."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from facelab_addon.testing.lip_truth import truth_line
    from facelab_addon.testing.route import _ZUP, ERRORS, capture_error

    kinds = list(ERRORS)
    fig = plt.figure(figsize=(4 * len(kinds), 11))
    gs = fig.add_gridspec(1 + len(faces), len(kinds), height_ratios=[1] * len(faces) + [1.6])
    for row, (name, face) in enumerate(faces.items()):
        V = face.neutral @ _ZUP.T * 10.0  # millimetres, Z-up
        F = np.asarray(face.faces)
        skin = np.asarray(face.part_vertex_mask("M_Face"))
        loop = truth_line(face).loop  # the route scene's own truth line (not the detector under test)
        tri = F[:, :3] if F.shape[1] >= 3 else F
        for col, kind in enumerate(kinds):
            e, _ = capture_error(V, F, loop, skin, 10.0, 1.25, kind)  # mm (10 units per cm)
            n = np.linalg.norm(e, axis=1)
            a = fig.add_subplot(gs[row, col])
            c = V[loop].mean(axis=0)
            w = np.ptp(V[loop, 0])
            nrm = np.cross(V[tri[:, 1]] - V[tri[:, 0]], V[tri[:, 2]] - V[tri[:, 0]])
            sel = (np.abs(V[tri, 0] - c[0]) < 0.8 * w).all(1) & (np.abs(V[tri, 2] - c[2]) < 0.5 * w).all(1)
            sel &= (nrm[:, 1] < 0) & skin[tri].all(1)
            tc = a.tripcolor(V[:, 0], V[:, 2], tri[sel], n, cmap="magma", vmin=0, vmax=1.25, shading="gouraud")
            big = np.flatnonzero(n > 0.3)[::7]
            a.quiver(V[big, 0], V[big, 2], e[big, 0], e[big, 2], color="cyan", angles="xy", scale_units="xy",
                     scale=0.25, width=0.004)  # in-plane part, 4x
            a.set_xlim(c[0] - 0.8 * w, c[0] + 0.8 * w)
            a.set_ylim(c[2] - 0.5 * w, c[2] + 0.5 * w)
            a.set_aspect("equal")
            a.set_axis_off()
            a.set_title(f"{name.split(' (')[0]}: {kind}", fontsize=9)
        fig.colorbar(tc, ax=a, fraction=0.04, label="error, mm")
    b = fig.add_subplot(gs[len(faces), :])
    cases = []
    for t in table:
        c = (t["face"], t["error"], t["noise_px"], t["views"])
        if c not in cases:
            cases.append(c)
    colours = {"band": "tab:blue", "smooth": "tab:orange", "paper": "tab:gray"}
    for k, prior in enumerate(PRIORS):
        ys = [next((t.get("refine_cut_pct", np.nan) for t in table if (t["face"], t["error"], t["noise_px"],
                                                                       t["views"]) == c and t["prior"] == prior),
                   np.nan) for c in cases]
        b.bar(np.arange(len(cases)) + (k - 1) * 0.27, ys, 0.27, color=colours[prior], label=f"prior {prior}")
    b.set_xticks(range(len(cases)))
    b.set_xticklabels([f"{f.split(' (')[0].replace('ICT-FaceKit', 'ICT').replace('ICT remeshed', 'remeshed')}\n{e}"
                       f"{' +%.1fpx' % n if n else ''}\n{v} view{'s' if v > 1 else ''}" for f, e, n, v in cases],
                      fontsize=7)
    b.set_ylabel("Refine: 3D inner-lip RMS cut, %")
    b.axhline(0, color="k", lw=0.5)
    b.legend(fontsize=8)
    b.set_title("Refine on 10 sketched frames, metres at rest, per capture error model (testing.route.ERRORS)",
                fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="metres, unposed only (one view; two with Camera.below)")
    ap.add_argument("--views", action="store_true",
                    help="only the view comparison: metres, at rest and posed, one view, + Camera.below, + Camera.side")
    ap.add_argument("--errors", action="store_true",
                    help="only the error-model comparison: metres at rest, one view and + Camera.below, every capture "
                         "error model (and the wide one with 1.5 px sketch noise), Refine with each prior")
    ap.add_argument("--error-models", default=None,
                    help="--errors: only these comma-separated error models (e.g. corners,wide,narrow)")
    ap.add_argument("--priors", default=None, help="--errors: only these comma-separated priors (e.g. band)")
    ap.add_argument("--png", default=None, help="write the picture here (e.g. docs/images/any_face.png)")
    ap.add_argument("--face", choices=["ict", "makehuman"], default="ict",
                    help="ict: ICT-FaceKit and its remesh (default); makehuman: MakeHuman's CC0 head with ICT's mouth "
                         "shapes by deformation transfer (testing.makehuman; needs FACELAB_MAKEHUMAN_OBJ)")
    ap.add_argument("--train", default=None,
                    help="comma-separated training frames (default 2,6,...,38)")
    args = ap.parse_args(argv)
    if args.train:
        global TRAIN
        TRAIN = [int(f) for f in args.train.split(",")]
    if args.priors:
        global PRIORS
        PRIORS = [p for p in PRIORS if p in args.priors.split(",")]
    out_json = json_stdout()  # Blender prints to stdout; keep it for the JSON alone
    tmp = tempfile.mkdtemp(prefix="facelab-anyface-")
    t_all = time.perf_counter()
    with blender_session() as bpy:
        from facelab_addon.core.capture.ict import load_ict
        from facelab_addon.testing.remeshed import remeshed_ict

        ict = load_ict()
        if args.face == "makehuman":
            from facelab_addon.testing import makehuman

            if makehuman.makehuman_obj_path() is None:
                out_json.emit(dict(skipped=f"needs MakeHuman's mesh: {makehuman.HOW_TO}"))
                return 0
            faces = {"MakeHuman (CC0, ICT shapes by DT)": makehuman.makehuman_head(ict=ict)}
        else:
            faces = {"ICT-FaceKit": ict, "ICT remeshed (quads)": remeshed_ict(ict)}
        out = dict(bpy_version=bpy.app.version_string, frames=len(FRAMES), training_frames=TRAIN, faces={})
        pics = {}
        if args.errors:
            out.update(errors_mode(faces, log, args.error_models.split(",") if args.error_models else None))
            if args.png:
                errors_picture(args.png, out["table"], faces)
                out["picture"] = args.png
            out["total_s"] = since(t_all, 1)
            out_json.emit(out)
            return 0
        for name, face in faces.items():
            runs = []
            for units, posed, extra in (QUICK if args.quick else VIEWS if args.views else CASES):
                r, pic = run_route(face, units, posed, tmp, log, extra)
                runs.append(r)
                if pic is not None and units == "m" and not posed and not extra:
                    pics[name] = pic
            ok = [r for r in runs if "error" not in r and r["views"] == 1 and not r["armature_posed"]]  # units only
            agree = None
            if len(ok) > 1:
                keys = [("refine_one_view", "rms_cut_pct"), ("propagate_held_out", "after_pct_of_capture")]
                agree = {f"{a}.{b}": [r[a][b] for r in ok] for a, b in keys}
            out["faces"][name] = dict(runs=runs, units_agree=agree)
        out["total_s"] = since(t_all, 1)
        if args.png and pics:
            picture(args.png, pics, out["faces"])
            out["picture"] = args.png
        out_json.emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
