"""FaceLab demo: sketch-based lip refinement on the ICT-FaceKit face, headless.

1. Builds a scene: the captured face (the truth with an injected inner-lip gap),
   a frontal camera, a backplate rendered from the truth, and a lip sketch
   (Grease Pencil strokes that trace the truth's inner-lip silhouettes).
2. Runs the Refine Lips operator on the problem frame.
3. Saves out/demo/lip_refine.blend and before/after renders with the contours
   overlaid, plus a 3D error heat map, into out/demo/images/ (docs/images/ with
   --refresh-docs).
4. Propagation (scripts/demo_propagate.py): sketches a few frames of a 48-frame
   performance, propagates, renders held-out frames and plots the error per frame.
5. Solve Performance + Retarget (scripts/demo_solve.py): a stereo helmet capture
   (Movie Clips with tracks, Mask / Grease Pencil lip contours) -> Bind Tracks ->
   Solve Performance -> Retarget to a wide-mouthed creature (solve.blend).
6. Reconstruct from Bundles (scripts/demo_reconstruct.py): 100 animated bundle
   empties of a held-out performance -> Reconstruct from Bundles (reconstruct.blend).

Run it with ``bash scripts/demo.sh`` (it sets up its own environment); run parts
selectively with e.g. ``bash scripts/demo.sh --only solve,reconstruct``. It prints one
line per step and a final table; everything else (Blender's own messages, per-frame
numbers) goes to out/demo/demo.log and out/demo/*_summary.json.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-demo-"))

import numpy as np  # noqa: E402

FRAME = 12
SCALE = 0.01  # ICT centimetres -> metres
UNITS_PER_MM = 0.001


def scenario(ict):
    """Truth, capture, camera, sketch and masks for the demo (metres)."""
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as syn

    F = ict.faces
    truth = ict.pose({"jawOpen": 0.2, "mouthFunnel": 0.3}) * SCALE
    fixed = syn.ict_fixed_mask(ict) if hasattr(syn, "ict_fixed_mask") else ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(truth, F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UNITS_PER_MM)
    cam = syn.frontal_camera(truth, mouth.center, distance=0.40)
    upper, lower = syn.lip_contours(truth, F, cam, fixed, mouth=mouth)
    captured, err_mask = syn.inject_lip_error(truth, F, fixed, kind="gap", amount_mm=2.5, mouth=mouth)
    return dict(F=F, truth=truth, captured=captured, fixed=fixed, cam=cam, upper=upper, lower=lower, lip=err_mask)


def render(blend, out, **kw):
    cmd = [sys.executable, str(ROOT / "scripts" / "render_blend.py"), str(blend), str(out)]
    for k, v in kw.items():
        flag = "--" + k.replace("_", "-")
        if v is True:
            cmd.append(flag)
        elif isinstance(v, (list, tuple)):
            cmd += [flag, *map(str, v)]
        else:
            cmd += [flag, str(v)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


PARTS = ("refine", "propagate", "solve", "reconstruct")


def run_refine(ict, out, img_dir, samples):
    """Step 1: Refine Lips on one frame (lip_refine.blend, refine_*.png)."""
    import bpy

    import facelab_addon
    from facelab_addon.blender import compat
    from facelab_addon.blender.camera import camera_from_blender, new_camera_object
    from facelab_addon.blender.mesh import evaluated_vertices
    from facelab_addon.blender.scene import add_studio_lights, new_mesh_object, set_backplate
    from facelab_addon.blender.strokes import read_lip_strokes, write_stroke_pixels
    from facelab_addon.core.geometry.silhouette import contour_distance

    t0 = time.perf_counter()
    s = scenario(ict)
    print(f"scenario ready ({time.perf_counter() - t0:.1f} s)")

    bpy.ops.wm.read_factory_settings(use_empty=True)
    facelab_addon.register()
    atexit.register(facelab_addon.unregister)  # bpy 4.5 hangs at exit with FaceLab registered
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 24
    scene.frame_set(FRAME)
    mat = bpy.data.materials.new("Skin")
    compat.node_tree(mat)
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.8, 0.55, 0.45, 1)
    bsdf.inputs["Roughness"].default_value = 0.55
    face = new_mesh_object("Face", s["captured"], poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    truth = new_mesh_object("Truth", s["truth"], poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    for ob in (face, truth):
        ob.data.materials.append(mat)
        ob.data.shade_smooth() if hasattr(ob.data, "shade_smooth") else None
    truth.hide_render = True
    truth.hide_set(True)
    vg = face.vertex_groups.new(name="FL_fixed")
    vg.add(np.flatnonzero(s["fixed"]).tolist(), 1.0, "REPLACE")
    cam_obj = new_camera_object(scene, s["cam"])
    add_studio_lights(scene)

    # backplate: the truth rendered from the capture camera
    blend = out / "lip_refine.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    cam = s["cam"]
    pu = np.r_[s["upper"], s["lower"]]
    lo_px, hi_px = pu.min(0) - [90, 110], pu.max(0) + [90, 110]
    border = [lo_px[0] / cam.width, hi_px[0] / cam.width, 1 - hi_px[1] / cam.height, 1 - lo_px[1] / cam.height]
    plate = out / "backplate.png"
    print("[demo]   rendering the backplate (Cycles, CPU)")
    render(blend, plate, hide=["Face"], show=["Truth"], samples=samples)
    set_backplate(cam_obj, plate)

    # the artist's sketch and the refinement
    bpy.context.view_layer.objects.active = face
    face.select_set(True)
    bpy.ops.facelab.new_lip_sketch()
    gp = scene.facelab.sketch
    bcam = camera_from_blender(scene)
    write_stroke_pixels(gp, "Upper lip", FRAME, [s["upper"]], bcam)
    write_stroke_pixels(gp, "Lower lip", FRAME, [s["lower"]], bcam)
    bpy.context.view_layer.objects.active = face
    t1 = time.perf_counter()
    bpy.ops.facelab.refine_lips()
    t_refine = time.perf_counter() - t1
    dg = bpy.context.evaluated_depsgraph_get()
    refined = evaluated_vertices(face, dg)
    strokes = read_lip_strokes(scene, bcam, FRAME, depsgraph=dg)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    print(f"[demo]   Refine Lips: {t_refine:.2f} s; saved {blend}")

    # numbers
    F, fixed, lip = s["F"], s["fixed"], s["lip"]
    U, L = np.concatenate(strokes["upper"]), np.concatenate(strokes["lower"])

    def contour(X):
        return np.r_[contour_distance(X, F, cam, U, +1, candidates=~fixed), contour_distance(X, F, cam, L, -1, candidates=~fixed)]

    def err(X):
        return np.linalg.norm(X - s["truth"], axis=1) / UNITS_PER_MM

    summary = dict(
        refine_seconds=round(t_refine, 3),
        contour_px_before=float(np.mean(contour(s["captured"]))),
        contour_px_after=float(np.mean(contour(refined))),
        lip_rms_mm_before=float(np.sqrt(np.mean(err(s["captured"])[lip] ** 2))),
        lip_rms_mm_after=float(np.sqrt(np.mean(err(refined)[lip] ** 2))),
        lip_max_mm_before=float(err(s["captured"])[lip].max()),
        lip_max_mm_after=float(err(refined)[lip].max()),
    )

    # renders: before (frame FRAME-1: corrective key at 0) and after (FRAME)
    print("[demo]   rendering before / after / truth")
    r_before, r_after, r_truth = out / "before.png", out / "after.png", out / "truth_crop.png"
    render(blend, r_before, frame=FRAME - 1, hide=["Truth"], border=border, samples=samples)
    render(blend, r_after, frame=FRAME, hide=["Truth"], border=border, samples=samples)
    render(blend, r_truth, frame=FRAME, hide=["Face"], show=["Truth"], border=border, samples=samples)
    figures(out, img_dir, s, refined, U, L, lo_px, hi_px, r_before, r_after, r_truth, summary, err)
    (out / "refine_summary.json").write_text(json.dumps(summary, indent=2))
    return summary



def _row(part, summary):
    """One line of the final table: (step, measure, before, after, note)."""
    if part == "refine":
        return ("Refine Lips (1 frame)", "inner-lip RMS vs truth", f"{summary['lip_rms_mm_before']:.2f} mm",
                f"{summary['lip_rms_mm_after']:.2f} mm",
                f"contour {summary['contour_px_before']:.1f} -> {summary['contour_px_after']:.2f} px")
    if part == "propagate":
        return (f"Propagate ({summary['frames']} frames)", "held-out inner-lip RMS",
                f"{summary['held_out_lip_rms_mm_before']:.3f} mm", f"{summary['held_out_lip_rms_mm_after']:.3f} mm",
                f"{len(summary['training_frames'])} sketched frames, {summary['corrective_shapes']} FL_Prop keys")
    if part == "solve":
        a, b = summary["markers_only"], summary["markers_contours_corrective"]
        return ("Solve Performance", "inner-lip RMS (markers only -> + contours + corrective)",
                f"{a['lip_rms_mm']:.2f} mm", f"{b['lip_rms_mm']:.2f} mm",
                f"contour {a['inner_lip_contour_px_cam1']:.1f} -> {b['inner_lip_contour_px_cam1']:.1f} px")
    if part == "reconstruct":
        base = summary["blendshape_fit_baseline"]["front_face_mean_mm"]
        key = next(k for k in summary if k.startswith("reconstruct_smooth") and k != "reconstruct_smooth1")
        return ("Reconstruct from Bundles", "front-face mean error (blendshape fit -> FaceLab)", f"{base:.2f} mm",
                f"{summary[key]['front_face_mean_mm']:.2f} mm", f"{summary['bundles']} bundles")
    return (part, "", "", "", "")


def _table(rows, times, out):
    head = ("step", "measure", "before", "after", "time", "")
    body = [(*r[:4], f"{times[p]:.0f} s", r[4]) for p, r in rows]
    widths = [max(len(str(x[i])) for x in [head, *body]) for i in range(len(head))]
    line = lambda cells: "  ".join(str(c).ljust(w) for c, w in zip(cells, widths)).rstrip()  # noqa: E731
    print("[table] " + line(head))
    print("[table] " + "  ".join("-" * w for w in widths))
    for b in body:
        print("[table] " + line(b))


def supervise(argv) -> int:
    """Run the demo in a child process: show its ``[demo]`` progress lines and the final table, and send
    everything else (Blender's EGL and deprecation messages, render logs, per-frame detail) to
    ``OUT/demo.log``."""
    import subprocess

    ap = argparse.ArgumentParser(add_help=False)
    ap.add_argument("--out", default=str(ROOT / "out" / "demo"))
    known, _ = ap.parse_known_args(argv)
    out = Path(known.out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "demo.log"
    env = dict(os.environ, FACELAB_DEMO_CHILD="1", PYTHONUNBUFFERED="1")
    with open(log_path, "w") as log:
        p = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), *argv], env=env, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, bufsize=1)
        for line in p.stdout:
            log.write(line)
            log.flush()
            if line.startswith("[demo]"):
                print(line[len("[demo] "):].rstrip(), flush=True)
            elif line.startswith("[table]"):
                print(line[len("[table] "):].rstrip(), flush=True)
            elif line.startswith(("usage:", "demo.py: error")):
                print(line.rstrip(), flush=True)
        rc = p.wait()
    if rc not in (0, 2):  # 2: a usage error, already shown
        tail = log_path.read_text().splitlines()[-25:]
        print(f"The demo failed (exit {rc}); the end of {log_path}:", file=sys.stderr)
        print("\n".join("    " + t for t in tail), file=sys.stderr)
    else:
        print(f"Full log (Blender's own messages, renders): {log_path}")
    return rc


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if os.environ.get("FACELAB_DEMO_CHILD") != "1" and not {"-h", "--help"} & set(argv):
        return supervise(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "out" / "demo"))
    ap.add_argument("--images", default=None,
                    help="where the figures go (default: OUT/images; see --refresh-docs)")
    ap.add_argument("--refresh-docs", action="store_true",
                    help="write the figures into docs/images/, the README's pictures (tracked files)")
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--only", default=",".join(PARTS),
                    help="comma-separated parts to run, in this order: " + ",".join(PARTS) + " (default: all)")
    a = ap.parse_args(argv)
    parts = [p.strip() for p in a.only.split(",") if p.strip()]
    bad = [p for p in parts if p not in PARTS]
    if bad:
        ap.error(f"unknown part(s) {bad} in --only; choose from {','.join(PARTS)}")
    out = Path(a.out)
    img_dir = Path(a.images) if a.images else (ROOT / "docs" / "images" if a.refresh_docs else out / "images")
    out.mkdir(parents=True, exist_ok=True)
    img_dir.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(ROOT / "scripts"))

    from facelab_addon.core.capture.ict import load_ict

    t_all = time.perf_counter()
    print("[demo] loading the ICT-FaceKit face")
    ict = load_ict()
    times, rows = {}, []
    for i, part in enumerate(p for p in PARTS if p in parts):
        t0 = time.perf_counter()
        print(f"[demo] step {i + 1}/{len(parts)}: {STEP_TITLES[part]}")
        if part == "refine":
            summary = run_refine(ict, out, img_dir, a.samples)
        elif part == "propagate":
            from demo_propagate import run as run_propagation

            summary = run_propagation(ict, out, img_dir, render, a.samples)
        elif part == "solve":
            from demo_solve import run as run_solve

            summary = run_solve(ict, out, img_dir, render, min(a.samples, 16))
        else:
            from demo_reconstruct import run as run_reconstruct

            summary = run_reconstruct(ict, out, img_dir, render, min(a.samples, 16))
        times[part] = time.perf_counter() - t0
        rows.append((part, _row(part, summary)))
        print(f"[demo]   done in {times[part]:.0f} s; details in {out / (part + '_summary.json')}")
    for backup in out.rglob("*.blend1"):  # Blender's backup of a re-saved .blend: the demo wants one copy
        backup.unlink()
    print(f"[demo] finished in {time.perf_counter() - t_all:.0f} s: scenes (.blend) in {out}, figures in {img_dir}")
    _table(rows, times, out)
    return 0


STEP_TITLES = {
    "refine": "Refine Lips on one frame of a capture with a 2.5 mm lip gap",
    "propagate": "sketch a few frames of a 48-frame performance (over its plate), Propagate to all",
    "solve": "helmet stereo capture -> Bind Tracks -> Solve Performance -> Retarget",
    "reconstruct": "animated bundles -> Reconstruct from Bundles",
}


def figures(out, img_dir, s, refined, U, L, lo_px, hi_px, r_before, r_after, r_truth, summary, err):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    from facelab_addon.core.geometry.silhouette import lip_side, silhouette_edges

    cam, F, fixed = s["cam"], s["F"], s["fixed"]
    ext = (lo_px[0], hi_px[0], hi_px[1], lo_px[1])

    def silhouettes(ax, X, color):
        E = silhouette_edges(X, F, cam)
        E = E[~fixed[E].any(1)]
        p = cam.project(X)
        keep = ((p[E] >= lo_px) & (p[E] <= hi_px)).all(axis=(1, 2))
        E = E[keep]
        side = lip_side(X, F, cam, E[:, 0])
        for sd, ls in ((1, "-"), (-1, "-")):
            seg = p[E[side == sd]]
            ax.add_collection(LineCollection(seg, colors=color, linewidths=1.6, linestyles=ls))

    fig, axes = plt.subplots(1, 3, figsize=(18, 5.2))
    for ax, path, X, title in (
        (axes[0], r_before, s["captured"], "Capture (before): lips gap open"),
        (axes[1], r_after, refined, "Refine Lips (after)"),
        (axes[2], r_truth, s["truth"], "Ground truth"),
    ):
        ax.imshow(plt.imread(path), extent=ext)
        ax.plot(U[:, 0], U[:, 1], color="#ff3b30", lw=1.2, ls="--", label="sketch: upper lip")
        ax.plot(L[:, 0], L[:, 1], color="#0a84ff", lw=1.2, ls="--", label="sketch: lower lip")
        silhouettes(ax, X, "#ffd60a")
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_title(title)
        ax.axis("off")
    axes[0].plot([], [], color="#ffd60a", lw=1.6, label="mesh inner-lip silhouette")
    axes[0].legend(loc="lower left", fontsize=8, framealpha=0.8)
    fig.suptitle(
        f"Contour error {summary['contour_px_before']:.1f} px -> {summary['contour_px_after']:.2f} px;  "
        f"inner-lip RMS {summary['lip_rms_mm_before']:.2f} mm -> {summary['lip_rms_mm_after']:.2f} mm"
    )
    fig.tight_layout()
    fig.savefig(img_dir / "refine_before_after.png", dpi=90)
    plt.close(fig)

    # 3D error heat map on the lips, before and after (frontal projection)
    p = cam.project(s["truth"])
    sel = ~fixed & (p >= lo_px).all(1) & (p <= hi_px).all(1)
    e0, e1 = err(s["captured"]), err(refined)
    vmax = max(e0[sel].max(), 1e-6)
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.6))
    for ax, e, title in ((axes[0], e0, "before"), (axes[1], e1, "after")):
        sc = ax.scatter(p[sel, 0], p[sel, 1], c=e[sel], s=6, cmap="inferno", vmin=0, vmax=vmax)
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect("equal")
        ax.set_title(f"3D error vs truth, {title} (mm)")
        ax.axis("off")
    fig.colorbar(sc, ax=axes, fraction=0.025, label="mm")
    fig.savefig(img_dir / "refine_error_heatmap.png", dpi=90)
    plt.close(fig)
    print(f"wrote {img_dir / 'refine_before_after.png'} and {img_dir / 'refine_error_heatmap.png'}")


if __name__ == "__main__":
    sys.exit(main())
