"""The Review pictures of docs/panel.md and the README: the correction heat map and the capture /
corrected toggle, on the ICT-FaceKit face after Propagate, rendered with Cycles on the CPU.

    python scripts/review_figures.py [--out out/review] [--images docs/images] [--samples 16]

Builds the shot through the operators (a 30-frame capture whose inner lips fail to close, 5 frames
corrected by sculpting, Auto Regions, Propagate), then on the held-out frame with the largest
correction runs Correction Heat Map and Compare Capture / Corrected, saves the scenes in ``--out``
and renders them in subprocesses (``scripts/render_blend.py``). Writes ``review_heatmap.png`` and
``review_toggle.png`` into ``--images`` and ``review_summary.json`` into ``--out``.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCALE = 0.01  # ICT centimetres -> metres

EXPR = ("jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R")
N_FRAMES = 30
TRAIN = [3, 9, 15, 21, 27]
TILT_DEG = -20.0  # heat-map view: the camera swung below the mouth


def render(blend, out, **kw):
    cmd = [sys.executable, str(ROOT / "scripts" / "render_blend.py"), str(blend), str(out)]
    for k, v in kw.items():
        cmd += ["--" + k.replace("_", "-"), *(map(str, v) if isinstance(v, (list, tuple)) else [str(v)])]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def build(out):
    import bpy

    import facelab_addon
    from facelab_addon.blender import compat, review
    from facelab_addon.blender.scene import add_studio_lights
    from facelab_addon.blender.shapekeys import add_corrective_key, key_spike, key_values_bulk
    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as syn
    from facelab_addon.testing.scenes import build_ict_face_scene
    from facelab_addon.testing.weights import rectified_sine_weights

    bpy.ops.wm.read_factory_settings(use_empty=True)
    facelab_addon.register()
    ict = load_ict()
    neutral = ict.neutral * SCALE
    W = rectified_sine_weights(N_FRAMES, len(EXPR), seed=3)
    frames = np.arange(1, N_FRAMES + 1)
    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(neutral, ict.faces, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=1e-3)
    w, side = syn.lip_error_weights(neutral, ict.faces, fixed, mouth=mouth)
    err = np.zeros_like(neutral)
    err[:, 1] = side * w * 1.25e-3  # the lips 2.5 mm apart at full strength
    strength = np.clip(1.0 - W[:, 0] / 0.35, 0.2, 1.0)  # worst when the jaw is closed
    cam = syn.frontal_camera(neutral, mouth.center, distance=0.40)
    fs = build_ict_face_scene(ict, list(EXPR), weights=W, frames=frames, scale=SCALE, fixed_group=True, camera=cam)
    scene, face = fs.scene, fs.obj
    add_corrective_key(face, "CaptureError", err)
    key_values_bulk(face, ["CaptureError"], frames, strength[:, None])
    add_studio_lights(scene)
    bpy.context.view_layer.objects.active = face
    scene.facelab.face = face
    for f in TRAIN:  # the artist's corrections: sculpted keys that cancel the error there
        scene.frame_set(f)
        key_spike(add_corrective_key(face, f"Sculpt_{f}", -strength[f - 1] * err), f)
        bpy.ops.facelab.mark_training_frame()
    bpy.ops.facelab.auto_regions()
    bpy.ops.facelab.propagate()

    held = [f for f in frames if f not in TRAIN]
    f = int(max(held, key=lambda g: strength[g - 1]))
    scene.frame_set(f)
    bpy.ops.facelab.correction_heatmap()
    mag = review.correction_magnitude(face, bpy.context.evaluated_depsgraph_get(), metres_per_unit=1.0)
    truth = np.linalg.norm(strength[f - 1] * err, axis=1) * 1e3
    vmax = float(face.data["FL_correction_range_mm"][1])

    # materials: the skin, and for the heat-map render the color attribute as the base colour
    skin = bpy.data.materials.new("Skin")
    compat.node_tree(skin)
    skin.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.55, 0.45, 1)
    face.data.materials.append(skin)
    corrected_blend = out / "review_corrected.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(corrected_blend))
    heat = bpy.data.materials.new("FL_correction heat map")
    nt = compat.node_tree(heat)
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = "FL_correction"
    bsdf = nt.nodes["Principled BSDF"]
    nt.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = 0.7
    face.data.materials[0] = heat
    # the heat map is seen from a little below, where the inner lips show
    from mathutils import Matrix, Vector

    c = Vector(face.matrix_world @ Vector(neutral[mouth.loop].mean(0)))
    cam_obj = scene.camera
    front = cam_obj.matrix_world.copy()
    cam_obj.matrix_world = (Matrix.Translation(c) @ Matrix.Rotation(np.radians(TILT_DEG), 4, "X")
                            @ Matrix.Translation(-c) @ cam_obj.matrix_world)
    heat_blend = out / "review_heatmap.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(heat_blend))
    face.data.materials[0] = skin
    cam_obj.matrix_world = front
    bpy.ops.facelab.review_toggle()  # the capture, as the button shows it
    capture_blend = out / "review_capture.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(capture_blend))
    muted = sorted(kb.name for kb in face.data.shape_keys.key_blocks if kb.mute)

    def border(pad):
        pts = cam.project(neutral[mouth.loop])
        lo, hi = pts.min(0) - pad, pts.max(0) + pad
        return [lo[0] / cam.width, hi[0] / cam.width, 1 - hi[1] / cam.height, 1 - lo[1] / cam.height]

    lips = truth > 0
    summary = dict(frame=f, training_frames=TRAIN, heatmap_max_mm=round(vmax, 4),
                   heatmap_mean_on_lips_mm=round(float(mag[lips].mean()), 4),
                   injected_error_mean_on_lips_mm=round(float(truth[lips].mean()), 4),
                   muted_while_capture_shown=muted)
    facelab_addon.unregister()
    return dict(frame=f, border=border(np.array([70, 80])), heat_border=border(np.array([150, 190])), vmax=vmax, heat=heat_blend, capture=capture_blend,
                corrected=corrected_blend, summary=summary)


def figures(r, out, img_dir, samples):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LinearSegmentedColormap

    from facelab_addon.blender.review import HEAT_STOPS

    f, border = r["frame"], r["border"]
    pngs = {}
    for name in ("heat", "capture", "corrected"):
        pngs[name] = out / f"review_{name}_{f}.png"
        render(r[name], pngs[name], frame=f, border=r["heat_border"] if name == "heat" else border, samples=samples)

    # linear RGB stops -> display (sRGB) for the colour bar, as Blender shows them
    srgb = lambda c: np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    cmap = LinearSegmentedColormap.from_list("fl", [(s[0], tuple(srgb(np.array(s[1:])))) for s in HEAT_STOPS])
    fig, (ax, cax) = plt.subplots(1, 2, figsize=(7.2, 5.4), gridspec_kw=dict(width_ratios=[20, 1]))
    ax.imshow(plt.imread(pngs["heat"]))
    ax.set_title(f"Correction Heat Map: how far FaceLab's corrections move each vertex,\nframe {f} "
                 "(not a training frame)", fontsize=10)
    ax.axis("off")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, r["vmax"]))
    fig.colorbar(sm, cax=cax, label="correction (mm, world space)")
    fig.tight_layout()
    fig.savefig(img_dir / "review_heatmap.png", dpi=90, bbox_inches="tight")
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, name, title in zip(axes, ("capture", "corrected"),
                               ("Show Capture: every FaceLab key muted", "Show Corrected: your mutes restored")):
        ax.imshow(plt.imread(pngs[name]))
        ax.set_title(f"frame {f}: {title}", fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(img_dir / "review_toggle.png", dpi=80, bbox_inches="tight")
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "review")
    ap.add_argument("--images", type=Path, default=ROOT / "docs" / "images")
    ap.add_argument("--samples", type=int, default=16)
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    a.images.mkdir(parents=True, exist_ok=True)
    r = build(a.out.resolve())
    figures(r, a.out.resolve(), a.images, a.samples)
    (a.out / "review_summary.json").write_text(json.dumps(r["summary"], indent=2) + "\n")
    print(json.dumps(r["summary"], indent=2))


if __name__ == "__main__":
    main()
