"""Benchmark: retargeting to a wide-mouthed creature with the lip-sync heuristic (Bhat et al. 2013 §5.1).

Actor: ICT-FaceKit (metres). Creature: an ICT identity whose mouth is widened
by a smooth warp (``retarget.widen_mouth``, 1.6x stretch at the mouth centre
with a Gaussian falloff): same topology, so the correspondence is the vertex
map. The actor's 57 expressions are deformation-transferred once; the actor
performs a speech-like sequence of mouth shapes (open jaw, "ee", "oo", closed
"mm", "ah"; ``testing.weights.viseme_weights``) with a small per-frame
out-of-subspace corrective (a lip pout).
The creature copies the weights and gets the transferred corrective, with and
without the lip-sync heuristic.

Reported (millimetres): along the creature's talking portion (its length
matched to the actor's lips), the absolute difference between the creature's
and the actor's upper-to-lower lip distances at corresponding points (arc
length), and the creature's lip gap between each original corner and its new
end point (the part the heuristic seals). Also: time per frame, and sanity
checks of the transfer on ICT (identity deformation, identical creature).

    python benchmarks/retarget.py [--quick] [--no-render] [--samples 16]

Prints one JSON object and writes benchmarks/results/retarget.json and the
picture docs/images/retarget_lipsync.png (Cycles CPU renders in a subprocess,
see scripts/render_blend.py).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _harness import user_resources  # noqa: E402

from facelab_addon.core.capture.ict import load_ict  # noqa: E402
from facelab_addon.core.geometry.laplacian import uniform_laplacian  # noqa: E402
from facelab_addon.core.solve.deformation_transfer import (  # noqa: E402
    DeformationTransfer,
    triangle_correspondence_from_markers,
)
from facelab_addon.core.solve.lip_contours import EndPoints, lip_contours, lip_distances  # noqa: E402
from facelab_addon.core.solve.lip_sync import LipSync, LipSyncParams  # noqa: E402
from facelab_addon.core.solve.retarget import Retargeter  # noqa: E402
from facelab_addon.testing.creature import widen_mouth  # noqa: E402
from facelab_addon.testing.weights import viseme_weights  # noqa: E402

MM = 1000.0  # metres -> millimetres
IDENTITY = "identity003"
FACTOR = 1.6


def pout(V, center, amount):
    """Actor corrective: lips pushed forward by ``amount`` metres, Gaussian falloff (6 mm x 12 mm)."""
    d = V - center
    g = np.exp(-0.5 * ((d[:, 0] / 0.018) ** 2 + (d[:, 1] / 0.008) ** 2 + (d[:, 2] / 0.012) ** 2))
    out = np.zeros_like(V)
    out[:, 2] = amount * g
    return out


def run(quick: bool = False, render: bool = True, samples: int = 24, png=None) -> dict:
    t_load = time.perf_counter()
    m = load_ict(scale=0.01)
    V, F = m.neutral, m.faces
    names = m.expression_names
    D = m.deltas(names)
    ac = lip_contours(V, F)
    center = V[ac.vertices].mean(0)
    C = widen_mouth(m.pose(identity={IDENTITY: 1.0}), center, factor=FACTOR)
    t_load = time.perf_counter() - t_load

    # sanity of the transfer on ICT
    t0 = time.perf_counter()
    same = DeformationTransfer(V, F, V, F)
    t_same = time.perf_counter() - t0
    jaw = D[names.index("jawOpen")]
    ident_err = np.abs(DeformationTransfer(V, F, C, F).transfer_deltas(np.zeros_like(V))).max() * MM
    repro_err = np.abs(same.transfer_deltas(jaw) - jaw).max() * MM

    rt = Retargeter(V, F, D, C, F, actor_contours=ac)
    cc = rt.lip_sync.creature_contours
    # the former settings (strong 1000 constraints on the raw targets), for the smoothness comparison only
    old_ls = LipSync(C, F, cc, ac, params=LipSyncParams(strength=1000.0, seal_strength=1000.0, smooth=0.0))
    Lu = uniform_laplacian(F, len(V))
    W = viseme_weights(names, 2 if quick else 4)
    T = len(W)
    amount = 0.0015 * np.sin(np.linspace(0, 3 * np.pi, T)) ** 2  # up to 1.5 mm pout
    rows = []
    t_corr, t_ls = [], []
    frames_out = {}
    eps = {}
    for t in range(T):
        corr = pout(V, center, amount[t])
        ta = time.perf_counter()
        c0, _ = rt.frame(W[t], corr, lip_sync=False)  # copied weights + transferred corrective
        tb = time.perf_counter()
        blend_c = C + np.tensordot(W[t], rt.creature_deltas, 1)
        A = V + np.tensordot(W[t], D, 1) + corr
        X0 = blend_c + c0
        X1, info = rt.lip_sync.solve(A, X0)  # what rt.frame(W[t], corr) adds
        tc = time.perf_counter()
        t_corr.append(tb - ta)
        t_ls.append(tc - tb)
        ep = info["end_points"]
        r0 = lip_distances(A, ac, X0, cc, ep, reference=X0)
        r1 = lip_distances(A, ac, X1, cc, ep, reference=X0)
        rw = lip_distances(A, ac, X0, cc, EndPoints())  # plain transfer, whole contour against whole contour
        X_old, _ = old_ls.solve(A, X0)
        rough = {}
        for lab, Xs in (("new", X1), ("old", X_old)):
            dd = Xs - X0
            mv = np.linalg.norm(dd, axis=1) > 1e-5
            rg = np.linalg.norm(Lu @ dd, axis=1) * MM
            rough[lab] = (float(np.percentile(rg[mv], 99)) if mv.any() else 0.0, float(rg.max()),
                          float(np.linalg.norm(dd, axis=1).max() * MM))
        rows.append(dict(
            roughness_p99_mm=rough["new"][0], roughness_max_mm=rough["new"][1], lip_sync_motion_max_mm=rough["new"][2],
            old_roughness_p99_mm=rough["old"][0], old_roughness_max_mm=rough["old"][1],
            old_lip_sync_motion_max_mm=rough["old"][2],
            actor_max_gap_mm=float(r0["actor"].max() * MM),
            without_mean=float(r0["abs_diff"].mean() * MM), without_max=float(r0["abs_diff"].max() * MM),
            with_mean=float(r1["abs_diff"].mean() * MM), with_max=float(r1["abs_diff"].max() * MM),
            sealed_without_max=float(r0["sealed"].max() * MM) if len(r0["sealed"]) else 0.0,
            sealed_with_max=float(r1["sealed"].max() * MM) if len(r1["sealed"]) else 0.0,
            whole_contour_without_mean=float(rw["abs_diff"].mean() * MM),
            whole_contour_without_max=float(rw["abs_diff"].max() * MM),
            talking_fraction=float(np.mean([ep.upper[1] - ep.upper[0], ep.lower[1] - ep.lower[0]])),
        ))
        frames_out[t] = (A, X0, X1)
        eps[t] = ep

    # the artist's knob: a distance threshold lets the talking portion be longer than the actor's lips
    thresholds = {}
    for th_mm in (0.0, 5.0, 10.0):
        fr, dm, sg = [], [], []
        for t in range(0, T, 2):
            A, X0, _ = frames_out[t]
            X, inf = rt.lip_sync.solve(A, X0, threshold=th_mm / MM)
            ep = inf["end_points"]
            r = lip_distances(A, ac, X, cc, ep, reference=X0)
            fr.append(np.mean([ep.upper[1] - ep.upper[0], ep.lower[1] - ep.lower[0]]))
            dm.append(r["abs_diff"].mean() * MM)
            sg.append(r["sealed"].max() * MM if len(r["sealed"]) else 0.0)
        thresholds[f"{th_mm:g}mm"] = dict(talking_fraction=float(np.mean(fr)), abs_diff_mean_mm=float(np.mean(dm)),
                                          sealed_gap_max_mm=float(np.max(sg)))

    def agg(key, fn):
        return float(fn([r[key] for r in rows]))

    # open frames matter most: the lips are apart, so the shape reads
    open_rows = [r for r in rows if r["actor_max_gap_mm"] > 3.0]
    res = dict(
        actor="ICT-FaceKit neutral (metres)",
        creature=f"ICT {IDENTITY} with the mouth widened x{FACTOR} (widen_mouth), same topology",
        vertices=int(len(V)), shapes=len(names), frames=T, open_frames=len(open_rows),
        actor_lip_length_mm=float(np.linalg.norm(np.diff(V[ac.upper], axis=0), axis=1).sum() * MM),
        creature_lip_length_mm=float(np.linalg.norm(np.diff(C[cc.upper], axis=0), axis=1).sum() * MM),
        creature_mouth_width_mm=float(np.linalg.norm(C[cc.corners[0]] - C[cc.corners[1]]) * MM),
        actor_mouth_width_mm=float(np.linalg.norm(V[ac.corners[0]] - V[ac.corners[1]]) * MM),
        talking_fraction_mean=agg("talking_fraction", np.mean),
        lip_distance_abs_diff_mm=dict(
            without_lip_sync=dict(mean=agg("without_mean", np.mean), max=agg("without_max", np.max)),
            with_lip_sync=dict(mean=agg("with_mean", np.mean), max=agg("with_max", np.max)),
        ),
        lip_distance_abs_diff_whole_contour_without_lip_sync_mm=dict(
            mean=agg("whole_contour_without_mean", np.mean), max=agg("whole_contour_without_max", np.max)),
        sealed_gap_max_mm=dict(without_lip_sync=agg("sealed_without_max", np.max),
                               with_lip_sync=agg("sealed_with_max", np.max)),
        threshold_sweep=thresholds,
        lip_sync_smoothness_mm=dict(
            definition="|d_i - mean of the neighbours' d| of the lip-sync offset d = X_lipsync - X_transferred, "
                       "99th percentile over the moved vertices (max over frames) and largest value",
            current=dict(p99=agg("roughness_p99_mm", np.max), max=agg("roughness_max_mm", np.max),
                         motion_max=agg("lip_sync_motion_max_mm", np.max)),
            former_strength_1000_unsmoothed=dict(p99=agg("old_roughness_p99_mm", np.max),
                                                 max=agg("old_roughness_max_mm", np.max),
                                                 motion_max=agg("old_lip_sync_motion_max_mm", np.max)),
        ),
        mean_diff_ratio_with_over_without=agg("with_mean", np.mean) / max(agg("without_mean", np.mean), 1e-12),
        transfer_checks_mm=dict(identity_deformation_max=float(ident_err), identical_creature_jawOpen_max=float(repro_err)),
        timing_s=dict(
            load=round(t_load, 3), transfer_factor=round(rt.info["factor_s"], 3),
            transfer_57_shapes=round(rt.info["transfer_shapes_s"], 3),
            lip_sync_setup=round(rt.info["lip_sync_setup_s"], 3),
            same_topology_factor=round(t_same, 3),
            per_frame_corrective_transfer_mean=float(np.mean(t_corr)),
            per_frame_lip_sync_mean=float(np.mean(t_ls)),
            per_frame_total_mean=float(np.mean(t_corr) + np.mean(t_ls)),
        ),
        per_frame=rows,
        note="timings measured on a 2-core machine shared with other jobs (noisy)",
    )
    if not quick:
        res["different_topology_marker_correspondence"] = marker_correspondence_check(m, C)
    gaps = np.array([r["actor_max_gap_mm"] for r in rows])
    pick = [int(np.argmax(gaps)), int(np.argsort(gaps)[len(gaps) // 2])]
    pick = sorted(set(pick), key=lambda i: -gaps[i])
    png = Path(png) if png else (None if quick else ROOT / "docs" / "images" / "retarget_lipsync.png")
    if png is not None:
        cpng = png.with_name(png.stem + "_contours.png")
        contour_figure(frames_out, pick, rows, ac, cc, eps, cpng)
        res["contour_picture"] = str(cpng.relative_to(ROOT)) if cpng.is_relative_to(ROOT) else str(cpng)
    if render and png is not None:
        t0 = time.perf_counter()
        render_comparison(m, frames_out, pick, rows, png, samples=samples)
        res["picture"] = str(png.relative_to(ROOT)) if png.is_relative_to(ROOT) else str(png)
        res["picture_frames"] = pick
        res["timing_s"]["render"] = round(time.perf_counter() - t0, 1)
    return res


def marker_correspondence_check(m, C, names=("jawOpen", "mouthFunnel")) -> dict:
    """Different topology: the creature's quads split along the other diagonal, correspondence from the 68
    ICT landmarks (with the ICT materials as part labels); transferred shapes against the vertex-map transfer."""
    V, F = m.neutral, m.faces
    off, pv = m.poly_offsets, m.poly_verts
    tris, tpoly = [], []
    for p in range(len(off) - 1):
        c = pv[off[p] : off[p + 1]]
        new = [[c[1], c[2], c[3]], [c[1], c[3], c[0]]] if len(c) == 4 else [[c[0], c[i], c[i + 1]]
                                                                            for i in range(1, len(c) - 1)]
        tris += new
        tpoly += [p] * len(new)
    Ft = np.array(tris, dtype=np.int64)
    tpoly = np.array(tpoly)
    t0 = time.perf_counter()
    corr = triangle_correspondence_from_markers(V, F, C, Ft, m.landmarks, m.landmarks,
                                                source_groups=m.poly_part[m.tri_poly], target_groups=m.poly_part[tpoly])
    t_corr = time.perf_counter() - t0
    d = m.deltas(list(names))
    ref = DeformationTransfer(V, F, C, F).transfer_deltas(d)
    out = DeformationTransfer(V, F, C, Ft, corr).transfer_deltas(d)
    face = m.part_vertex_mask("M_Face")
    res = dict(creature="same vertices, quads split along the other diagonal", markers=int(len(m.landmarks)),
               correspondence_s=round(t_corr, 2))
    for k, n in enumerate(names):
        e = np.linalg.norm(out[k] - ref[k], axis=1)[face] * MM
        res[n] = dict(face_err_mean_mm=float(e.mean()), face_err_p95_mm=float(np.percentile(e, 95)),
                      face_err_max_mm=float(e.max()), motion_max_mm=float(np.linalg.norm(ref[k], axis=1).max() * MM))
    return res


# --------------------------------------------------------------------------
# picture: Cycles CPU in a subprocess
# --------------------------------------------------------------------------


def render_comparison(m, frames_out, pick, rows, png, samples=16):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with tempfile.TemporaryDirectory(prefix="facelab-retarget-") as tmp:
        tmp = Path(tmp)
        arrays = {}
        for r, t in enumerate(pick):
            A, X0, X1 = frames_out[t]
            for c, X in enumerate((A, X0, X1)):
                arrays[f"v_{r}_{c}"] = X
        np.savez(tmp / "scene.npz", poly_verts=m.poly_verts, poly_offsets=m.poly_offsets, poly_part=m.poly_part,
                 parts=np.array(m.parts), rows=len(pick), **arrays)
        blend = tmp / "retarget.blend"
        subprocess.run([sys.executable, __file__, "--build-blend", str(tmp / "scene.npz"), str(blend)], check=True,
                       cwd=ROOT, stdout=subprocess.DEVNULL)
        raw = tmp / "render.png"
        subprocess.run([sys.executable, str(ROOT / "scripts" / "render_blend.py"), str(blend), str(raw),
                        "--samples", str(samples)], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        img = plt.imread(raw)
    h, w = img.shape[:2]
    top = 60  # title band, pixels
    fig = plt.figure(figsize=(w / 100, (h + top) / 100), dpi=100)
    ax = fig.add_axes([0, 0, 1, h / (h + top)])
    ax.imshow(img)
    ax.axis("off")
    titles = ["actor (ICT)", "creature: deformation transfer only", "creature: + lip-sync heuristic"]
    for c, ttl in enumerate(titles):
        fig.text((c + 0.5) / 3, 1 - 0.5 * top / (h + top), ttl, ha="center", va="center", fontsize=15)
    for r, t in enumerate(pick):
        row = rows[t]
        y = 1 - (top + (r + 1) * h / len(pick)) / (h + top) + 0.02
        fig.text(1 / 3 + 0.005, y, f"frame {t}: lip-distance error mean {row['without_mean']:.1f} mm, "
                 f"sides open up to {row['sealed_without_max']:.1f} mm", fontsize=10, color="w")
        fig.text(2 / 3 + 0.005, y, f"mean {row['with_mean']:.2f} mm, sealed sides {row['sealed_with_max']:.2f} mm",
                 fontsize=10, color="w")
        fig.text(0.005, y, f"frame {t}: lips {row['actor_max_gap_mm']:.0f} mm apart", fontsize=10, color="w")
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)
    try:  # Cycles noise makes big PNGs: 1200 px wide, 128 colours (about 0.35 MB instead of 1.5 MB)
        from PIL import Image

        im = Image.open(png).convert("RGB")
        im = im.resize((1200, round(im.size[1] * 1200 / im.size[0])), Image.LANCZOS)
        im.quantize(colors=128, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(png, optimize=True)
    except ImportError:
        pass


def contour_figure(frames_out, pick, rows, ac, cc, end_points, png):
    """Front view (x, y in mm) of the inner-lip contours: actor, creature by transfer, creature with lip sync."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from facelab_addon.core.solve.lip_contours import contour_points

    fig, axes = plt.subplots(len(pick), 1, figsize=(8.0, 3.4 * len(pick)))
    axes = np.atleast_1d(axes)
    for ax, t in zip(axes, pick):
        A, X0, X1 = frames_out[t]
        for X, cont, col, lab in ((X0, cc, "tab:blue", "creature: transfer only"),
                                  (X1, cc, "tab:red", "creature: + lip sync"), (A, ac, "k", "actor")):
            for j, ch in enumerate((cont.upper, cont.lower)):
                ax.plot(X[ch, 0] * MM, X[ch, 1] * MM, "-", color=col, lw=1.6, label=lab if j == 0 else None)
        ep = end_points[t]
        for ch, f in ((cc.upper, ep.upper), (cc.lower, ep.lower)):
            e, b, _ = contour_points(X0, ch, f)  # end points are placed on the transferred frame
            P = b[:, :1] * X1[e[:, 0]] + b[:, 1:] * X1[e[:, 1]]
            ax.plot(P[:, 0] * MM, P[:, 1] * MM, "o", color="tab:red", ms=5, mfc="w")
        ax.set_title(f"frame {t}: talking portion {100 * rows[t]['talking_fraction']:.0f} % of the creature's lips "
                     "(o = new end points)", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    axes[0].legend(frameon=False, fontsize=8, loc="upper center", ncol=3, bbox_to_anchor=(0.5, -0.18))
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=80)
    plt.close(fig)


def build_blend(npz_path, blend_path):
    """Run in a subprocess: a .blend with actor / creature / creature + lip sync in a grid, ortho camera."""
    user_resources("facelab-bl-")
    import bpy

    from facelab_addon.blender import compat
    from facelab_addon.blender.scene import add_studio_lights, new_mesh_object

    z = np.load(npz_path)
    rows = int(z["rows"])
    parts = [str(p) for p in z["parts"]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    mats = {}
    for name, col, rough in (("Skin", (0.8, 0.55, 0.45), 0.5), ("Mouth", (0.35, 0.08, 0.08), 0.6),
                             ("Teeth", (0.9, 0.88, 0.8), 0.3)):
        mt = bpy.data.materials.new(name)
        if mt.node_tree is None:
            compat.node_tree(mt)
        bsdf = mt.node_tree.nodes["Principled BSDF"]
        bsdf.inputs["Base Color"].default_value = (*col, 1)
        bsdf.inputs["Roughness"].default_value = rough
        mats[name] = mt
    part_mat = np.zeros(len(parts), np.int32)
    for i, p in enumerate(parts):
        part_mat[i] = 1 if p == "M_GumsTongue" else 2 if p == "M_Teeth" else 0
    pidx = part_mat[z["poly_part"]]
    # crop every copy to a box around the mouth so the copies in the grid do not overlap
    dx, dy = 0.12, 0.08
    box_lo, box_hi = np.array([-dx / 2, -0.034 - dy / 2, 0.04]), np.array([dx / 2, -0.034 + dy / 2, 1.0])
    pv, off = z["poly_verts"], z["poly_offsets"]
    counts = np.diff(off)
    poly_of_corner = np.repeat(np.arange(len(counts)), counts)
    for r in range(rows):
        for c in range(3):
            X = z[f"v_{r}_{c}"].copy()
            inside = ((X >= box_lo) & (X <= box_hi)).all(axis=1)
            keep = np.ones(len(counts), bool)
            np.logical_and.at(keep, poly_of_corner, inside[pv])
            kc = keep[poly_of_corner]
            used = np.unique(pv[kc])
            remap = -np.ones(len(X), np.int64)
            remap[used] = np.arange(len(used))
            Xs = X[used]
            Xs[:, 0] += (c - 1) * dx
            Xs[:, 1] -= r * dy
            off_k = np.r_[0, np.cumsum(counts[keep])]
            ob = new_mesh_object(f"p{r}{c}", Xs, poly_verts=remap[pv[kc]], poly_offsets=off_k)
            for mt in mats.values():
                ob.data.materials.append(mt)
            ob.data.polygons.foreach_set("material_index", pidx[keep])
            ob.data.polygons.foreach_set("use_smooth", np.ones(int(keep.sum()), bool))
            ob.data.update()
    cy = -0.034 - (rows - 1) * dy / 2
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.data.type = "ORTHO"
    cam.data.ortho_scale = 3 * dx
    cam.location = (0.0, cy, 0.6)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.resolution_x = 1500
    scene.render.resolution_y = int(round(1500 * rows * dy / (3 * dx)))
    scene.render.resolution_percentage = 100
    add_studio_lights(scene)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend_path))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-render", action="store_true")
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--png", default=None)
    ap.add_argument("--build-blend", nargs=2, metavar=("NPZ", "BLEND"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.build_blend:
        build_blend(*a.build_blend)
        return
    res = run(quick=a.quick, render=not a.no_render, samples=a.samples, png=a.png)
    out = ROOT / "benchmarks" / "results" / "retarget.json"
    if not a.quick:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
