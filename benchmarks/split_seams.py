"""Benchmark: the Dinev route on a face split along its seams (a glTF import) against the same face welded.

Blender's glTF importer (Merge Vertices off) and many engine exports split the vertices along UV seams: ICT-FaceKit
split by its own UVs has 28,911 vertices for 26,719 (M_Face in 9 pieces); the remeshed face (no UVs) gets islands
of its mouth area cut out (``testing.split_seams.mouth_boxes``: 11,150 -> 12,049). FaceLab welds the seams back
(``core.geometry.weld``, ``blender.mesh.face_topology``). Per face, both runs of
``testing.split_seams.run_route`` (metres, head + jaw armature, unposed, one view; Auto Regions, Refine Lips on 4
sketched frames, Propagate over 40 frames), the split run with the welded run's capture error and sketch pixels:

* the inner-lip RMS error (mm, ``testing.route.lip_errors``; on the split face over one copy of each vertex, the
  welded face's vertex set) of the capture, after Refine (training frames) and after Propagate (held-out frames),
  welded and split;
* the largest difference between the split result and the welded one at the vertex it copies (mouth widths), and
  the largest gap between twins on the evaluated mesh (mouth widths; and mm after Propagate), after Refine and
  after Propagate;
* the same for ``split_unwelded``: the split face with the welding switched off (FaceLab before it);
* the seconds of ``face_topology`` on the split face (rest + every shape key) and of the whole route, both runs.

Usage: ``PYTHONPATH=. python benchmarks/split_seams.py [--faces ict,remeshed] > benchmarks/results/split_seams.json``.
About a minute. Blender's output goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FRAMES = np.arange(1, 41)
TRAIN = [8, 16, 24, 32]


def measure(face, name):
    from facelab_addon.blender.mesh import face_topology
    from facelab_addon.testing.split_seams import run_route, split_seams

    welded = run_route(face, frames=FRAMES, train=TRAIN)
    split = split_seams(face)
    cut = run_route(split, frames=FRAMES, train=TRAIN, error=welded["error"][split.source],
                    strokes=welded["strokes"])
    t0 = time.perf_counter()
    topo = face_topology(cut["rs"].obj)  # with FaceLab's keys, which keep every seam closed
    weld_s = time.perf_counter() - t0
    raw = _unwelded(lambda: run_route(split, frames=FRAMES, train=TRAIN, error=welded["error"][split.source],
                                      strokes=welded["strokes"]))
    held = np.setdiff1d(FRAMES, TRAIN)
    hi = np.searchsorted(FRAMES, held)
    ti = np.searchsorted(FRAMES, TRAIN)
    row = dict(face=name, vertices=len(face.neutral), split_vertices=len(split.neutral),
               welded_duplicates=topo.n_duplicates, face_topology_seconds=round(weld_s, 3))
    w = welded["width"]
    d = split.duplicates()
    first = np.r_[True, np.diff(split.source) != 0]  # one copy of every vertex: the welded face's vertex set
    for label, r, once in (("welded", welded, np.ones(len(face.neutral), bool)), ("split", cut, first),
                           ("split_unwelded", raw, first)):
        rs = r["rs"]

        def rms(X, i):  # testing.route.lip_errors on the truth kept by run_route (its scene is gone by now)
            e = np.linalg.norm(X - r["truth"][i], axis=2)[:, rs.inner_lips & once]
            return round(float(np.sqrt(np.mean(e * e, axis=1)).mean() * rs.mm_per_unit), 4)

        row[label] = dict(lip_rms_mm_captured_training=rms(r["captured"][ti], ti),
                          lip_rms_mm_refined_training=rms(r["refined"], ti),
                          lip_rms_mm_captured_held_out=rms(r["captured"][hi], hi),
                          lip_rms_mm_propagated_held_out=rms(r["propagated"][hi], hi),
                          route_seconds=round(r["seconds"], 2))
    src = split.source
    for label, r in (("split", cut), ("split_unwelded", raw)):
        row[label]["max_difference_mouth_widths"] = dict(
            refine=float(np.abs(r["refined"] - welded["refined"][:, src]).max() / w),
            propagate=float(np.abs(r["propagated"] - welded["propagated"][:, src]).max() / w))
        row[label]["max_twin_gap_mouth_widths"] = dict(
            refine=float(np.linalg.norm(r["refined"][:, d[:, 0]] - r["refined"][:, d[:, 1]], axis=2).max() / w),
            propagate=float(np.linalg.norm(r["propagated"][:, d[:, 0]] - r["propagated"][:, d[:, 1]],
                                           axis=2).max() / w))
        row[label]["max_twin_gap_mm"] = round(row[label]["max_twin_gap_mouth_widths"]["propagate"] * w
                                              * r["rs"].mm_per_unit, 4)
    return row


def _unwelded(run):
    """``run()`` with ``blender.mesh.face_topology`` welding nothing: FaceLab before the seams were welded."""
    from facelab_addon.blender import mesh
    from facelab_addon.core.geometry.weld import Weld

    keep = mesh.weld
    mesh.weld = lambda F, V, poses=(), **kw: Weld(representative=np.arange(len(V)), faces=np.asarray(F))
    try:
        return run()
    finally:
        mesh.weld = keep


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", default="ict,remeshed")
    args = ap.parse_args(argv)
    stdout = os.dup(1)
    os.dup2(2, 1)  # Blender's prints to stderr; the JSON alone on stdout
    import bpy

    import facelab_addon
    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.testing.remeshed import remeshed_ict

    bpy.ops.wm.read_factory_settings(use_empty=True)
    facelab_addon.register()
    ict = load_ict()
    rows = []
    for name in args.faces.split(","):
        face = ict if name == "ict" else remeshed_ict(ict)
        rows.append(measure(face, name))
    out = dict(benchmark="split_seams", frames=[int(FRAMES[0]), int(FRAMES[-1])], training_frames=TRAIN,
               blender=bpy.app.version_string, faces=rows)
    os.write(stdout, (json.dumps(out, indent=1) + "\n").encode())


if __name__ == "__main__":
    main()
