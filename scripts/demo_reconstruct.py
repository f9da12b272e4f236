"""Demo step 4: Reconstruct from Bundles (Cong, Lan & Fedkiw 2019, local geometric indexing).

The face carries a dataset of ICT shapes as shape keys (the expressions,
nonlinear in-betweens and FACS-style combinations of ``testing.datasets``). A
held-out performance (combinations that are not in the dataset, eased from
pose to pose) is seen only through 100 bundles (animated empties in a
collection ``FL_bundles``, 0.5 mm Gaussian noise, like a mocap solve). The
artist runs **Reconstruct from Bundles** with smoothing; the demo compares it
with the simple method an artist would otherwise use: a bounded blendshape fit of the
same bundles (weights in [0, 1], ``scipy.optimize.lsq_linear``).

Writes out/demo/reconstruct.blend, out/demo/reconstruct_summary.json and
docs/images/demo_reconstruct_*.png.
"""

from __future__ import annotations

import atexit
import json
import time

import numpy as np

SCALE = 0.01  # ICT centimetres -> metres
N_FRAMES = 25  # frame 0: the neutral (bind frame)
N_BUNDLES = 100
NOISE_MM = 0.5
SMOOTH = 3


def run(ict, out, img_dir, render, samples):
    import bpy

    import facelab_addon
    from facelab_addon.blender import compat
    from facelab_addon.blender.caches import evaluate_frames
    from facelab_addon.blender.camera import new_camera_object
    from facelab_addon.blender.scene import add_studio_lights
    from facelab_addon.core.lgi.fit_residual import FitResidual
    from facelab_addon.core.lgi.natural_neighbor import surface_points
    from facelab_addon.names import BUNDLES_COLLECTION
    from facelab_addon.testing import datasets as ds
    from facelab_addon.testing import synthetic as syn
    from facelab_addon.testing.scenes import baked_sequence_object, build_ict_face_scene, keyed_empties

    t_start = time.perf_counter()
    F = ict.faces
    data = ds.ict_dataset(ict)
    gen = data.generator
    neutral = ict.neutral * SCALE
    bf, bb = ds.ict_bundle_layout(ict, N_BUNDLES)
    AW = ds.animated_weights(N_FRAMES - 1, seed=3, hold=6)
    truth = np.concatenate([neutral[None], np.stack([gen(w) for w in AW]) * SCALE])  # (T,V,3) m
    rng = np.random.default_rng(5)
    Q = surface_points(truth, F, bf, bb)
    Qn = Q + NOISE_MM * 1e-3 * rng.standard_normal(Q.shape)
    Qn[0] = Q[0]  # the bind frame: the neutral, clean
    frames = np.arange(N_FRAMES)

    fs = build_ict_face_scene(ict, shapes=dict(zip(data.names, data.shapes)), frame_range=(0, N_FRAMES - 1),
                              scale=SCALE, uv_layer=True)
    scene, face = fs.scene, fs.obj
    if "facelab_solve" not in bpy.types.Scene.bl_rna.properties:  # earlier demo steps registered it
        facelab_addon.register()
        atexit.register(facelab_addon.unregister)  # bpy 4.5 hangs at exit with FaceLab registered
    mat = bpy.data.materials.new("Skin")
    compat.node_tree(mat)
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.8, 0.55, 0.45, 1)
    bsdf.inputs["Roughness"].default_value = 0.55
    face.data.materials.append(mat)
    coll = bpy.data.collections.new(BUNDLES_COLLECTION)
    scene.collection.children.link(coll)
    keyed_empties(scene, Qn, digits=3, collection=coll, display_size=0.0015)
    recon = scene.facelab_recon
    recon.bundle_source, recon.bundle_collection, recon.bind_frame = "COLLECTION", coll, 0
    scene.facelab.face = face
    t_build = time.perf_counter() - t_start
    print(f"[demo]   reconstruct scene built: {len(data.names)} dataset shape keys, {N_BUNDLES} bundle empties x "
          f"{N_FRAMES} frames ({t_build:.1f} s)")

    skin = ict.part_vertex_mask("M_Face")
    front = skin & (neutral[:, 2] > 0.07)

    def err(X):
        e = np.linalg.norm(X - truth, axis=2)[1:] * 1e3  # mm, frames 1..
        return dict(front_face_mean_mm=float(e[:, front].mean()), front_face_max_mm=float(e[:, front].max()),
                    skin_mean_mm=float(e[:, skin].mean()),
                    front_face_mean_mm_per_frame=[round(float(v), 3) for v in e[:, front].mean(1)])

    results, timings = {}, {}
    for smooth in (1, SMOOTH):
        recon.smooth = smooth
        t0 = time.perf_counter()
        assert bpy.ops.facelab.reconstruct_from_bundles() == {"FINISHED"}
        timings[f"reconstruct_smooth{smooth}_s"] = round(time.perf_counter() - t0, 2)
        X = evaluate_frames(face, frames, mute_shape_keys_prefix=())
        results[f"reconstruct_smooth{smooth}"] = (X, err(X))
        print(f"[demo]   Reconstruct from Bundles (smoothing {smooth}): front-face mean error "
              f"{results[f'reconstruct_smooth{smooth}'][1]['front_face_mean_mm']:.3f} mm")
    t0 = time.perf_counter()
    S = data.shapes * SCALE  # (S,V,3) dataset shapes as positions
    fit = FitResidual(neutral, F, S, bf, bb)  # only its bounded fit (weights in [0,1]) is used here
    B = S - neutral  # the shapes' offsets from the neutral
    Xb = np.stack([neutral] + [neutral + np.tensordot(fit.fit_weights(Qn[t]), B, axes=1) for t in frames[1:]])
    timings["blendshape_fit_s"] = round(time.perf_counter() - t0, 2)
    results["blendshape_fit_baseline"] = (Xb, err(Xb))
    X = results[f"reconstruct_smooth{SMOOTH}"][0]

    truth_ob = baked_sequence_object(ict, "Truth", truth, frames)
    fit_ob = baked_sequence_object(ict, "Blendshape fit (baseline)", Xb, frames)
    for ob in (truth_ob, fit_ob):
        ob.data.materials.append(mat)
        ob.hide_render = True
        ob.hide_set(True)
    mouth = neutral[syn.ICT_MOUTH_LOOP].mean(0)
    cam = syn.frontal_camera(neutral, mouth + [0, 0.025, 0], distance=0.55)
    cam_obj = new_camera_object(scene, cam)
    add_studio_lights(scene)
    bpy.context.view_layer.objects.active = face
    blend = out / "reconstruct.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    print(f"[demo]   saved {blend}")

    # the figure frame: where the baseline is worst
    f = 1 + int(np.argmax(results["blendshape_fit_baseline"][1]["front_face_mean_mm_per_frame"]))
    p = cam.project(neutral[front])
    lo, hi = p.min(0) - 40, p.max(0) + 40
    lo, hi = np.maximum(lo, 0), np.minimum(hi, [cam.width, cam.height])
    border = [lo[0] / cam.width, hi[0] / cam.width, 1 - hi[1] / cam.height, 1 - lo[1] / cam.height]
    names = ["Face", "Truth", "Blendshape fit (baseline)"]
    r = {k: out / f"reconstruct_{k}.png" for k in ("truth", "fit", "recon")}
    print(f"[demo]   rendering reconstruct frame {f}, Cycles CPU")
    t0 = time.perf_counter()
    for k, name in (("truth", "Truth"), ("fit", "Blendshape fit (baseline)"), ("recon", "Face")):
        render(blend, r[k], frame=f, hide=[n for n in names if n != name], show=[name],
               border=border, samples=samples)
    timings["render_s"] = round(time.perf_counter() - t0, 1)
    summary = dict(frames=N_FRAMES, bundles=N_BUNDLES, bundle_noise_mm=NOISE_MM, dataset_shapes=len(data.names),
                   smoothing_frames=SMOOTH, figure_frame=f, note="errors over frames 1..; frame 0 is the bind "
                   "frame (neutral); 'front face' = M_Face vertices with z > 7 cm (the area the bundles cover)",
                   **{k: v[1] for k, v in results.items()}, timings=timings, build_scene_s=round(t_build, 1))
    figure(img_dir, r, cam, (lo, hi), truth[f], {k: v[0][f] for k, v in results.items()}, Qn[f], front, summary, f)
    (out / "reconstruct_summary.json").write_text(json.dumps(summary, indent=2))
    summary["total_s"] = round(time.perf_counter() - t_start, 1)
    return summary


def figure(img_dir, r, cam, box, truth, X, q, front, summary, f):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = box
    ext = (lo[0], hi[0], hi[1], lo[1])
    bl, rc = "blendshape_fit_baseline", f"reconstruct_smooth{SMOOTH}"
    e = {k: np.linalg.norm(X[k] - truth, axis=1) * 1e3 for k in (bl, rc)}
    vmax = 5.0  # mm; larger errors saturate
    p = cam.project(truth)
    fig, axes = plt.subplots(2, 3, figsize=(13, 9.6))
    for ax, k, title in ((axes[0, 0], "truth", "Ground truth (held-out pose)"),
                         (axes[0, 1], "fit", "Blendshape fit of the bundles (baseline)"),
                         (axes[0, 2], "recon", f"Reconstruct from Bundles (smoothing {SMOOTH})")):
        ax.imshow(plt.imread(r[k]), extent=ext)
        ax.set_title(title, fontsize=10)
    pq = cam.project(q)
    axes[0, 0].plot(pq[:, 0], pq[:, 1], ".", ms=3, color="#0a84ff", label=f"bundles (+{NOISE_MM} mm noise)")
    axes[0, 0].legend(loc="lower left", fontsize=8)
    axes[1, 0].axis("off")
    axes[1, 0].text(0.02, 0.5, "\n".join([
        f"frame {f}, {summary['bundles']} bundles,",
        f"{summary['dataset_shapes']} dataset shapes",
        "",
        "mean front-face error, all frames:",
        f"  blendshape fit     {summary[bl]['front_face_mean_mm']:.2f} mm",
        f"  reconstruct        {summary['reconstruct_smooth1']['front_face_mean_mm']:.2f} mm",
        f"  + smoothing {SMOOTH}      {summary[rc]['front_face_mean_mm']:.2f} mm"]),
        fontsize=10, family="monospace", va="center")
    for ax, k, title in ((axes[1, 1], bl, "error vs truth: blendshape fit"),
                         (axes[1, 2], rc, "error vs truth: Reconstruct from Bundles")):
        o = np.argsort(e[k][front])
        sc = ax.scatter(p[front][o, 0], p[front][o, 1], c=e[k][front][o], s=3, cmap="inferno", vmin=0, vmax=vmax)
        ax.set_title(f"{title}\nmean {e[k][front].mean():.2f} mm, max {e[k][front].max():.2f} mm", fontsize=10)
        ax.set_facecolor("#202020")
    for ax in axes.ravel()[[0, 1, 2, 4, 5]]:
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(sc, ax=axes[1, 1:], fraction=0.03, label="mm", extend="max")
    fig.savefig(img_dir / "demo_reconstruct_before_after.png", dpi=80, bbox_inches="tight")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 3.4))
    t = np.arange(1, summary["frames"])
    for lab, k, st in (("blendshape fit (baseline)", bl, "o-"), ("Reconstruct from Bundles", "reconstruct_smooth1", "s-"),
                       (f"Reconstruct from Bundles, smoothing {SMOOTH}", rc, "^-")):
        ax.plot(t, summary[k]["front_face_mean_mm_per_frame"], st, ms=4, label=lab)
    ax.set_xlabel("frame")
    ax.set_ylabel("mean front-face error (mm)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(img_dir / "demo_reconstruct_errors.png", dpi=90)
    plt.close(fig)
    print(f"wrote {img_dir}/demo_reconstruct_before_after.png, demo_reconstruct_errors.png")
