"""Benchmark: sketch-based lip refinement (Dinev et al. 2018, §5) on ICT-FaceKit.

Ground truth: ICT-FaceKit poses (26,719 vertices, centimetres). For each case
a capture error is injected into the inner lips of the truth
(``testing.synthetic.inject_lip_error``: the same smooth, deterministic error for
every method), the "artist's sketch" is the truth's inner-lip silhouettes in a
frontal camera (1920x1080, 50 mm lens, 40 cm in front of the mouth,
``testing.synthetic.lip_contours``), and ``core.lips.sketch.refine_lips`` corrects the
captured mesh from that sketch with the paper's settings (5 iterations,
lambda_pos 0.1 / 1 for the hidden parts, lambda_reg 3, lambda_silh 1).

Reported per case:

* ``contour_px``: distance in pixels from the mesh's inner-lip silhouette
  (the contour an artist would see, ``lip_contours`` of that mesh) to the
  sketch polyline, before and after; and the other direction (sketch to
  silhouette) after, so a silhouette that covers only part of the sketch
  cannot pass;
* ``lip_error_mm``: RMS and max 3D distance to the truth over the inner-lip
  region (``synthetic.inner_lip_mask``: the support of the injected error),
  before and after, and the RMS reduction;
* ``midline_separation_mm``: upper minus lower lip tip at the midline;
* ``seconds``: wall time of one ``refine_lips`` call (5 iterations, whole
  face, including building and factoring its system), the first call of the
  case reported as ``cold`` and excluded from the median of the others (only
  the first case's cold call is also cold for the process);
* ``blender_laplacian_deform``: Blender's Laplacian Deform modifier (bpy,
  headless) on the same mesh, anchored at the vertices our solve holds
  (hidden parts and everything outside its free region) plus the matched lip
  silhouette vertices moved to our refined positions; bind and evaluation
  timed separately.

Usage: ``PYTHONPATH=. python benchmarks/sketch_refine.py [--quick] [--no-blender]``.
Prints one JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from facelab_addon.core.capture.ict import load_ict  # noqa: E402
from facelab_addon.core.errors import FaceLabError  # noqa: E402
from facelab_addon.core.geometry.silhouette import point_segment_distance  # noqa: E402
from facelab_addon.core.lips.sketch import press_lips, refine_lips, resample_polyline  # noqa: E402
from facelab_addon.testing import synthetic as S  # noqa: E402

TARGET_CONTOUR_MEAN_PX = 1.0
TARGET_REDUCTION_PCT = 50.0
TARGET_SECONDS = 0.25

POSE_OPEN = {"jawOpen": 0.2, "mouthFunnel": 0.3}
# lips touching: light press (midline separation about 0 mm; neutral is ~0.6 mm apart)
POSE_CLOSED = {"mouthPress_L": 0.25, "mouthPress_R": 0.25}

CASES = [
    ("open_gap", POSE_OPEN, "gap", 2.5),
    ("closed_gap", POSE_CLOSED, "gap", 2.5),
    ("closed_cross", POSE_CLOSED, "cross", 2.0),
    ("neutral_gap", {}, "gap", 2.5),
]


def _r(x, nd=3):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def _poly_dist(P, Q):
    """(len(P),) distance from points P (N,2) to the polyline Q (M,2), pixels."""
    return point_segment_distance(P, Q[:-1], Q[1:]).min(axis=1)


def contour_metrics(Y, F, cam, mouth, sketch_u, sketch_l):
    """Silhouette-to-sketch (and sketch-to-silhouette) distances in pixels."""
    try:
        cu, cl = S.lip_contours(Y, F, cam, mouth=mouth)
    except FaceLabError:
        return None
    to_sketch, to_sil = [], []
    for c, sk in ((cu, sketch_u), (cl, sketch_l)):
        inside = (c[:, 0] >= sk[:, 0].min()) & (c[:, 0] <= sk[:, 0].max())
        if inside.sum() >= 2:
            to_sketch.append(_poly_dist(c[inside], sk))
        to_sil.append(_poly_dist(resample_polyline(sk, 1.0), c))
    a = np.concatenate(to_sketch) if to_sketch else np.array([np.inf])
    b = np.concatenate(to_sil)
    return dict(mean=_r(a.mean()), max=_r(a.max()), sketch_to_silhouette_mean=_r(b.mean()),
                sketch_to_silhouette_max=_r(b.max()))


def lip_error(Y, T, mask, mm):
    e = np.linalg.norm(Y[mask] - T[mask], axis=1) / mm
    return dict(rms=_r(np.sqrt((e**2).mean())), max=_r(e.max()))


# ----------------------------------------------------------------------------- Blender
class BlenderLD:
    """Blender's Laplacian Deform modifier on the ICT mesh (headless bpy)."""

    def __init__(self, model):
        os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-bpy-"))
        t = time.perf_counter()
        import bpy  # noqa: F401

        self.bpy = bpy
        self.import_seconds = time.perf_counter() - t
        self.version = bpy.app.version_string
        off = model.poly_offsets
        pv = model.poly_verts
        self.polys = [pv[off[i]:off[i + 1]].tolist() for i in range(len(off) - 1)]
        bpy.ops.wm.read_factory_settings(use_empty=True)

    def run(self, captured, anchors, anchor_targets, evals=5):
        bpy = self.bpy
        n = len(captured)
        me = bpy.data.meshes.new("facelab_bench")
        me.from_pydata(captured.tolist(), [], self.polys)
        me.update()
        obj = bpy.data.objects.new("facelab_bench", me)
        bpy.context.scene.collection.objects.link(obj)
        vg = obj.vertex_groups.new(name="anchors")
        vg.add(np.flatnonzero(anchors).tolist(), 1.0, "REPLACE")
        mod = obj.modifiers.new("LaplacianDeform", "LAPLACIANDEFORM")
        mod.vertex_group = "anchors"
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()

        t = time.perf_counter()
        with bpy.context.temp_override(object=obj, active_object=obj, selected_objects=[obj]):
            bpy.ops.object.laplaciandeform_bind(modifier=mod.name)
        dg.update()
        bind_s = time.perf_counter() - t
        if not mod.is_bind:
            raise RuntimeError("Laplacian Deform bind failed")

        base = captured.astype(np.float64).copy()
        times = []
        result = None
        for k in range(evals + 1):
            co = base.copy()
            # alternate a 1e-9 offset so every evaluation sees changed anchors
            co[anchors] = anchor_targets[anchors] + (1e-9 * (k % 2))
            t = time.perf_counter()
            me.vertices.foreach_set("co", co.ravel())
            me.update()
            dg.update()
            ev = obj.evaluated_get(dg)
            out = np.empty(n * 3)
            ev.data.vertices.foreach_get("co", out)
            times.append(time.perf_counter() - t)
            if k == 0:
                result = out.reshape(n, 3)
        bpy.data.objects.remove(obj)
        bpy.data.meshes.remove(me)
        return dict(bind=bind_s, first_eval=times[0], evals=times[1:], result=result)


# ----------------------------------------------------------------------------- cases
def run_case(model, fixed, name, pose, kind, amount_mm, runs):
    F = model.faces
    mm = 0.1 * model.scale  # scene units per millimetre
    T = model.pose(pose)
    mouth = S.find_mouth(T, F, fixed, units_per_mm=mm)
    cam = S.frontal_camera(T, mouth.center, distance=40.0 * model.scale)
    sk_u, sk_l = S.lip_contours(T, F, cam, mouth=mouth)
    C, err_mask = S.inject_lip_error(T, F, fixed, kind=kind, amount_mm=amount_mm, mouth=mouth)
    lip = S.inner_lip_mask(T, F, fixed, mouth=mouth)

    times, X, info = [], None, None
    for _ in range(runs + 1):
        t = time.perf_counter()
        X, info = refine_lips(C, F, cam, sk_u, sk_l, fixed=fixed, iterations=5, return_info=True)
        times.append(time.perf_counter() - t)
    warm = statistics.median(times[1:])

    # what the solver was asked to reach after pressing crossing stretches
    pu = press_lips(resample_polyline(sk_u), resample_polyline(sk_l))
    pressed = int(pu[2].sum() + pu[3].sum())

    before = contour_metrics(C, F, cam, mouth, sk_u, sk_l)
    after = contour_metrics(X, F, cam, mouth, sk_u, sk_l)
    truth_c = contour_metrics(T, F, cam, mouth, sk_u, sk_l)
    e0, e1 = lip_error(C, T, lip, mm), lip_error(X, T, lip, mm)
    axes = np.stack([mouth.lateral, mouth.up, mouth.forward], axis=1)
    e1["rms_by_axis_lateral_up_forward"] = [_r(v) for v in np.sqrt(((((X - T)[lip] @ axes) / mm) ** 2).mean(axis=0))]
    red = 100.0 * (1.0 - e1["rms"] / e0["rms"]) if e0["rms"] else None
    outside = ~lip
    moved = np.linalg.norm(X - C, axis=1) / mm
    res = dict(
        name=name,
        pose=pose,
        error=dict(kind=kind, amount_mm=amount_mm, vertices=int(err_mask.sum())),
        sketch=dict(upper_points=len(sk_u), lower_points=len(sk_l), pressed_samples=pressed,
                    truth_silhouette_to_sketch_px=truth_c["mean"]),
        contour_px=dict(before=before, after=after,
                        mean_pass=bool(after is not None and after["mean"] <= TARGET_CONTOUR_MEAN_PX)),
        lip_error_mm=dict(region_vertices=int(lip.sum()), before=e0, after=e1, reduction_pct=_r(red, 1),
                          reduction_pass=bool(red is not None and red >= TARGET_REDUCTION_PCT)),
        midline_separation_mm={k: _r(S.lip_separation(Y, mouth) / mm)
                               for k, Y in (("truth", T), ("before", C), ("after", X))},
        outside_lip_region_mm=dict(max_error_after=_r((np.linalg.norm(X - T, axis=1)[outside] / mm).max()),
                                   max_moved=_r(moved[outside].max())),
        solver=dict(free_vertices=int(info["n_free"]),
                    silhouette_px_per_iteration=[_r(v, 2) for v in info["silhouette_px"]],
                    matched_upper=len(info["matched_upper"]), matched_lower=len(info["matched_lower"])),
        seconds={"cold": _r(times[0], 4), "median": _r(warm, 4), "runs": runs, "all": [_r(t, 4) for t in times[1:]],
                 "pass": bool(warm <= TARGET_SECONDS)},
    )

    # what Blender's modifier gets: our hold set plus the matched lip vertices at our result
    anchors = fixed | ~info["region"]
    matched = np.r_[info["matched_upper"], info["matched_lower"]].astype(np.int64)
    anchors[matched] = True
    targets = C.copy()
    targets[matched] = X[matched]
    res["_blender_input"] = dict(C=C, T=T, lip=lip, anchors=anchors, targets=targets, ours=warm, mm=mm)
    return res


def run_blender(blender, res, evals):
    d = res.pop("_blender_input")
    if blender is None:
        return
    try:
        b = blender.run(d["C"], d["anchors"], d["targets"], evals=evals)
    except Exception as e:  # report, don't hide
        res["blender_laplacian_deform"] = dict(error=f"{type(e).__name__}: {e}")
        return
    ev = statistics.median(b["evals"])
    res["blender_laplacian_deform"] = dict(
        anchors=int(d["anchors"].sum()),
        free_vertices=int((~d["anchors"]).sum()),
        bind_seconds=_r(b["bind"], 4),
        first_eval_seconds=_r(b["first_eval"], 4),
        eval_seconds_median=_r(ev, 4),
        ratio_bind_plus_first_eval_to_ours=_r((b["bind"] + b["first_eval"]) / d["ours"], 2),
        ratio_eval_to_ours=_r(ev / d["ours"], 2),
        lip_error_mm_after=lip_error(b["result"], d["T"], d["lip"], d["mm"]),
        note="one Laplacian Deform solve with our final lip correspondences as hard anchors "
        "(no silhouette re-matching); ratios are against our median 5-iteration time",
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer timing runs and cases")
    ap.add_argument("--no-blender", action="store_true", help="skip the Blender Laplacian Deform timing")
    args = ap.parse_args(argv)
    runs = 3 if args.quick else 9
    # Blender and the libraries may print to stdout; keep it for the JSON alone.
    sys.stdout.flush()
    json_fd = os.dup(1)
    os.dup2(2, 1)
    t0 = time.perf_counter()
    model = load_ict()
    load_s = time.perf_counter() - t0
    fixed = ~model.part_vertex_mask("M_Face")
    load_before = os.getloadavg()
    cases = CASES[:3] if args.quick else CASES
    # all of our timings first, so that loading Blender cannot disturb them
    out_cases = [run_case(model, fixed, *c, runs=runs) for c in cases]
    blender, bl_err = None, None
    if not args.no_blender:
        try:
            blender = BlenderLD(model)
        except Exception as e:
            bl_err = f"{type(e).__name__}: {e}"
    for c in out_cases:
        run_blender(blender, c, evals=3 if args.quick else 5)

    def all_of(key, sub):
        return all(c[key][sub] for c in out_cases)

    cam = S.frontal_camera(model.neutral, S.ICT_MOUTH_LOOP, distance=40.0 * model.scale)
    report = dict(
        benchmark="sketch_refine",
        method="core.lips.sketch.refine_lips (Dinev et al. 2018 §5), iterations=5, lambda_pos=0.1 (fixed 1), "
        "lambda_reg=3, lambda_silh=1",
        quick=bool(args.quick),
        mesh=dict(name="ICT-FaceKit generic_neutral_mesh", vertices=len(model.neutral), triangles=len(model.faces),
                  fixed_vertices=int(fixed.sum()), units="cm"),
        camera=dict(width=cam.width, height=cam.height, focal_mm=50, sensor_width_mm=36, distance_cm=40,
                    focal_px=_r(cam.K[0, 0], 1), mm_per_px_at_mouth=_r(40.0 / cam.K[0, 0] * 10, 4)),
        targets=dict(contour_mean_px_max=TARGET_CONTOUR_MEAN_PX, lip_error_reduction_pct_min=TARGET_REDUCTION_PCT,
                     seconds_5_iterations_max=TARGET_SECONDS),
        cases=out_cases,
        summary=dict(
            contour_mean_pass=all_of("contour_px", "mean_pass"),
            lip_error_reduction_pass=all_of("lip_error_mm", "reduction_pass"),
            seconds_pass=all_of("seconds", "pass"),
        ),
        environment=dict(python=platform.python_version(), numpy=np.__version__, cpus=os.cpu_count(),
                         machine=platform.machine(), ict_load_seconds=_r(load_s, 2),
                         blender=(blender.version if blender else None), blender_error=bl_err,
                         bpy_import_seconds=_r(blender.import_seconds, 2) if blender else None,
                         load_average_1min_before_after=[_r(load_before[0], 2), _r(os.getloadavg()[0], 2)],
                         blas_threads_env={k: os.environ.get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                                          "MKL_NUM_THREADS")}),
    )
    report["summary"]["all_pass"] = all(report["summary"].values())
    sys.stdout.flush()
    with os.fdopen(json_fd, "w") as fh:
        json.dump(report, fh, indent=1)
        fh.write("\n")


if __name__ == "__main__":
    main()
