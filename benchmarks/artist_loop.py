"""Benchmark: the artist's loop (sketch -> Refine Lips -> Propagate -> refine the suggested frames -> Propagate
again) on three faces, through the pipeline functions the operators call (``facelab_addon.testing.loop``).

Faces: the shipped sample (48 frames; the README's first frames 11, 37, 44), ICT-FaceKit and the remeshed
quad face of the route benchmarks (``testing.route`` scenes, metres, under an armature at rest, one frontal
view, 40 frames; first frames 11, 20, 30). Sketches are the truth's visible inner-lip silhouettes (a frame
whose truth cannot be drawn is skipped, as an artist would). Each loop starts from 3 sketched frames and runs
rounds of "sketch and Refine the next 3 frames, Propagate" up to 12 training frames (the ICT faces: 9, to keep
the run to a few minutes).

Compared, each as a whole loop:

* mechanisms, with FaceLab's suggestions: the paper's maps (``ridge`` none), damping (Damp Uncertain
  Frames), leave-one-out ridge (``PropagateSettings.ridge = "loo"``), and both;
* with the shipped settings, how the next frames are chosen: FaceLab's suggestions, the frames Propagate
  expects worse than their capture first, the most extrapolated frames, frames evenly spaced in time;
* and for each loop the same final training frames refined before one Propagate (the one-pass result).

Per round: held-out inner-lip RMS (mm, over the frames the loop never refined) and its worst frame, the held-out
frames worse than their capture by more than 0.01 mm (and those Propagate's report did not name), and how far
each training frame has moved from what Refine gave it (largest vertex distance, mm).

Usage: ``PYTHONPATH=. python benchmarks/artist_loop.py [--faces sample,ict,remeshed]
[--png docs/images/artist_loop.png]``
Prints one JSON object (save as ``benchmarks/results/artist_loop.json``); progress on stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _harness import blender_session, json_stdout, log, since  # noqa: E402

MECHANISMS = {"paper": dict(ridge="none", damping=False), "damping": dict(ridge="none", damping=True),
              "loo ridge": dict(ridge="loo", damping=False), "loo ridge + damping": dict(ridge="loo", damping=True)}
STRATEGIES = ["facelab", "worse", "extrapolated", "even"]
TOTAL = {"sample": 12, "ict": 9, "remeshed": 9}
ROUTE_FIRST = [11, 20, 30]


def _face(name, ict_cache):
    from facelab_addon.testing.loop import route_face, sample_face

    if name == "sample":
        return sample_face()
    if "ict" not in ict_cache:
        from facelab_addon.core.capture.ict import load_ict

        ict_cache["ict"] = load_ict()
    if name == "ict":
        return route_face(ict_cache["ict"], "ICT-FaceKit", first=ROUTE_FIRST)
    if "remeshed" not in ict_cache:
        from facelab_addon.testing.remeshed import remeshed_ict

        ict_cache["remeshed"] = remeshed_ict(ict_cache["ict"])
    return route_face(ict_cache["remeshed"], "ICT remeshed (quads)", first=ROUTE_FIRST)


def _clean(rounds):
    keep = ("training", "held_out_rms_mm", "worst_frame", "worst_mm", "worse_than_capture", "worse_not_named",
            "expected_worse", "max_training_drift_mm")
    out = []
    for r in rounds:
        d = {k: r[k] for k in keep}
        for k in ("held_out_rms_mm", "worst_mm"):
            d[k] = round(d[k], 4)
        d["max_training_drift_mm"] = round(d["max_training_drift_mm"], 5)
        out.append(d)
    return out


def run(name, mechanism, strategy, ict_cache):
    """One loop and its one-pass twin on a fresh scene each."""
    import bpy

    from facelab_addon.pipeline.propagate import PropagateSettings
    from facelab_addon.testing.loop import run_loop

    settings = PropagateSettings(suggestions=6, **MECHANISMS[mechanism])
    t0 = time.perf_counter()
    face = _face(name, ict_cache)
    loop = run_loop(face, settings=settings, strategy=strategy, total=TOTAL[name])
    t_loop = since(t0, 1)
    frames = sorted(int(f) for f in loop["rounds"][-1]["training"])
    face2 = _face(name, ict_cache)
    one = run_loop(face2, settings=settings, plan=[frames])
    # the one-pass result on the loop's held-out frames (the same frames: both refine the same set)
    held = np.setdiff1d(face.frames, frames)
    e0 = face.errors(face.capture)[np.searchsorted(face.frames, held)]
    rounds = _clean(loop["rounds"])
    res = dict(face=name, mechanism=mechanism, strategy=strategy, order=loop["order"], rounds=rounds,
               capture_held_out_rms_mm=round(float(np.sqrt(np.mean(e0 ** 2))), 4),
               one_pass=_clean(one["rounds"])[-1], seconds=t_loop)
    hs = [r["held_out_rms_mm"] for r in rounds]
    res["monotone"] = bool(all(b <= a + 1e-4 for a, b in zip(hs, hs[1:])))
    res["loop_vs_one_pass_pct"] = round(100 * (hs[-1] / res["one_pass"]["held_out_rms_mm"] - 1), 1)
    for s in bpy.data.scenes[1:]:  # keep memory flat between loops
        bpy.data.scenes.remove(s)
    log(f"{name:9s} {mechanism:20s} {strategy:12s} held-out {hs} one-pass {res['one_pass']['held_out_rms_mm']} "
        f"worse {[len(r['worse_than_capture']) for r in rounds]} drift "
        f"{max(r['max_training_drift_mm'] for r in rounds):.5f} ({t_loop} s)")
    return res


def plot(out, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    faces = list(dict.fromkeys(r["face"] for r in out["runs"]))
    fig, axes = plt.subplots(1, len(faces), figsize=(5 * len(faces), 4), squeeze=False)
    for ax, name in zip(axes[0], faces):
        runs = [r for r in out["runs"] if r["face"] == name]
        for r in runs:
            style = "-" if r["strategy"] == "facelab" else "--"
            ax.plot([len(x["training"]) for x in r["rounds"]], [x["held_out_rms_mm"] for x in r["rounds"]],
                    style, marker="o", label=f"{r['mechanism']} / {r['strategy']}")
        ax.axhline(runs[0]["capture_held_out_rms_mm"], color="k", lw=0.8, ls=":", label="capture")
        ax.set_title(name)
        ax.set_xlabel("training frames after the round")
        ax.set_ylabel("held-out inner-lip RMS (mm)")
        ax.set_ylim(bottom=0)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", default="sample,ict,remeshed")
    ap.add_argument("--png", default=str(ROOT / "docs" / "images" / "artist_loop.png"))
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "artist_loop.json"))
    args = ap.parse_args(argv)
    out_json = json_stdout()
    t_all = time.perf_counter()
    with blender_session() as bpy:
        from facelab_addon.pipeline.propagate import PropagateSettings

        shipped = next(m for m, kw in MECHANISMS.items()
                       if kw == dict(ridge=PropagateSettings().ridge, damping=PropagateSettings().damping))
        out = dict(bpy_version=bpy.app.version_string, shipped=shipped, runs=[])
        cache = {}
        for name in args.faces.split(","):
            for m in MECHANISMS:
                out["runs"].append(run(name, m, "facelab", cache))
            for s in STRATEGIES[1:]:
                out["runs"].append(run(name, shipped, s, cache))
        out["total_s"] = since(t_all, 1)
        if args.png:
            plot(out, args.png)
        import json

        Path(args.out).write_text(json.dumps(out, indent=1))
        out_json.emit(out)


if __name__ == "__main__":
    main()
