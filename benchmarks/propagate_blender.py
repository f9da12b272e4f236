"""Benchmark: the Propagate operator end to end in Blender (Dinev et al. 2018, §4) on ICT-FaceKit.

Scene (as ``tests/blender/test_propagate_operator.py``, at scale): the
ICT-FaceKit face in metres (26,719 vertices) with eight mouth expressions as
shape keys (jawOpen, mouthClose, mouthFunnel, mouthPucker, mouthSmile_L/R,
mouthPress_L/R), keyed with ``key_values_bulk`` on N frames of smooth,
speech-like weights (``testing.weights.speech_weights``, as ``benchmarks/propagate.py``). The
capture error is one shape key, ``CaptureError`` (``testing.synthetic.
lip_error_weights``: the inner lips pulled apart, 1 mm per lip at value 1,
faded to zero at the border of the ``FL_lips`` group so that the trusted
mouth region and the Dirichlet border are error-free), keyed with a
non-linear function of the pose: lips fail to close when the jaw is nearly
shut, and cross (negative values; the key's slider minimum is lowered) when
pressed. The truth is the capture minus that key. Auto Regions writes the
regions; 10 training frames are chosen by ``core.lips.suggest.suggest_frames``
on the captured sequence (no regressor: extreme poses first); each is
"sculpted" (``add_corrective_key`` cancelling the error + ``key_spike``) and
marked (``bpy.ops.facelab.mark_training_frame``). Then
``bpy.ops.facelab.propagate`` runs once, and once more after the frame it
suggests first is corrected too (incremental): sculpted from what the viewport shows (the capture with
Propagate's correction, which Mark Training Frame keeps) to the truth, checked to train as the truth.

Reported: .blend sizes before/after (uncompressed and zstd), FL_Prop_* keys
and keyframes written, operator wall time split into its parts (the parts of
``pipeline.propagate.propagate`` are wrapped with timers; "self" times add up to
the wall time), peak RSS of each part and of the process, held-out inner-lip
error against the truth on the evaluated mesh, the deviation of the evaluated
mesh from ``LipRegressor.predict``.

Usage: ``PYTHONPATH=. python benchmarks/propagate_blender.py [--frames 1000] [--quick]``.
Prints one JSON object on stdout; Blender's own output goes to stderr.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _harness import blender_session, json_stdout, since, user_resources  # noqa: E402

SCALE = 0.01  # ICT centimetres -> metres
M_TO_MM = 1000.0
EXPR = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R", "mouthPress_L",
        "mouthPress_R"]
N_TRAIN = 10
ERR_CM = 0.1  # CaptureError amplitude at weight 1 (per lip), cm
TARGET_GROWTH_MB = 30.0
TARGET_CORE_RSS_MB = 1000.0
COMPRESS_TOL_MM = 0.01


# --------------------------------------------------------------------------- memory
def _status(field):
    for ln in Path("/proc/self/status").read_text().splitlines():
        if ln.startswith(field + ":"):
            return int(ln.split()[1]) * 1024 / 1e6  # kB (KiB) -> MB
    return float("nan")


class Mem:
    """Peak-RSS bookkeeping with per-phase resets (Linux ``clear_refs``), keeping the process maximum."""

    def __init__(self):
        self.process_peak = _status("VmHWM")
        self.window = 0.0  # peak since start_window(), across resets
        self.can_reset = True

    def start_window(self):
        self.window = _status("VmRSS")

    def window_peak(self):
        return max(self.window, self.peak())

    def reset(self):
        h = _status("VmHWM")
        self.process_peak = max(self.process_peak, h)
        self.window = max(self.window, h)
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            self.can_reset = False

    def peak(self):
        p = _status("VmHWM")
        self.process_peak = max(self.process_peak, p)
        return p

    @staticmethod
    def rss():
        return _status("VmRSS")


MEM = Mem()


# --------------------------------------------------------------------------- timers
class Timers:
    """Inclusive/self wall time and peak RSS of wrapped functions (nested calls are attributed to children)."""

    def __init__(self):
        self.incl = defaultdict(float)
        self.self_ = defaultdict(float)
        self.calls = defaultdict(int)
        self.peak = defaultdict(float)
        self.stack = []
        self.patches = []

    def wrap(self, label, fn, *, inside_passthrough=()):
        timers = self

        def wrapped(*a, **k):
            if timers.stack and timers.stack[-1][0] in inside_passthrough:
                return fn(*a, **k)
            rss0 = MEM.peak()
            MEM.reset()
            t0 = time.perf_counter()
            timers.stack.append([label, 0.0])
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - t0
                _, child = timers.stack.pop()
                timers.incl[label] += dt
                timers.self_[label] += dt - child
                timers.calls[label] += 1
                p = MEM.peak()
                timers.peak[label] = max(timers.peak[label], p)
                if timers.stack:
                    timers.stack[-1][1] += dt
                # the parent's peak so far must survive this reset
                for lab, _ in timers.stack:
                    timers.peak[lab] = max(timers.peak[lab], p, rss0)

        return wrapped

    def patch(self, owner, name, label, **kw):
        orig = getattr(owner, name)
        setattr(owner, name, self.wrap(label, orig, **kw))
        self.patches.append((owner, name, orig))

    def restore(self):
        for owner, name, orig in reversed(self.patches):
            setattr(owner, name, orig)
        self.patches.clear()

    def report(self, wall):
        out = {}
        for lab in sorted(self.incl, key=lambda x: -self.self_[x]):
            out[lab] = dict(self_s=round(self.self_[lab], 3), incl_s=round(self.incl[lab], 3), calls=self.calls[lab],
                            peak_rss_mb=round(self.peak[lab], 1))
        out["other (operator, depsgraph, numpy glue)"] = dict(self_s=round(wall - sum(self.self_.values()), 3))
        return out


def instrument(timers):
    """Wrap the parts of ``pipeline.propagate.propagate`` (module attributes it looks up at call time)."""
    from facelab_addon.blender import cache_integrate, caches, capture_stream
    from facelab_addon.core.lips import suggest
    from facelab_addon.core.lips.regressor import LipRegressor, reduced
    from facelab_addon.pipeline import correctives as corr
    from facelab_addon.pipeline import propagate as op

    timers.patch(capture_stream.CaptureReader, "read", "read captured chunk (mouth + lip vertices)")
    timers.patch(caches, "evaluate_frames", "read_corrected (training frames)",
                 inside_passthrough=("read captured chunk (mouth + lip vertices)",))
    timers.patch(op, "face_topology", "setup: face_topology (triangles, weld)")
    timers.patch(op, "region_faces", "setup: region_faces")
    timers.patch(op, "rest_vertices", "setup: rest_vertices")
    timers.patch(LipRegressor, "__init__", "regressor: LipRegressor.__init__ (Poisson factor, patches)")
    timers.patch(LipRegressor, "fit", "regressor: fit")
    timers.patch(LipRegressor, "correct_chunk", "correct_chunk (predict + extrapolation, per chunk)")
    timers.patch(cache_integrate.IntegrateMap, "to_key", "map onto the cache (Integrate)")
    timers.patch(reduced.StreamingBasis, "add", "compress: StreamingBasis.add")
    timers.patch(reduced.StreamingBasis, "finish", "compress: StreamingBasis.finish (SVD, 0.01 mm)")
    timers.patch(suggest.SuggestScreen, "select", "suggest: select (re-read candidates)")
    timers.patch(op, "_suggest", "suggest (3 markers, all passes)")
    timers.patch(corr, "remove_keys", "write: remove old FL_Prop keys")  # the keys go through pipeline.correctives
    timers.patch(corr, "add_keys_from_deltas", "write: add FL_Prop keys")
    timers.patch(corr, "key_values_bulk", "write: key FL_Prop values")
    timers.patch(op, "key_property_bulk", "write: key FL_extrapolation")


def capture_error_weight(W):
    """(T,) CaptureError key value: + gap when the lips should be closed, - crossing when pressed (non-linear)."""
    jaw, close = W[:, 0], W[:, 1]
    press = 0.5 * (W[:, 6] + W[:, 7])
    closed = np.clip(1.0 - jaw / 0.25, 0.0, 1.0) ** 2 + 2.0 * close * np.clip(jaw, 0, 1)
    return np.tanh(1.5 * closed) - 1.4 * np.tanh((press / 0.35) ** 2)


def build(bpy, ict, frames, W):
    """The animated capture: keyed expressions (``build_ict_face_scene``), Auto Regions, then the CaptureError
    key inside the lip region."""
    from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
    from facelab_addon.blender.shapekeys import add_corrective_key, key_values_bulk
    from facelab_addon.core.geometry.geodesic import geodesic_distance
    from facelab_addon.core.lips import regions
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as syn
    from facelab_addon.testing.scenes import build_ict_face_scene

    fs = build_ict_face_scene(ict, EXPR, weights=W, frames=frames, scale=SCALE)
    scene, obj = fs.scene, fs.obj
    t0 = time.perf_counter()
    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
    t_regions = time.perf_counter() - t0

    # error shape: synthetic.lip_error_weights (1 mm per lip at weight 1), faded to zero at the FL_lips border.
    # Unfaded it reaches 6 mm from the lip tips, i.e. 1 mm on the lip border (held at the capture by the
    # Poisson solve) and on FL_mouth (the trusted input): no regression could remove that part.
    V = ict.neutral * SCALE
    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(V, ict.faces, fixed, loop=syn.ICT_MOUTH_LOOP)
    w, side = syn.lip_error_weights(V, ict.faces, fixed, mouth=mouth)
    tris = mesh_triangles(obj.data)
    lips = vertex_group_mask(obj, "FL_lips")
    border = regions.region_border(tris, regions.faces_in_region(tris, lips), len(V))
    interior = lips.copy()
    interior[border] = False
    width = regions.DEFAULT_LIP_WIDTH * mouth.width
    db = geodesic_distance(V, tris, border, limit=width)
    u = np.clip(np.where(np.isfinite(db), db, width) / (0.35 * width), 0.0, 1.0)
    fade = u * u * (3 - 2 * u) * interior
    err = np.zeros_like(V)
    err[:, 1] = side * w * fade * ERR_CM * SCALE
    leak_unfaded = float(np.max(np.abs(w[~interior]))) * ERR_CM * 10  # mm per unit key value
    kb = add_corrective_key(obj, "CaptureError", err)
    kb.slider_min = -2.0  # negative values (lips crossing) would otherwise be clamped to 0 by Blender
    cap_w = capture_error_weight(W)
    assert cap_w.min() >= kb.slider_min and cap_w.max() <= kb.slider_max
    key_values_bulk(obj, ["CaptureError"], frames, cap_w[:, None])
    info = dict(auto_regions_s=round(t_regions, 2), error_vertices=int((np.abs(err).max(axis=1) > 0).sum()),
                lip_vertices=int(lips.sum()), lip_border_vertices=int(len(border)),
                unfaded_error_outside_lip_interior_mm=round(leak_unfaded, 3))
    return scene, obj, err, cap_w, info


def blend_sizes(bpy, directory, tag):
    out = {}
    for comp in (False, True):
        p = Path(directory) / f"{tag}_{'zstd' if comp else 'raw'}.blend"
        t0 = time.perf_counter()
        bpy.ops.wm.save_as_mainfile(filepath=str(p), compress=comp, copy=True)
        out["zstd_mb" if comp else "raw_mb"] = p.stat().st_size / 1e6
        out["zstd_save_s" if comp else "raw_save_s"] = time.perf_counter() - t0
        p.unlink()
    return out


def count_prop(obj):
    from facelab_addon.blender.caches import _anim_fcurves

    key = obj.data.shape_keys
    names = [kb.name for kb in key.key_blocks if kb.name.startswith("FL_Prop_")]
    kf_keys = sum(len(fc.keyframe_points) for fc in _anim_fcurves(key) if fc.data_path.startswith('key_blocks["FL_Prop_'))
    kf_extra = sum(len(fc.keyframe_points) for fc in _anim_fcurves(obj) if "FL_extrapolation" in fc.data_path)
    return names, kf_keys, kf_extra


# --------------------------------------------------------------------------- operator runs
def run_operator(bpy, label, **kw):
    timers = Timers()
    instrument(timers)
    rss0 = MEM.rss()
    MEM.reset()
    MEM.start_window()
    t0 = time.perf_counter()
    try:
        res = bpy.ops.facelab.propagate(**kw)
    finally:
        wall = time.perf_counter() - t0
        timers.restore()
    peak = MEM.window_peak()
    return dict(result=sorted(res), wall_s=round(wall, 3), rss_before_mb=round(rss0, 1), peak_rss_mb=round(peak, 1),
                peak_rss_growth_mb=round(peak - rss0, 1), split=timers.report(wall))


# --------------------------------------------------------------------------- accuracy
def accuracy(bpy, obj, frames, train, err, cap_w, chunk=100):
    """Held-out inner-lip error vs the truth on the evaluated mesh, and its deviation from LipRegressor.predict."""
    from facelab_addon.blender import caches
    from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
    from facelab_addon.blender.shapekeys import rest_vertices, shape_key_sequence
    from facelab_addon.core.lips.regressor import LipRegressor
    from facelab_addon.core.lips.regions import faces_in_region

    tris = mesh_triangles(obj.data)
    mouth, lips = vertex_group_mask(obj, "FL_mouth"), vertex_group_mask(obj, "FL_lips")
    rest = rest_vertices(obj)
    corrected = caches.evaluate_frames(obj, train, mute_shape_keys_prefix=("FL_Prop_",))
    reg = LipRegressor(rest, tris, faces_in_region(tris, mouth), faces_in_region(tris, lips))
    reg.fit(corrected)
    held = np.setdiff1d(frames, train)
    idx = np.searchsorted(frames, held)
    s2b = s2a = 0.0
    mxb = mxa = dev = 0.0
    n = 0
    t_eval = 0.0
    for s in range(0, len(held), chunk):
        f, i = held[s : s + chunk], idx[s : s + chunk]
        cap = shape_key_sequence(obj, f, skip_prefixes=("FL_",))  # the capture (validated against frame_set below)
        truth = cap.astype(np.float64) - cap_w[i, None, None] * err[None]
        t0 = time.perf_counter()
        got = caches.evaluate_frames(obj, f, mute_shape_keys_prefix=())
        t_eval += time.perf_counter() - t0
        expect = reg.predict(cap)
        dev = max(dev, float(np.abs(got - expect).max()))
        eb = np.linalg.norm(cap[:, lips] - truth[:, lips], axis=-1) * M_TO_MM
        ea = np.linalg.norm(got[:, lips] - truth[:, lips], axis=-1) * M_TO_MM
        s2b += float(np.sum(eb**2))
        s2a += float(np.sum(ea**2))
        mxb, mxa = max(mxb, float(eb.max())), max(mxa, float(ea.max()))
        n += eb.size
    rb, ra = np.sqrt(s2b / n), np.sqrt(s2a / n)
    return dict(
        held_out_frames=int(len(held)),
        lip_vertices=int(lips.sum()),
        before=dict(rms_mm=round(rb, 4), max_mm=round(mxb, 4)),
        after=dict(rms_mm=round(ra, 4), max_mm=round(mxa, 4)),
        rms_reduction_pct=round(100 * (1 - ra / rb), 1),
        max_dev_evaluated_vs_predict_mm=round(dev * M_TO_MM, 5),
        within_compression_tol=bool(dev * M_TO_MM <= COMPRESS_TOL_MM + 1e-3),
        evaluate_frames_s=round(t_eval, 2),
    )


# --------------------------------------------------------------------------- main
def main(argv=None):
    global _ORIG_READ
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000, help="sequence length (default 1000)")
    ap.add_argument("--quick", action="store_true", help="200 frames")
    args = ap.parse_args(argv)
    T = 200 if args.quick else args.frames

    out_json = json_stdout()  # Blender and libraries print to stdout; keep it for the JSON alone
    tmp = tempfile.mkdtemp(prefix="facelab-propbench-")
    user_resources()  # before bpy starts
    out = dict(frames=T, training_frames_n=N_TRAIN, platform=platform.platform(), cpus=os.cpu_count())
    t_all = time.perf_counter()

    t0 = time.perf_counter()
    import bpy

    from facelab_addon.blender import caches
    from facelab_addon.blender.mesh import mesh_triangles
    from facelab_addon.blender.shapekeys import (
        add_corrective_key,
        key_spike,
        shape_key_sequence,
    )
    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.core.lips.suggest import suggest_frames
    from facelab_addon.pipeline import propagate as op
    from facelab_addon.pipeline.training import read_training_frames
    from facelab_addon.testing.weights import speech_weights

    out["bpy_version"] = bpy.app.version_string
    out["bpy_import_s"] = since(t0)
    out["rss_after_bpy_import_mb"] = round(MEM.rss(), 1)
    with blender_session():
        ict = load_ict()
        frames = np.arange(1, T + 1)
        W = speech_weights(T, channels=EXPR)

        t0 = time.perf_counter()
        scene, obj, err, cap_w, info = build(bpy, ict, frames, W)
        out["build_scene_s"] = round(time.perf_counter() - t0, 2)
        out["vertices"] = len(obj.data.vertices)
        out["capture_error"] = dict(amplitude_mm_per_lip=ERR_CM * 10, key_value_min=round(float(cap_w.min()), 3),
                                    key_value_max=round(float(cap_w.max()), 3), **info)

        # ----- training frames: suggest_frames on the captured sequence (shape-key fast path, checked vs frame_set)
        tris = mesh_triangles(obj.data)
        mouth_faces, lip_faces = op.region_faces(obj, tris)
        rest = op.rest_vertices(obj)
        t0 = time.perf_counter()
        captured = shape_key_sequence(obj, frames)
        t_fast = time.perf_counter() - t0
        probe = frames[:: max(1, T // 20)]
        t0 = time.perf_counter()
        slow = caches.evaluate_frames(obj, probe)
        t_slow = (time.perf_counter() - t0) / len(probe)
        fast_dev = float(np.abs(slow - captured[probe - 1]).max())
        t0 = time.perf_counter()
        picks = suggest_frames(captured, N_TRAIN, rest_vertices=rest, faces=tris, mouth_faces=mouth_faces)
        t_suggest = time.perf_counter() - t0
        train = sorted(int(frames[i]) for i in picks)
        del captured, slow
        out["training_frames"] = dict(method="suggest_frames(captured, 10) without a regressor (extreme poses first)",
                                      frames=train, suggest_s=round(t_suggest, 2))
        out["read_capture"] = dict(
            frame_set_per_frame_ms=round(1e3 * t_slow, 2),
            frame_set_extrapolated_s=round(t_slow * T, 2),
            shape_key_sequence_s=round(t_fast, 3),
            max_abs_diff_mm=fast_dev * M_TO_MM,
        )

        for f in train:
            scene.frame_set(f)
            kb = add_corrective_key(obj, f"Sculpt_{f}", -cap_w[f - 1] * err)
            key_spike(kb, f)
            assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
        scene.frame_set(1)

        sizes = {"before": blend_sizes(bpy, tmp, "before")}
        out["rss_before_propagate_mb"] = round(MEM.rss(), 1)

        # ----- Propagate, one run
        run1 = run_operator(bpy, "first", suggestions=3)
        names, kf_keys, kf_extra = count_prop(obj)
        run1["fl_prop_keys"] = len(names)
        run1["keyframes"] = dict(fl_prop_values=kf_keys, fl_extrapolation=kf_extra, total=kf_keys + kf_extra)
        run1["suggested"] = sorted(int(m.frame) for m in scene.timeline_markers if m.name.startswith("FL suggest"))
        out["propagate"] = run1
        sizes["after"] = blend_sizes(bpy, tmp, "after")

        t0 = time.perf_counter()
        out["accuracy"] = accuracy(bpy, obj, frames, train, err, cap_w)
        out["accuracy"]["seconds"] = round(time.perf_counter() - t0, 1)

        # ----- incremental: correct the first suggested frame, propagate again
        f_new = [int(m.name.split()[-1]) for m in scene.timeline_markers if m.name.startswith("FL suggest")][0]
        scene.frame_set(f_new)
        # the artist sculpts what the viewport shows (the capture with Propagate's correction) to the truth; Mark
        # Training Frame keeps the shown correction (pipeline.training.mark_training_frame), so the sculpt is only
        # the rest: cancelling the whole capture error here would correct the frame twice
        cap_new = shape_key_sequence(obj, [f_new], skip_prefixes=("FL_",))[0].astype(np.float64)
        shown = caches.evaluate_frames(obj, [f_new], mute_shape_keys_prefix=())[0].astype(np.float64)
        kb = add_corrective_key(obj, f"Sculpt_{f_new}", cap_new - cap_w[f_new - 1] * err - shown)
        key_spike(kb, f_new)
        assert bpy.ops.facelab.mark_training_frame() == {"FINISHED"}
        trained_as = read_training_frames(obj, [f_new])[0].astype(np.float64)
        added_err_mm = float(np.abs(trained_as - (cap_new - cap_w[f_new - 1] * err)).max()) * M_TO_MM
        assert added_err_mm <= COMPRESS_TOL_MM, f"frame {f_new} trains {added_err_mm:.3g} mm off its truth"
        scene.frame_set(1)
        run2 = run_operator(bpy, "incremental", suggestions=3)
        names2, kf2, kfe2 = count_prop(obj)
        run2.update(added_frame=f_new, added_frame_max_error_mm=round(added_err_mm, 6), fl_prop_keys=len(names2), keyframes=kf2 + kfe2,
                    incremental_path_used="regressor: add (incremental)" in run2["split"]
                    and "regressor: LipRegressor.__init__ (Poisson factor, patches)" not in run2["split"])
        out["propagate_incremental"] = run2
        sizes["after_incremental"] = blend_sizes(bpy, tmp, "after_incremental")
        train2 = sorted(train + [f_new])
        t0 = time.perf_counter()
        acc2 = accuracy(bpy, obj, frames, train2, err, cap_w)
        out["accuracy_incremental"] = dict(after=acc2["after"], before=acc2["before"],
                                           max_dev_evaluated_vs_predict_mm=acc2["max_dev_evaluated_vs_predict_mm"],
                                           seconds=round(time.perf_counter() - t0, 1))

        b, a = sizes["before"], sizes["after"]
        sizes = {k: {kk: round(vv, 2) for kk, vv in v.items()} for k, v in sizes.items()}
        sizes["growth_raw_mb"] = round(a["raw_mb"] - b["raw_mb"], 2)
        sizes["growth_zstd_mb"] = round(a["zstd_mb"] - b["zstd_mb"], 2)
        sizes["target_growth_mb"] = TARGET_GROWTH_MB if T >= 1000 else round(TARGET_GROWTH_MB * T / 1000, 1)
        sizes["growth_ok"] = sizes["growth_raw_mb"] <= sizes["target_growth_mb"]
        out["blend"] = sizes
        MEM.peak()
        out["process_peak_rss_mb"] = round(MEM.process_peak, 1)
        out["peak_rss_reset_supported"] = MEM.can_reset
        out["target_core_rss_mb"] = TARGET_CORE_RSS_MB
        out["total_s"] = since(t_all, 1)
        out_json.emit(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
