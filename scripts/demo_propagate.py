"""Demo step 2: propagate sketch corrections over a performance (Dinev et al. 2018 §4).

A 48-frame ICT "performance" (mouth expressions keyed as shape keys) carries a
systematic capture error (a key 'CaptureError': the inner lips fail to close,
more so when the jaw is closed). The artist sketches the true inner-lip
contours over the plate (the truth rendered, loaded with Load Plate) on a few
frames suggested by FaceLab and refines them (Refine Lips),
then Auto Regions and Propagate correct every frame. Renders compare two held-out
frames before / after / truth (a typical one and the worst one), and a plot shows the
inner-lip error per frame.
"""

from __future__ import annotations

import json
import time

import numpy as np

EXPR = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R", "mouthPress_L",
        "mouthPress_R"]
N_FRAMES = 48
SCALE, UNITS_PER_MM = 0.01, 0.001


def _drawable(upper, lower, tol_px=2.0):
    """True if an artist would draw these truth contours as they are: the upper one above
    the lower one everywhere (the truth's silhouettes cross where ICT's lips overlap; there
    an artist draws the line where the lips meet instead, which the truth does not give us)."""
    from facelab_addon.core.geometry.polyline import y_at

    ly = y_at(upper[:, 0], lower)
    ok = np.isfinite(ly)
    return ok.any() and bool((ly[ok] >= upper[ok, 1] - tol_px).all())


def render_plate(plate_dir, frames, scale=1 / 3, samples=4):
    """Render the truth (``CaptureError`` muted) on ``frames`` into ``plate_dir/plate_0001.png``...;
    returns the first file."""
    import subprocess
    import sys
    from pathlib import Path

    import bpy

    plate_dir.mkdir(parents=True, exist_ok=True)
    blend = plate_dir / "plate_scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    script = Path(__file__).resolve().parent / "demo_plates.py"
    subprocess.run([sys.executable, str(script), str(blend), str(plate_dir), "--frames", str(int(frames[0])),
                    str(int(frames[-1])), "--mute-keys", "CaptureError", "--scale", str(scale), "--samples",
                    str(samples), "--prefix", "plate"], check=True, stdout=subprocess.DEVNULL)
    blend.unlink()
    return plate_dir / "plate_0001.png"


def run(ict, out, img_dir, render, samples, n_train=8):
    import bpy

    from facelab_addon.blender import compat
    from facelab_addon.blender.caches import evaluate_frames
    from facelab_addon.blender.camera import camera_from_blender
    from facelab_addon.blender.scene import add_studio_lights
    from facelab_addon.blender.shapekeys import add_corrective_key, key_values_bulk
    from facelab_addon.blender.strokes import write_stroke_pixels
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.core.lips.suggest import suggest_frames
    from facelab_addon.testing import synthetic as syn
    from facelab_addon.testing.scenes import build_ict_face_scene
    from facelab_addon.testing.weights import rectified_sine_weights

    F = ict.faces
    neutral = ict.neutral * SCALE
    deltas = np.stack([(ict.expressions[n] - ict.neutral) * SCALE for n in EXPR])
    W = rectified_sine_weights(N_FRAMES, len(EXPR), seed=7)
    frames = np.arange(1, N_FRAMES + 1)
    truth = neutral[None] + np.einsum("tk,kvd->tvd", W, deltas)
    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(neutral, F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UNITS_PER_MM)
    w, side = syn.lip_error_weights(neutral, F, fixed, mouth=mouth)
    err = np.zeros_like(neutral)
    err[:, 1] = side * w * 1.25 * UNITS_PER_MM  # 2.5 mm gap at full strength
    strength = np.clip(1.0 - W[:, 0] / 0.35, 0.2, 1.0)  # worst when the jaw is closed
    captured = truth + strength[:, None, None] * err[None]

    cam = syn.frontal_camera(neutral, mouth.center, distance=0.40)
    fs = build_ict_face_scene(ict, EXPR, weights=W, frames=frames, scale=SCALE, fixed_group=True, camera=cam)
    scene, face = fs.scene, fs.obj
    if "facelab" not in bpy.types.Scene.bl_rna.properties:  # run alone (--only propagate)
        import atexit

        import facelab_addon

        facelab_addon.register()
        atexit.register(facelab_addon.unregister)  # bpy 4.5 hangs at exit with FaceLab registered
    add_corrective_key(face, "CaptureError", err)
    key_values_bulk(face, ["CaptureError"], frames, strength[:, None])
    mat = bpy.data.materials.get("Skin") or bpy.data.materials.new("Skin")
    compat.node_tree(mat)
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.55, 0.45, 1)
    face.data.materials.append(mat)
    add_studio_lights(scene)
    bcam = camera_from_blender(scene)
    # the plate: what the actor did (the capture error muted), rendered from the camera; Load Plate puts it
    # behind the camera (at a third of the resolution: it is for looking at, the sketch is in full pixels)
    first = render_plate(out / "propagate_plate", frames)
    assert bpy.ops.facelab.load_plate(filepath=str(first), match_resolution=False) == {"FINISHED"}
    print(f"[demo]   plate: {len(frames)} frames rendered (Cycles CPU) and loaded with Load Plate")

    # FaceLab suggests the frames worth correcting (extreme poses); the artist sketches them
    from facelab_addon.core.lips.regions import auto_regions, faces_in_region

    mouth_mask, _ = auto_regions(neutral, F)
    ranked = [int(frames[i]) for i in suggest_frames(
        captured, 3 * n_train, rest_vertices=neutral, faces=F, mouth_faces=faces_in_region(F, mouth_mask))]
    train = []
    t0 = time.perf_counter()
    for f in ranked:  # the artist sketches suggested frames where both inner contours are visible
        if len(train) == n_train:
            break
        m_f = find_mouth(truth[f - 1], F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UNITS_PER_MM)
        try:
            upper, lower = syn.lip_contours(truth[f - 1], F, cam, fixed, mouth=m_f)
        except Exception:
            continue
        if not _drawable(upper, lower):
            continue
        scene.frame_set(f)
        bpy.context.view_layer.objects.active = face
        bpy.ops.facelab.new_lip_sketch()
        write_stroke_pixels(scene.facelab.sketch, "Upper lip", f, [upper], bcam)
        write_stroke_pixels(scene.facelab.sketch, "Lower lip", f, [lower], bcam)
        bpy.context.view_layer.objects.active = face
        bpy.ops.facelab.refine_lips()
        train.append(f)
    train.sort()
    t_sketch = time.perf_counter() - t0
    bpy.context.view_layer.objects.active = face
    bpy.ops.facelab.auto_regions()
    t1 = time.perf_counter()
    bpy.ops.facelab.propagate()
    t_prop = time.perf_counter() - t1
    result = evaluate_frames(face, frames, mute_shape_keys_prefix=())
    blend = out / "propagate.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))

    lips = side != 0
    def rms(X):
        return np.sqrt((np.linalg.norm(X - truth, axis=2)[:, lips] ** 2).mean(axis=1)) / UNITS_PER_MM

    e0, e1 = rms(captured), rms(result)
    held = np.setdiff1d(frames, train)
    summary = dict(
        frames=int(N_FRAMES), training_frames=train, refine_seconds_total=round(t_sketch, 2),
        propagate_seconds=round(t_prop, 2),
        corrective_shapes=sum(kb.name.startswith("FL_Prop_") for kb in face.data.shape_keys.key_blocks),
        held_out_lip_rms_mm_before=float(np.sqrt((e0[held - 1] ** 2).mean())),
        held_out_lip_rms_mm_after=float(np.sqrt((e1[held - 1] ** 2).mean())),
    )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 3.4))
    ax.plot(frames, e0, color="#888", lw=2, label="capture")
    ax.plot(frames, e1, color="#d62728", lw=2, label="after Propagate")
    ax.scatter(train, e1[np.array(train) - 1], color="k", zorder=3, label="sketched training frames")
    ax.set_xlabel("frame")
    ax.set_ylabel("inner-lip RMS error (mm)")
    ax.set_ylim(0, None)
    ax.legend(frameon=False)
    better, worse = int((e1[held - 1] < e0[held - 1]).sum()), int((e1[held - 1] > e0[held - 1]).sum())
    ax.set_title(f"Inner-lip error per frame, capture vs after Propagate from {len(train)} sketched frames:\n"
                 f"lower on {better} of the {len(held)} other frames, higher on {worse}", fontsize=10)
    fig.tight_layout()
    fig.savefig(img_dir / "propagate_timeline.png", dpi=90)
    plt.close(fig)

    # render two held-out frames: before (FaceLab keys muted), after, truth (error key muted too): a typical
    # frame (the median gain) and the worst (the smallest gain: made worse, if any frame was)
    gain = e0[held - 1] - e1[held - 1]
    order = np.argsort(gain)
    picks = {int(held[order[len(held) // 2]]): "typical", int(held[order[0]]): "worst"}
    show = sorted(picks)
    pts = np.concatenate([cam.project(truth[f - 1][mouth.loop]) for f in show])
    lo, hi = pts.min(0) - [70, 90], pts.max(0) + [70, 90]
    border = [lo[0] / cam.width, hi[0] / cam.width, 1 - hi[1] / cam.height, 1 - lo[1] / cam.height]
    fig, axes = plt.subplots(len(show), 3, figsize=(15, 3.3 * len(show)), squeeze=False)
    for r, f in enumerate(show):
        for c, (mute, title) in enumerate(((["FL_"], "capture"), ([], "FaceLab: propagated"),
                                           (["FL_", "CaptureError"], "ground truth"))):
            png = out / f"prop_{f}_{c}.png"
            render(blend, png, frame=f, border=border, samples=samples, mute_keys=mute)
            ax = axes[r, c]
            ax.imshow(plt.imread(png))
            head = (f"frame {f}, not sketched, the {picks[f]} one ({e0[f - 1]:.2f} -> {e1[f - 1]:.2f} mm)" if c == 0
                    else f"frame {f}")
            ax.set_title(f"{head}\n{title}", fontsize=10)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(img_dir / "propagate_before_after.png", dpi=80)
    plt.close(fig)
    summary.update(held_out_frames_better=better, held_out_frames_worse=worse,
                   before_after_frames={picks[f]: f for f in show})
    (out / "propagate_summary.json").write_text(json.dumps(summary, indent=2))
    return summary
