"""Benchmark: the artist route on cases ``any_face.py`` does not show (other actors, cameras, sketch noise, an
imported head).

The route is ``benchmarks/any_face.py``'s ``run_route`` (imported, not copied): Auto Regions (automatic), a
sketch of the truth's inner-lip silhouettes and Refine Lips on 10 training frames, Propagate over 40 frames,
through the operators, on a scene of ``testing.route.build_route_scene`` (Z-up, under a head + jaw armature,
unposed, the ``wide`` capture error), metres, one view (the main camera). Cases (``CASES``):

* ``reference``: any_face.py's metres / unposed / one-view run;
* ``identity s0..s2``: other actors: ICT's neutral plus ``sum_i w_i (identity_i - neutral)`` over its 10 identity
  targets, ``w ~ N(0, 1)`` seeded 0, 1, 2; every expression keeps its ICT offset (ICT's linear model:
  identity and expression offsets add);
* ``lens 35 mm`` / ``lens 85 mm``: every camera's focal length, the distance kept at 40 cm (the framing is not
  kept: the mouth is 0.7x / 1.7x as many pixels wide as with the 50 mm lens);
* ``yaw 15°``: the camera 15° to the face's side (still 40 cm from the mouth, looking at it);
* ``roll 10°``: the camera rolled 10° about its viewing axis;
* ``distance 25 cm`` / ``60 cm``: the camera nearer / farther, 50 mm lens (the mouth 1.6x / 0.67x as wide in pixels);
* ``noise 1.5 px s0`` / ``s1``: each sketched stroke with a hand's 1.5 px RMS smooth jitter
  (``testing.route.jitter_stroke``), seeds 0 and 1;
* ``OBJ import``: the face written to an OBJ as it is (Y up, centimetres) and read back with
  ``bpy.ops.wm.obj_import`` and Blender's default axis settings into a metre scene: the object is rotated 90°
  about X (its local data stays Y up) and, a centimetre file read as metres, 100 times too big (a 20 m head);
  shape keys, capture error, armature, cameras (40 "cm" of that face away) and truth follow it;
* ``OBJ import x0.01``: the same with the importer's scale 0.01 (what an artist sets for a centimetre file).

Per case (JSON): Refine's 3D inner-lip RMS cut on the training frames (%), the contour error in pixels before and
after, Propagate's held-out inner-lip RMS as % of the capture's, the largest movement outside ``FL_mouth`` and
``FL_lips`` (mm, all frames; on the imported giant, world millimetres), seconds, and any exception.

Faces: ICT-FaceKit and ``testing.remeshed.remeshed_ict`` (ICT decimated to quads; the identity offsets transferred
barycentrically), as in any_face.py.

Usage: ``PYTHONPATH=. python benchmarks/route_sweep.py [--faces ict,remeshed] [--cases identity,lens]
[--png docs/images/route_sweep.png] > benchmarks/results/route_sweep.json``. About 5 minutes (both faces, 2 shared
cores). Blender's output goes to stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import any_face  # noqa: E402  (the route: run_route)
from _harness import blender_session, json_stdout, log, since  # noqa: E402

#: ``(name, group, options)``; options: ``identity`` (seed of the identity mix), ``scene`` (keyword arguments of
#: ``build_route_scene``), ``noise_px`` and ``seed`` (the sketch jitter).
CASES = [
    ("reference", "reference", {}),
    *[(f"identity s{s}", "actor", dict(identity=s)) for s in range(3)],
    ("lens 35 mm", "camera", dict(scene=dict(lens_mm=35.0))),
    ("lens 85 mm", "camera", dict(scene=dict(lens_mm=85.0))),
    ("yaw 15°", "camera", dict(scene=dict(camera_yaw=15.0))),
    ("roll 10°", "camera", dict(scene=dict(camera_roll=10.0))),
    ("distance 25 cm", "camera", dict(scene=dict(camera_cm=25.0))),
    ("distance 60 cm", "camera", dict(scene=dict(camera_cm=60.0))),
    *[(f"noise 1.5 px s{s}", "noise", dict(noise_px=1.5, seed=s)) for s in range(2)],
    ("OBJ import", "import", dict(scene=dict(obj_import=True))),
    ("OBJ import x0.01", "import", dict(scene=dict(obj_import=True, import_scale=0.01))),
]


def identity_face(face, ict, seed):
    """``face`` as another actor: ICT's identity offsets (``w ~ N(0, 1)``, seeded) added to its neutral and to every
    expression target (a :class:`RemeshedFace` gets them transferred). Returns ``(face, weights)``."""
    w = np.random.default_rng(seed).normal(size=len(ict.identities))
    off = ict.pose(identity=dict(zip(ict.identities, w))) - ict.neutral
    if hasattr(face, "transfer"):
        off = face.transfer(off)
    new = dataclasses.replace(face, neutral=face.neutral + off,
                              expressions={n: X + off for n, X in face.expressions.items()})
    return new, [round(float(x), 3) for x in w]


def run_case(face, ict, name, group, opt, tmp, log):
    row = dict(case=name, group=group)
    f = face
    if "identity" in opt:
        f, row["identity_weights"] = identity_face(face, ict, opt["identity"])
    if opt.get("scene"):
        row["scene"] = opt["scene"]
    if opt.get("noise_px"):
        row.update(noise_px=opt["noise_px"], seed=opt.get("seed", 0))
    t0 = time.perf_counter()
    try:
        r, _ = any_face.run_route(f, "m", False, tmp, log, (), noise_px=opt.get("noise_px", 0.0),
                                  seed=opt.get("seed", 0), scene_kw=opt.get("scene"), bake=False)
    except Exception as e:  # the sweep reports what breaks
        row.update(exception=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=4)[-1500:],
                   seconds=round(time.perf_counter() - t0, 2))
        log(f"{name}: EXCEPTION {row['exception']}")
        return row
    row["seconds"] = round(time.perf_counter() - t0, 2)
    if "error" in r:
        row["exception"] = r["error"]
    rv = r.get("refine_one_view")
    if rv:
        row.update(refine_cut_pct=rv["rms_cut_pct"], contour_px_before=rv["contour_px_before"],
                   contour_px_after=rv["contour_px_after"], inner_lip_rms_mm_before=rv["inner_lip_rms_mm_before"],
                   depth_rms_mm_before=rv["depth_rms_mm_before"], depth_rms_mm_after=rv["depth_rms_mm_after"],
                   best_possible_cut_pct=rv["best_possible_cut_pct"])
    ph = r.get("propagate_held_out")
    if ph:
        row["held_out_pct_of_capture"] = ph["after_pct_of_capture"]
        row["propagate_reproduces_refine_pct"] = r.get("propagate_reproduces_refine_pct")
    mo = r.get("max_move_outside_mouth_area_mm")
    if mo:
        row["max_move_outside_mouth_area_mm"] = max(mo["held_out_frames"], mo["training_frames"])
    if r.get("auto_regions"):
        row["auto_regions"] = r["auto_regions"]
    log(f"{name}: cut {row.get('refine_cut_pct')} %, px {row.get('contour_px_before')} -> "
        f"{row.get('contour_px_after')}, held-out {row.get('held_out_pct_of_capture')} %, outside "
        f"{row.get('max_move_outside_mouth_area_mm')} mm, {row['seconds']} s")
    return row


def picture(path, faces):
    """One bar chart per face: Refine's cut and Propagate's held-out share per case, with the 50 % targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(faces), 1, figsize=(13, 4.6 * len(faces)), squeeze=False)
    for ax, (label, rows) in zip(axes[:, 0], faces.items()):
        _bars(ax, rows, f"{label}: the artist route (10 sketched frames, one view, metres) on unseen cases")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def _bars(ax, rows, title):
    x = np.arange(len(rows))
    cut = [r.get("refine_cut_pct", np.nan) for r in rows]
    held = [r.get("held_out_pct_of_capture", np.nan) for r in rows]
    ax.bar(x - 0.2, cut, 0.4, color="tab:blue", label="Refine: 3D inner-lip RMS cut, % (target >= 50)")
    ax.bar(x + 0.2, held, 0.4, color="tab:orange", label="Propagate: held-out RMS, % of capture (target <= 50)")
    for xi, c, h, r in zip(x, cut, held, rows):
        if "exception" in r or not np.isfinite(c):
            ax.text(xi, 5, "failed", rotation=90, ha="center", color="red", fontsize=8)
            continue
        ax.text(xi - 0.2, max(c, 0) + 1, f"{c:.0f}", ha="center", fontsize=7)
        ax.text(xi + 0.2, max(h, 0) + 1, f"{h:.0f}", ha="center", fontsize=7)
    ax.axhline(50, color="k", ls=":", lw=1, label="the 50 % targets")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(x)
    ax.set_xticklabels([r["case"] for r in rows], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("%")
    top = max([v for v in cut + held if np.isfinite(v)] + [60])
    ax.set_ylim(min([v for v in cut if np.isfinite(v)] + [0]) - 5, top + 22)
    ax.legend(fontsize=8, loc="upper left", ncol=3)
    ax.set_title(title, fontsize=10)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", default="ict,remeshed", help="comma-separated: ict, remeshed")
    ap.add_argument("--cases", default=None, help="only cases whose name contains one of these (comma-separated)")
    ap.add_argument("--png", default=None, help="write the bar chart here (e.g. docs/images/route_sweep.png)")
    args = ap.parse_args(argv)
    out_json = json_stdout()  # Blender prints to stdout; keep it for the JSON alone
    tmp = tempfile.mkdtemp(prefix="facelab-sweep-")
    t_all = time.perf_counter()
    with blender_session() as bpy:
        from facelab_addon.core.capture.ict import load_ict

        ict = load_ict()
        want = args.cases.split(",") if args.cases else None
        out = dict(bpy_version=bpy.app.version_string, units="m", armature_posed=False, views=1,
                   training_frames=any_face.TRAIN, frames=len(any_face.FRAMES), faces={})
        for key in args.faces.split(","):
            if key == "ict":
                face, label = ict, "ICT-FaceKit"
            else:
                from facelab_addon.testing.remeshed import remeshed_ict

                face, label = remeshed_ict(ict), "ICT remeshed (quads)"
            rows = [run_case(face, ict, n, g, o, tmp, log) for n, g, o in CASES
                    if want is None or n == "reference" or any(w in n for w in want)]
            ref = next(r for r in rows if r["case"] == "reference")
            for r in rows:  # against the reference case
                if r is not ref and "refine_cut_pct" in r and "refine_cut_pct" in ref:
                    r["cut_minus_reference"] = round(r["refine_cut_pct"] - ref["refine_cut_pct"], 1)
                if r is not ref and "held_out_pct_of_capture" in r and "held_out_pct_of_capture" in ref:
                    r["held_out_minus_reference"] = round(r["held_out_pct_of_capture"]
                                                          - ref["held_out_pct_of_capture"], 1)
            out["faces"][label] = rows
        if args.png:
            picture(args.png, out["faces"])
            out["picture"] = args.png
        out["total_s"] = since(t_all, 1)
        out_json.emit(out, ensure_ascii=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
