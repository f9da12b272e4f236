"""Demo step 3: Solve Performance + Retarget (Bhat et al. 2013) from a stereo helmet capture.

The ICT face is captured by a simulated helmet stereo pair (``testing.capture_sim``):
painted markers on the skin, a smooth rig performance and, on top of it, an
inner-lip deformation the rig cannot express (the lips fail to close, up to
2.5 mm). The artist's scene, built through the operators as in production:

* two Movie Clips (image sequences: the truth rendered with Cycles from each helmet
  camera, with the painted dots) with one track per marker at its projected pixel
  (0.3 px noise), calibrated cameras;
* inner-lip contours: a shape-keyed Mask over clip 1 and Grease Pencil strokes
  drawn through camera 2;
* Bind Tracks on the neutral frame, Solve Performance (markers only first, kept
  as a baked copy, then markers + contours + corrective), Retarget to a creature
  (ICT with a widened mouth, ``testing.creature.widen_mouth``), left in view 30 cm
  beside the actor.

Writes out/demo/solve.blend, out/demo/solve_summary.json (errors vs the truth)
and docs/images/demo_solve_*.png.
"""

from __future__ import annotations

import atexit
import json
import time

import numpy as np

SCALE = 0.01  # ICT centimetres -> metres
EXPR = ["jawOpen", "mouthSmile_L", "mouthSmile_R", "mouthFunnel", "mouthPucker", "mouthLowerDown_L",
        "mouthLowerDown_R", "mouthUpperUp_L", "mouthUpperUp_R", "browInnerUp_L", "browInnerUp_R", "eyeBlink_L",
        "eyeBlink_R"]
N_FRAMES = 8  # frame 0 is the neutral (bind frame)
N_MARKERS = 60
NOISE_PX = 0.3
LIP_ERROR_MM = 2.5
N_MASK_POINTS = 24
MASK_NAMES = {"Upper lip": "mouth_upper", "Lower lip": "mouth_lower"}


def capture(ict, seed=4):
    """Truth (T,V,3) metres, weights (T,S), cameras, markers, marker pixels (T,C,M,2), tracked curves, lip mask."""
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.core.solve.contour_loops import contour_loops
    from facelab_addon.testing.capture_sim import DEFAULT_EXPRESSIONS, helmet_cameras, sample_markers
    from facelab_addon.testing.contour_truth import synthetic_tracked_curves
    from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP, inject_lip_error
    from facelab_addon.testing.weights import spline_weights

    F = ict.faces
    neutral = ict.neutral * SCALE
    D = np.stack([(ict.expressions[n] - ict.neutral) * SCALE for n in EXPR])
    ranges = {n: DEFAULT_EXPRESSIONS.get(n, (0.0, 0.5)) for n in EXPR}
    W = np.zeros((N_FRAMES, len(EXPR)))
    W[1:] = spline_weights(ranges, N_FRAMES - 1, seed=seed, n_keys=4)
    truth = neutral[None] + np.einsum("ts,svd->tvd", W, D)
    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(neutral, F, fixed, loop=ICT_MOUTH_LOOP, units_per_mm=0.001)
    amount = np.r_[0.0, LIP_ERROR_MM * (0.55 + 0.45 * np.sin(np.linspace(0, 2 * np.pi, N_FRAMES - 1)))]
    moved = np.zeros(len(neutral))
    for t in range(1, N_FRAMES):
        before = truth[t].copy()
        truth[t], _ = inject_lip_error(truth[t], F, fixed, kind="gap", amount_mm=float(amount[t]), mouth=mouth)
        moved = np.maximum(moved, np.linalg.norm(truth[t] - before, axis=1))
    lip = moved > 0.0005  # the lip vertices the out-of-rig error moves by more than 0.5 mm
    cams = helmet_cameras(center=np.array([0.0, -1.0, 8.0]) * SCALE, cm=SCALE)  # 1080x1920, 1200 px focal
    skin = ict.part_face_mask("M_Face")
    excl = np.concatenate([neutral[ICT_MOUTH_LOOP], neutral[ict.part_vertex_mask("M_ScleraLeft", "M_ScleraRight")]])
    markers = sample_markers(neutral, F, cams, skin, n=N_MARKERS, seed=3, exclude=excl, exclude_radius=0.009)
    X = markers.evaluate(truth)
    rng = np.random.default_rng(seed + 1)
    px = np.stack([np.stack([c.project(X[t]) for c in cams]) for t in range(N_FRAMES)])
    px = px + rng.normal(0.0, NOISE_PX, px.shape)
    eyeballs = {"left": np.flatnonzero(ict.part_vertex_mask("M_ScleraLeft")),
                "right": np.flatnonzero(ict.part_vertex_mask("M_ScleraRight"))}
    loops = contour_loops(neutral, F, fixed=fixed, mouth_loop=ICT_MOUTH_LOOP, eyeballs=eyeballs)
    curves = [synthetic_tracked_curves(truth[t], F, cams, loops, names=["mouth_upper", "mouth_lower"])
              for t in range(N_FRAMES)]
    return dict(F=F, neutral=neutral, truth=truth, W=W, cams=cams, markers=markers, px=px, curves=curves,
                fixed=fixed, lip=lip, amount=amount, eyeballs=eyeballs, mouth_center=neutral[ICT_MOUTH_LOOP].mean(0))


def _resample(P, n):
    """n points equally spaced by arc length along a polyline (N,2)."""
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]
    u = np.linspace(0, s[-1], n)
    return np.c_[np.interp(u, s, P[:, 0]), np.interp(u, s, P[:, 1])]


def _px_to_mask(px, W, H):
    """Pixels (top-left, y down) -> Mask space of a W x H clip (x scaled about 0.5 by W/H, y up)."""
    u, v = px[:, 0] / W, 1.0 - px[:, 1] / H
    return np.c_[(u - 0.5) * (W / H) + 0.5, v]


def render_helmet_plates(s, plates_dir, camera_names, scale=0.5, samples=8):
    """Footage of each helmet camera: the truth rendered with Cycles (at ``scale`` of the camera's
    resolution, upscaled), with the painted markers drawn on as dark dots at their tracked pixels.
    Returns the first PNG of each camera's sequence (``cam<c>_0001.png``...)."""
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    import bpy
    from PIL import Image, ImageDraw

    plates_dir = Path(plates_dir)
    plates_dir.mkdir(parents=True, exist_ok=True)
    blend = plates_dir / "plate_scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    script = Path(__file__).resolve().parent / "demo_plates.py"
    firsts = []
    for c, (cam, name) in enumerate(zip(s["cams"], camera_names)):
        raw = plates_dir / f"render_cam{c + 1}"
        subprocess.run([sys.executable, str(script), str(blend), str(raw), "--frames", "0", str(N_FRAMES - 1),
                        "--camera", name, "--show", "Truth", "--hide", "Face", "--scale", str(scale),
                        "--samples", str(samples), "--prefix", "r"], check=True, stdout=subprocess.DEVNULL,
                       env=dict(os.environ))
        for t in range(N_FRAMES):
            img = Image.open(raw / f"r_{t + 1:04d}.png").convert("RGB").resize((cam.width, cam.height), Image.BILINEAR)
            draw = ImageDraw.Draw(img)
            for x, y in s["px"][t, c]:
                if np.isfinite(x) and np.isfinite(y):
                    draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=(20, 20, 20))
            img.save(plates_dir / f"cam{c + 1}_{t + 1:04d}.png")
        firsts.append(plates_dir / f"cam{c + 1}_0001.png")
        shutil.rmtree(raw)
    blend.unlink()
    return firsts


def build_scene(ict, s, plates_dir):
    """The artist's scene: rig, cameras, Movie Clips with tracks, Mask and Grease Pencil contours."""
    import bpy

    from facelab_addon.blender import compat
    from facelab_addon.blender.camera import apply_camera_to_blender
    from facelab_addon.blender.scene import add_studio_lights
    from facelab_addon.blender.strokes import write_stroke_pixels
    from facelab_addon.blender.tracking_io import clip_from_pixels
    from facelab_addon.testing.scenes import baked_sequence_object, build_ict_face_scene

    fs = build_ict_face_scene(ict, EXPR, frame_range=(0, N_FRAMES - 1), scale=SCALE, fixed_group=True,
                              eyeball_groups=True, select=False)
    scene, face = fs.scene, fs.obj
    import facelab_addon

    if "facelab_solve" not in bpy.types.Scene.bl_rna.properties:  # earlier demo steps registered it
        facelab_addon.register()
        atexit.register(facelab_addon.unregister)  # bpy 4.5 hangs at exit with FaceLab registered
    T, cams = N_FRAMES, s["cams"]
    mat = bpy.data.materials.new("Skin")
    compat.node_tree(mat)
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.8, 0.55, 0.45, 1)
    bsdf.inputs["Roughness"].default_value = 0.55
    face.data.materials.append(mat)

    sol = scene.facelab_solve
    cam_objs = []
    for c, cam in enumerate(cams):
        cam_obj = bpy.data.objects.new(f"Helmet cam {c + 1}", bpy.data.cameras.new(f"Helmet cam {c + 1}"))
        scene.collection.objects.link(cam_obj)
        apply_camera_to_blender(cam, cam_obj, scene)
        cam_objs.append(cam_obj)
    # the footage: the truth rendered from each helmet camera, with the painted dots on the skin
    truth_ob = baked_sequence_object(ict, "Truth", s["truth"], np.arange(T))
    truth_ob.data.materials.append(mat)
    add_studio_lights(scene)
    firsts = render_helmet_plates(s, plates_dir, [o.name for o in cam_objs])
    views = []
    for c, (cam, cam_obj) in enumerate(zip(cams, cam_objs)):
        clip = clip_from_pixels(firsts[c], s["px"][:, c], cam, names=[f"M{j:02d}" for j in range(len(s["markers"]))],
                                scene_frame_start=0, name=f"Helmet cam {c + 1}")
        v = sol.views.add()
        v.camera, v.clip = cam_obj, clip
        views.append((cam_obj, clip))
    scene.camera = views[0][0]

    # contours: a Mask over clip 1 (one shape key per frame), Grease Pencil strokes through camera 2
    mask = bpy.data.masks.new("Lips")
    mask.frame_start, mask.frame_end = 0, T - 1
    splines = {}
    for n in MASK_NAMES:
        sp = mask.layers.new(name=n).splines.new()
        sp.points.add(N_MASK_POINTS - 1)
        splines[n] = sp
    win = bpy.context.window_manager.windows[0]
    area = win.screen.areas[-1]
    old_type = area.type
    area.type = "CLIP_EDITOR"
    space = area.spaces.active
    space.clip, space.mode, space.mask = views[0][1], "MASK", mask
    ctx = dict(window=win, area=area, region=next(r for r in area.regions if r.type == "WINDOW"), space_data=space)
    gp = bpy.data.objects.new("Lip sketch (cam 2)", compat.grease_pencil_data().new("Lip sketch (cam 2)"))
    scene.collection.objects.link(gp)
    gp.location = cams[1].center + 0.05 * cams[1].forward
    W, H = cams[0].width, cams[0].height
    for t in range(T):
        scene.frame_set(t)
        by = {(c.name, c.camera): c.pixels for c in s["curves"][t]}
        for n, key in MASK_NAMES.items():
            co = _px_to_mask(_resample(by[key, 0], N_MASK_POINTS), W, H).astype(np.float32).ravel()
            for attr in ("co", "handle_left", "handle_right"):
                splines[n].points.foreach_set(attr, co)
            for p in splines[n].points:
                p.select = True
            write_stroke_pixels(gp, n, t, [by[key, 1]], cams[1])
        for lay in mask.layers:
            mask.layers.active = lay
            with bpy.context.temp_override(**ctx):
                assert bpy.ops.mask.shape_key_insert() == {"FINISHED"}
    area.type = old_type
    sol.views[0].mask = mask
    sol.views[1].sketch = gp
    bpy.context.view_layer.objects.active = face
    face.select_set(True)
    scene.facelab.face = face
    return scene, face, mat


def errors(s, X, W_got, ict):
    """Weight, vertex and contour errors of a solve X (T,V,3) vs the truth."""
    from facelab_addon.core.geometry.silhouette import contour_distance

    skin = ict.part_vertex_mask("M_Face")
    e = np.linalg.norm(X - s["truth"], axis=2) * 1e3  # mm
    frames = np.arange(1, N_FRAMES)
    cpx = []
    for t in frames:
        by = {(c.name, c.camera): c.pixels for c in s["curves"][t]}
        d = [contour_distance(X[t], s["F"], s["cams"][0], by[k, 0], sd, candidates=~s["fixed"])
             for k, sd in (("mouth_upper", +1), ("mouth_lower", -1))]
        d = np.concatenate(d)
        cpx.append(float(np.mean(d[np.isfinite(d)])) if np.isfinite(d).any() else float("nan"))
    return dict(
        weight_max_abs_error=float(np.abs(W_got - s["W"])[frames].max()),
        weight_mean_abs_error=float(np.abs(W_got - s["W"])[frames].mean()),
        skin_rms_mm=float(np.sqrt(np.mean(e[frames][:, skin] ** 2))),
        lip_rms_mm=float(np.sqrt(np.mean(e[frames][:, s["lip"]] ** 2))),
        lip_max_mm=float(e[frames][:, s["lip"]].max()),
        lip_rms_mm_per_frame=[round(float(np.sqrt(np.mean(e[t, s["lip"]] ** 2))), 3) for t in frames],
        inner_lip_contour_px_cam1=float(np.nanmean(cpx)),
        inner_lip_contour_px_cam1_per_frame=[round(c, 2) for c in cpx],
    )


def run(ict, out, img_dir, render, samples):
    import bpy

    from facelab_addon.blender import compat
    from facelab_addon.blender.actions import curve_values as _curve_values
    from facelab_addon.blender.caches import evaluate_frames
    from facelab_addon.blender.scene import new_mesh_object
    from facelab_addon.testing.creature import widen_mouth
    from facelab_addon.testing.scenes import baked_sequence_object

    t_start = time.perf_counter()
    s = capture(ict)
    scene, face, mat = build_scene(ict, s, out / "solve_plates")
    sol = scene.facelab_solve
    frames = np.arange(N_FRAMES)
    t_build = time.perf_counter() - t_start
    print(f"[demo]   solve scene built: {len(s['markers'])} markers x 2 Movie Clips, Mask + Grease Pencil lips "
          f"({t_build:.1f} s)")

    timings = {}
    assert bpy.ops.facelab.bind_tracks(frame=0) == {"FINISHED"}
    results = {}
    for label, contours, corrective in (("markers_only", False, False), ("markers_contours", True, False),
                                        ("markers_contours_corrective", True, True)):
        sol.use_contours, sol.use_corrective = contours, corrective
        t0 = time.perf_counter()
        assert bpy.ops.facelab.solve_performance() == {"FINISHED"}
        timings[f"solve_{label}_s"] = round(time.perf_counter() - t0, 2)
        X = evaluate_frames(face, frames, mute_shape_keys_prefix=())
        Wg = _curve_values(face.data.shape_keys, EXPR, frames)
        results[label] = (X, errors(s, X, Wg, ict))
        print(f"[demo]   Solve Performance ({label}): lip RMS {results[label][1]['lip_rms_mm']:.2f} mm, "
              f"contour {results[label][1]['inner_lip_contour_px_cam1']:.2f} px")
    X_m, X_c = results["markers_only"][0], results["markers_contours_corrective"][0]
    truth_ob = bpy.data.objects["Truth"]  # built with the footage
    mo_ob = baked_sequence_object(ict, "Solve (markers only)", X_m, frames)
    mo_ob.data.materials.append(mat)
    for ob in (truth_ob, mo_ob):
        ob.hide_render = True
        ob.hide_set(True)

    cre = new_mesh_object("Creature", widen_mouth(s["neutral"], s["mouth_center"], factor=1.5),
                          poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    cmat = bpy.data.materials.new("Creature skin")
    compat.node_tree(cmat)
    cb = cmat.node_tree.nodes.get("Principled BSDF")
    cb.inputs["Base Color"].default_value = (0.35, 0.62, 0.45, 1)
    cb.inputs["Roughness"].default_value = 0.5
    cre.data.materials.append(cmat)
    sol.creature = cre
    t0 = time.perf_counter()
    assert bpy.ops.facelab.retarget() == {"FINISHED"}
    timings["retarget_s"] = round(time.perf_counter() - t0, 2)
    X_cre = evaluate_frames(cre, frames, mute_shape_keys_prefix=())
    cre.hide_render = True
    cre.hide_set(True)
    bpy.context.view_layer.objects.active = face
    blend = out / "solve.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    print(f"[demo]   saved {blend}")

    # the frame with the most visible lip error of the markers-only solve; the retarget frame: the widest jaw
    lip = s["lip"]
    e_m = np.sqrt(np.mean((np.linalg.norm(X_m - s["truth"], axis=2)[:, lip] * 1e3) ** 2, axis=1))
    f_lip = int(np.argmax(e_m))
    f_ret = int(np.argmax(s["W"][:, EXPR.index("jawOpen")] + s["W"][:, EXPR.index("mouthSmile_L")]))
    cam = s["cams"][0]
    W, H = cam.width, cam.height
    p = cam.project(s["truth"][f_lip][lip])
    c = p.mean(0)
    lo, hi = c - [200, 140], c + [200, 140]
    border = [lo[0] / W, hi[0] / W, 1 - hi[1] / H, 1 - lo[1] / H]
    pf = cam.project(s["neutral"][ict.part_vertex_mask("M_Face")])
    cf = cam.project(s["mouth_center"][None])[0]
    lo2, hi2 = cf - [330, 330], cf + [330, 200]
    lo2, hi2 = np.maximum(lo2, 0), np.minimum(hi2, [W, H])
    border2 = [lo2[0] / W, hi2[0] / W, 1 - hi2[1] / H, 1 - lo2[1] / H]
    del pf
    print(f"[demo]   rendering solve frames {f_lip} (lips) and {f_ret} (retarget), Cycles CPU")
    t0 = time.perf_counter()
    r = {k: out / f"solve_{k}.png" for k in ("truth", "markers", "full", "actor", "creature_plain", "creature")}
    others = ["Face", "Truth", "Solve (markers only)", "Creature"]
    for k, name, f, b, mute in (("truth", "Truth", f_lip, border, []),
                                ("markers", "Solve (markers only)", f_lip, border, []),
                                ("full", "Face", f_lip, border, []), ("actor", "Face", f_ret, border2, []),
                                ("creature_plain", "Creature", f_ret, border2, ["FL_Retarget_"]),
                                ("creature", "Creature", f_ret, border2, [])):
        kw = dict(mute_keys=mute) if mute else {}
        render(blend, r[k], frame=f, hide=[o for o in others if o != name], show=[name], border=b, samples=samples,
               **kw)
    timings["render_s"] = round(time.perf_counter() - t0, 1)
    # solve.blend keeps the creature in view, beside the actor (its shape keys are object-local)
    cre.hide_set(False)
    cre.hide_render = False
    cre.location.x += 0.3
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    summary = dict(
        lip_region="vertices the out-of-rig lip error moves by > 0.5 mm (%d)" % int(s["lip"].sum()),
        frames=N_FRAMES, markers=len(s["markers"]), marker_noise_px=NOISE_PX, cameras="helmet stereo 1080x1920",
        rig_expressions=len(EXPR), out_of_rig_lip_gap_mm_per_frame=[round(float(a), 2) for a in s["amount"]],
        figure_frame_lips=f_lip, figure_frame_retarget=f_ret,
        **{k: v[1] for k, v in results.items()}, timings=timings,
        build_scene_s=round(t_build, 1),
    )
    figures(s, img_dir, r, (lo, hi), (lo2, hi2), f_lip, f_ret, results, summary, X_cre)
    (out / "solve_summary.json").write_text(json.dumps(summary, indent=2))
    summary["total_s"] = round(time.perf_counter() - t_start, 1)
    return summary


def figures(s, img_dir, r, box, box2, f_lip, f_ret, results, summary, X_cre):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cam = s["cams"][0]
    (lo, hi), (lo2, hi2) = box, box2
    ext = (lo[0], hi[0], hi[1], lo[1])
    by = {(c.name, c.camera): c.pixels for c in s["curves"][f_lip]}
    mk = s["px"][f_lip, 0]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    em, ec = results["markers_only"][1], results["markers_contours_corrective"][1]
    for ax, k, title in ((axes[0], "truth", f"Ground truth: lips {s['amount'][f_lip]:.1f} mm further apart\nthan the rig can express"),
                         (axes[1], "markers", f"Solve: markers only\nlip RMS {em['lip_rms_mm_per_frame'][f_lip - 1]:.2f}"
                                              f" mm, contour {em['inner_lip_contour_px_cam1_per_frame'][f_lip - 1]:.1f} px"),
                         (axes[2], "full", f"Solve: markers + contours + corrective\nlip RMS "
                                           f"{ec['lip_rms_mm_per_frame'][f_lip - 1]:.2f} mm, contour "
                                           f"{ec['inner_lip_contour_px_cam1_per_frame'][f_lip - 1]:.1f} px")):
        ax.imshow(plt.imread(r[k]), extent=ext)
        for key, col, lab in (("mouth_upper", "#ff3b30", "tracked upper lip (Mask)"),
                              ("mouth_lower", "#0a84ff", "tracked lower lip (Mask)")):
            P = by[key, 0]
            ax.plot(P[:, 0], P[:, 1], color=col, lw=1.3, ls="--", label=lab)
        ax.plot(mk[:, 0], mk[:, 1], "o", ms=4, mfc="none", mec="#ffd60a", mew=1.0, label="tracks")
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    axes[0].legend(loc="lower left", fontsize=7, framealpha=0.8)
    fig.suptitle(f"Solve Performance, helmet camera 1, frame {f_lip}", fontsize=11)
    fig.tight_layout()
    fig.savefig(img_dir / "demo_solve_before_after.png", dpi=90)
    plt.close(fig)

    ext2 = (lo2[0], hi2[0], hi2[1], lo2[1])
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.7))
    for ax, k, title in ((axes[0], "actor", f"Actor (solved), frame {f_ret}"),
                         (axes[1], "creature_plain", "Creature (mouth 1.5x wider): transferred rig shapes\n"
                                                     "(FL_Retarget_* correctives muted)"),
                         (axes[2], "creature", "Creature: + FL_Retarget_* correctives\n(Lip Sync seals the lips "
                                               "beyond the actor's mouth width)")):
        ax.imshow(plt.imread(r[k]), extent=ext2)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(img_dir / "demo_solve_retarget.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 3.4))
    t = np.arange(1, N_FRAMES)
    for lab, key, st in (("markers only", "markers_only", "o-"), ("markers + contours", "markers_contours", "s-"),
                         ("markers + contours + corrective", "markers_contours_corrective", "^-")):
        ax.plot(t, results[key][1]["lip_rms_mm_per_frame"], st, label=lab)
    ax.plot(t, s["amount"][1:], "k--", lw=1, label="out-of-rig lip gap in the truth")
    ax.set_xlabel("frame")
    ax.set_ylabel("inner-lip RMS error (mm)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(img_dir / "demo_solve_errors.png", dpi=90)
    plt.close(fig)
    print(f"wrote {img_dir}/demo_solve_before_after.png, demo_solve_retarget.png, demo_solve_errors.png")
