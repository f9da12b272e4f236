"""Benchmark: Propagate at production scale (issue 14): 1k-10k frames on the 26.7k- and 105k-vertex face.

For each case a fresh subprocess *builds* the scene and saves it (ICT-FaceKit in metres, or ICT
subdivided once at its edge midpoints, ``testing.subdivide``: 105,569 vertices; eight mouth
expressions keyed with speech-like weights; a pose-dependent inner-lip ``CaptureError`` inside
``FL_lips``, as ``benchmarks/propagate_blender.py``; Auto Regions; 10 training frames corrected to
the truth), either as shape-key animation (``keys``) or baked to a PC2 played by a Mesh Cache
(``pc2``, the corrections then made with ``add_corrected_frame`` over the cache). Another fresh
subprocess opens the .blend and runs ``bpy.ops.facelab.propagate()`` once: wall time, the process's
peak RSS (``resource.getrusage`` max RSS: numpy and Blender allocations alike) and its RSS before
the operator, the CPU time it used (user + system, all threads: on a machine shared with other jobs
the wall time is inflated by the load, the CPU time much less), the .blend growth (uncompressed, saved before and after), FL_Prop keys written, and
the held-out inner-lip error against the truth on 20 frames of the evaluated mesh.

Also: core ``LipRegressor.predict`` frames/s at both sizes (in place, float32, after a warm-up) and
core ``refine_lips`` seconds at both sizes (``--core-only`` runs just these two; its JSON is saved to
``benchmarks/results/scale_core.json``: CPU a frame also with one BLAS thread, the ratio to the CPU time before
the float32 maps, and the float32 result's largest deviation from the float64 maps in mm),
medians of repeated runs where cheap, the machine's load (``uptime``) before and after, and a plot
of time and peak memory against frames for both sizes with the paper's timing for scale (Dinev et
al. 2018 report 5.15 s a frame for the prediction).

Usage: ``PYTHONPATH=. python benchmarks/scale.py [--quick] [--png docs/images/scale.png]``.
Prints one JSON object on stdout (save it to ``benchmarks/results/scale.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _harness import blender_session  # noqa: E402

SCALE = 0.01
N_TRAIN = 10
PAPER_S_PER_FRAME = 5.15  # Dinev et al. 2018: prediction, a frame
TARGET = dict(wall_s=60.0, peak_mb=2000.0, frames=10000, vertices=105_000)


def _uptime():
    return Path("/proc/loadavg").read_text().split()[:3]


def _rss_mb():
    for ln in Path("/proc/self/status").read_text().splitlines():
        if ln.startswith("VmRSS:"):
            return int(ln.split()[1]) * 1024 / 1e6
    return float("nan")


def _peak_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


# --------------------------------------------------------------------------- the face at both sizes
def face_model(size):
    """(neutral (V,3) m, faces (F,3), expression deltas (8,V,3) m, S or None) at ``size`` ('26k' or '105k')."""
    from propagate_blender import EXPR

    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.testing.subdivide import subdivide_midpoint

    ict = load_ict()
    V = ict.neutral * SCALE
    D = np.stack([(ict.expressions[n] - ict.neutral) * SCALE for n in EXPR])
    if size == "26k":
        return ict, V, ict.faces, D, None
    V2, F2, S = subdivide_midpoint(V, ict.faces)
    return ict, V2, F2, np.stack([S @ d for d in D]), S


def _lip_error(obj, V, faces):
    """(V,3) CaptureError at value 1: upper and lower inner lips pulled apart (1 mm each), zero on the FL_lips border."""
    from facelab_addon.blender.mesh import mesh_triangles, vertex_group_mask
    from facelab_addon.core.geometry.geodesic import geodesic_distance
    from facelab_addon.core.lips import regions

    tris = mesh_triangles(obj.data)
    lips = vertex_group_mask(obj, "FL_lips")
    border = regions.region_border(tris, regions.faces_in_region(tris, lips), len(V))
    interior = lips.copy()
    interior[border] = False
    width = float(np.ptp(V[lips, 1])) * 0.5
    db = geodesic_distance(V, tris, border, limit=width)
    u = np.clip(np.where(np.isfinite(db), db, width) / (0.35 * width), 0.0, 1.0)
    fade = u * u * (3 - 2 * u) * interior
    y0 = float(np.median(V[lips, 1]))
    err = np.zeros_like(V)
    err[:, 1] = np.sign(V[:, 1] - y0) * fade * 1e-3
    return err


def build(size, n_frames, source, path):
    """Subprocess: build the case's scene and save it to ``path``; returns build facts."""
    import bpy
    from propagate_blender import capture_error_weight

    from facelab_addon.blender.scene import new_mesh_object
    from facelab_addon.blender.shapekeys import add_corrective_key, key_spike, key_values_bulk
    from facelab_addon.core.capture.pointcache_writer import PointCacheWriter
    from facelab_addon.pipeline.training import add_corrected_frame, record_training_frame
    from facelab_addon.testing.weights import speech_weights

    t0 = time.perf_counter()
    ict, V, F, D, S = face_model(size)
    frames = np.arange(1, n_frames + 1)
    W = speech_weights(n_frames, channels=__import__("propagate_blender").EXPR)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, n_frames
    if S is None:
        obj = new_mesh_object("Face", V, poly_verts=ict.poly_verts, poly_offsets=ict.poly_offsets)
    else:
        obj = new_mesh_object("Face", V, poly_verts=F.ravel(), poly_offsets=np.arange(0, 3 * len(F) + 1, 3))
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    assert bpy.ops.facelab.auto_regions() == {"FINISHED"}
    err = _lip_error(obj, V, F)
    cap_w = capture_error_weight(W)
    # training frames: the most extreme mouth poses, spread over the shot
    order = np.argsort(-np.linalg.norm(W, axis=1))
    train = []
    for i in order:
        if all(abs(int(i) - j) > n_frames // (2 * N_TRAIN) for j in train):
            train.append(int(i))
        if len(train) == N_TRAIN:
            break
    train = sorted(train)
    if source == "keys":
        obj.shape_key_add(name="Basis", from_mix=False)
        names = [add_corrective_key(obj, f"E{k}", D[k]).name for k in range(len(D))]
        kb = add_corrective_key(obj, "CaptureError", err)
        kb.slider_min = -2.0
        key_values_bulk(obj, names + ["CaptureError"], frames, np.c_[W, cap_w])
        for i in train:
            key_spike(add_corrective_key(obj, f"Sculpt_{frames[i]}", -cap_w[i] * err), int(frames[i]))
            record_training_frame(scene, obj, int(frames[i]), "", "sculpt")
    else:
        pc2 = Path(path).with_suffix(".pc2")
        Df = D.reshape(len(D), -1)
        with PointCacheWriter(pc2, "PC2", len(V), n_frames, start_frame=1.0) as w:
            for s in range(0, n_frames, 256):
                X = (V.ravel() + W[s : s + 256] @ Df).reshape(-1, len(V), 3) + cap_w[s : s + 256, None, None] * err
                for x in X.astype(np.float32):
                    w.write(x)
        md = obj.modifiers.new("Capture", "MESH_CACHE")
        md.cache_format, md.filepath, md.frame_start = "PC2", str(pc2), 1.0
        for i in train:
            truth = (V.ravel() + W[i] @ Df).reshape(len(V), 3)
            add_corrected_frame(scene, obj, int(frames[i]), truth)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=False)
    np.savez(Path(path).with_suffix(".npz"), W=W, cap_w=cap_w, err=err, train=np.asarray(train))
    return dict(build_s=round(time.perf_counter() - t0, 1), blend_mb=round(Path(path).stat().st_size / 1e6, 2),
                vertices=len(V), training_frames=[int(frames[i]) for i in train],
                pc2_mb=round(Path(path).with_suffix(".pc2").stat().st_size / 1e6, 1) if source == "pc2" else 0.0)


def run(path, size, source):
    """Subprocess: open the case, run the Propagate operator once, measure."""
    import bpy

    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    obj = bpy.data.objects["Face"]
    bpy.context.view_layer.objects.active = obj
    before_mb = Path(path).stat().st_size / 1e6
    rss0, peak0 = _rss_mb(), _peak_mb()
    load = _uptime()
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    res = bpy.ops.facelab.propagate()
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)  # this process, all its threads
    peak = _peak_mb()
    out = Path(path).with_name(Path(path).stem + "_after.blend")
    bpy.ops.wm.save_as_mainfile(filepath=str(out), compress=False, copy=True)
    growth = out.stat().st_size / 1e6 - before_mb
    out.unlink()
    keys = [kb.name for kb in obj.data.shape_keys.key_blocks if kb.name.startswith("FL_Prop_")]
    from facelab_addon.blender.ownership import correction_cache

    md, files = correction_cache(obj, "FL_Prop_")  # the correction cache, when the correction went to one
    cache = dict(cache_modifier=f"{md.name} ({md.type})" if md is not None else "",
                 cache_file_mb=round(Path(files[-1]).stat().st_size / 1e6, 1) if md is not None else 0.0,
                 modifiers=[m.name for m in obj.modifiers])
    acc = _accuracy(obj, path, source)
    for f in files:  # the temp folder is removed after the case, this frees the disk sooner
        Path(f).unlink(missing_ok=True)
    return dict(result=sorted(res), wall_s=round(wall, 2), cpu_s=round(cpu, 2), rss_before_mb=round(rss0, 1),
                peak_rss_mb=round(peak, 1), peak_before_operator_mb=round(peak0, 1),
                peak_growth_mb=round(peak - rss0, 1), blend_growth_mb=round(growth, 2), keys=len(keys),
                load_during=load, **cache, **acc)


def _accuracy(obj, path, source, n=20):
    """Held-out inner-lip error (mm) vs the truth on ``n`` frames of the evaluated mesh, before and after."""
    from facelab_addon.blender import caches
    from facelab_addon.blender.mesh import vertex_group_mask

    d = np.load(Path(path).with_suffix(".npz"))
    T = len(d["W"])
    held = np.setdiff1d(np.linspace(0, T - 1, n + N_TRAIN).astype(int), d["train"])[:n]
    frames = held + 1
    lips = vertex_group_mask(obj, "FL_lips")
    got = caches.evaluate_frames(obj, frames, mute_shape_keys_prefix=())[:, lips].astype(np.float64)
    cap = caches.read_captured_frames(obj, frames)[:, lips].astype(np.float64)
    truth = cap - d["cap_w"][held, None, None] * d["err"][None, lips]
    eb = np.linalg.norm(cap - truth, axis=-1) * 1e3
    ea = np.linalg.norm(got - truth, axis=-1) * 1e3
    return dict(held_out_lip_rms_mm_before=round(float(np.sqrt(np.mean(eb**2))), 4),
                held_out_lip_rms_mm_after=round(float(np.sqrt(np.mean(ea**2))), 4))


BASELINE_CPU_MS = {"26k": 0.198, "105k": 0.982}  # core predict before float32 maps (scale.json, load 3)


def core_predict(size, n=512, repeats=5):
    """Subprocess: LipRegressor.predict frames/s, in place on float32 frames (median of ``repeats``).

    Wall and CPU time (``time.process_time``: all threads of this process) per run with the BLAS threads
    ``predict`` picks itself (two when a core is idle), then CPU time with BLAS limited to one thread; the
    largest deviation of the float32 prediction from the float64 maps (``lip_corrections``), in mm.
    """
    from propagate_blender import EXPR
    from threadpoolctl import threadpool_limits

    from facelab_addon.core.lips import regions
    from facelab_addon.core.lips.regressor import LipRegressor
    from facelab_addon.testing.weights import speech_weights

    ict, V, F, D, S = face_model(size)
    W = speech_weights(n, channels=EXPR)
    X = (V.ravel() + W @ D.reshape(len(D), -1)).reshape(n, len(V), 3)
    mouth, lip = regions.auto_regions(V, F)
    reg = LipRegressor(V, F, regions.faces_in_region(F, mouth), regions.faces_in_region(F, lip))
    reg.fit(X[:: n // N_TRAIN][:N_TRAIN] + 1e-4 * np.sin(np.arange(len(V)))[None, :, None])
    iv = reg.interior_vertices
    f64 = X[:64, iv] + reg.lip_corrections(X[:64])  # float64 maps
    dev_mm = 1e3 * float(np.abs(reg.predict(X[:64])[:, iv] - f64).max())  # the scene is in metres
    X32 = X.astype(np.float32)
    reg.predict(X32[:32], out=X32[:32])
    times, cpus, cpus1 = [], [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        reg.predict(X32, out=X32)
        times.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    with threadpool_limits(1):
        for _ in range(repeats):
            c0 = time.process_time()
            reg.predict(X32, out=X32)
            cpus1.append(time.process_time() - c0)
    fps = [n / t for t in times]
    cpu_ms = 1e3 * float(np.median(cpus)) / n
    return dict(vertices=len(V), frames=n, fps_median=round(float(np.median(fps)), 1),
                fps_all=[round(f, 1) for f in fps], cpu_ms_per_frame=round(cpu_ms, 3),
                cpu_ms_per_frame_min=round(1e3 * min(cpus) / n, 3),
                cpu_ms_per_frame_one_blas_thread=round(1e3 * float(np.median(cpus1)) / n, 3),
                cpu_ms_baseline=BASELINE_CPU_MS[size], cpu_ratio_to_baseline=round(cpu_ms / BASELINE_CPU_MS[size], 3),
                max_deviation_from_float64_mm=float(f"{dev_mm:.3g}"),
                load=_uptime(), paper_s_per_frame=PAPER_S_PER_FRAME,
                speedup_vs_paper=round(float(np.median(fps)) * PAPER_S_PER_FRAME))


def refine_time(size, runs=4):
    """Subprocess: core ``refine_lips`` (5 iterations, whole face) on the neutral face with a 2.5 mm inner-lip gap,
    sketch from the truth (as ``benchmarks/sketch_refine.py``); median of the warm runs."""
    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.core.lips.refine_params import RefineParams
    from facelab_addon.core.lips.sketch import refine_lips
    from facelab_addon.testing.gap_case import ict_gap_case

    g = ict_gap_case(load_ict(), size)
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        refine_lips(g.captured, g.faces, g.camera, g.upper, g.lower, RefineParams(iterations=5), fixed=g.fixed)
        ts.append(time.perf_counter() - t0)
    return dict(vertices=len(g.truth), seconds_median_warm=round(float(np.median(ts[1:])), 3),
                seconds_all=[round(t, 3) for t in ts], load=_uptime(), target_s=0.1 if size == "26k" else 0.3)


# --------------------------------------------------------------------------- Reconstruct and Solve, 1,000 frames
EXTRA = "cheekPuff_L"  # outside the rig / dataset: its part of the truth is what the per-frame correctives carry
CLIP_SIZE = (540, 960)


def _perframe_truth(ict, n_frames, idx):
    """Truth at vertices ``idx`` (T,len(idx),3) m: the rig expressions (speech weights) plus EXTRA; frame 0 neutral."""
    from propagate_blender import EXPR

    from facelab_addon.testing.weights import speech_weights

    W = speech_weights(n_frames, channels=EXPR)
    W[0] = 0.0
    t = np.arange(n_frames)
    w_extra = 0.35 * (1 - np.cos(2 * np.pi * t / 97.0))  # smooth, 0 on frame 0
    N = ict.neutral[idx] * SCALE
    D = np.stack([(ict.expressions[e][idx] - ict.neutral[idx]) * SCALE for e in EXPR])
    E = (ict.expressions[EXTRA][idx] - ict.neutral[idx]) * SCALE
    return N[None] + np.einsum("ts,svd->tvd", W, D) + w_extra[:, None, None] * E[None]


def build_perframe(kind, n_frames, path):
    """Subprocess: the 26.7k ICT face (metres) with the 8 mouth expressions as shape keys, and either 100
    keyed bundle empties on the front of the face (``recon``) or a helmet stereo pair of Movie Clips with
    50 tracks each (``solve``, bound on the neutral frame 0), following ``n_frames`` of speech plus
    ``EXTRA``; saved to ``path``."""
    import bpy
    from PIL import Image
    from propagate_blender import EXPR

    from facelab_addon.blender.camera import apply_camera_to_blender
    from facelab_addon.blender.mesh import mesh_triangles
    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.testing.capture_sim import helmet_cameras, sample_markers
    from facelab_addon.testing.scenes import build_ict_face_scene, keyed_empties
    from facelab_addon.testing.synthetic import ICT_MOUTH_LOOP

    t0 = time.perf_counter()
    ict = load_ict()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    fs = build_ict_face_scene(ict, EXPR, frame_range=(0, n_frames - 1), scale=SCALE, fixed_group=True,
                              select=False, reset=False)
    scene, obj = bpy.context.scene, fs.obj
    scene.frame_start, scene.frame_end = 0, n_frames - 1
    neutral = ict.neutral * SCALE
    info = dict(kind=kind, frames=n_frames, vertices=len(neutral))
    if kind == "recon":
        tris = mesh_triangles(obj.data)
        rng = np.random.default_rng(0)
        front = np.flatnonzero(ict.part_face_mask("M_Face")[: len(tris)] & (neutral[tris].mean(1)[:, 2] > 0.07))
        pick, bary = rng.choice(front, 100, replace=False), rng.dirichlet([4, 4, 4], 100)
        idx = tris[pick]  # (100,3)
        Tr = _perframe_truth(ict, n_frames, idx.ravel()).reshape(n_frames, 100, 3, 3)
        keyed_empties(scene, np.einsum("bk,tbkd->tbd", bary, Tr), collection="Bundles")
        info["bundles"] = 100
    else:
        from facelab_addon.blender.tracking import View
        from facelab_addon.pipeline.solve import BindSettings, bind_tracks

        cams = helmet_cameras(center=np.array([0.0, -1.0, 8.0]) * SCALE, cm=SCALE, focal_px=600.0,
                              width=CLIP_SIZE[0], height=CLIP_SIZE[1])
        skin = ict.part_face_mask("M_Face")
        excl = np.concatenate([neutral[ICT_MOUTH_LOOP], neutral[ict.part_vertex_mask("M_ScleraLeft", "M_ScleraRight")]])
        mk = sample_markers(neutral, ict.faces, cams, skin, n=50, seed=3, exclude=excl, exclude_radius=0.009)
        Tr = _perframe_truth(ict, n_frames, mk.vertices.ravel()).reshape(n_frames, len(mk.vertices), 3, 3)
        X = np.einsum("mk,tmkd->tmd", mk.bary, Tr)
        views = []
        img = Image.fromarray(np.zeros((CLIP_SIZE[1], CLIP_SIZE[0], 3), np.uint8))
        for c, cam in enumerate(cams):
            cam_obj = bpy.data.objects.new(f"Cam{c}", bpy.data.cameras.new(f"Cam{c}"))
            scene.collection.objects.link(cam_obj)
            apply_camera_to_blender(cam, cam_obj, scene)
            d = Path(path).parent / f"clip{c}"
            d.mkdir(exist_ok=True)
            for i in range(1, n_frames + 1):
                img.save(d / f"cam{c}_{i:05d}.png")
            clip = bpy.data.movieclips.load(str(d / f"cam{c}_00001.png"))
            clip.frame_start = 0
            tc = clip.tracking.camera
            tc.sensor_width, tc.focal_length = 36.0, cam.K[0, 0] * 36.0 / CLIP_SIZE[0]
            tc.principal_point_pixels = (cam.K[0, 2], CLIP_SIZE[1] - cam.K[1, 2])
            for j in range(len(mk.vertices)):
                tr = clip.tracking.tracks.new(name=f"M{j:02d}", frame=1)
                for f in range(2, n_frames + 1):
                    tr.markers.insert_frame(f)
                px = cam.project(X[:, j])
                tr.markers.foreach_set("co", np.c_[px[:, 0] / CLIP_SIZE[0], 1 - px[:, 1] / CLIP_SIZE[1]]
                                       .astype(np.float32).ravel())
            v = scene.facelab_solve.views.add()
            v.camera, v.clip = cam_obj, clip
            views.append(View(cam_obj, clip))
        scene.camera = views[0].camera
        b = bind_tracks(scene, obj, 0, BindSettings(views=views))
        info.update(tracks=len(b.bound), views=len(views))
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=False)
    info.update(build_s=round(time.perf_counter() - t0, 1), blend_mb=round(Path(path).stat().st_size / 1e6, 2))
    return info


class _RssSampler:
    """RSS of this process every ``every`` seconds on a thread: the peak and a coarse timeline (MB)."""

    def __init__(self, every=0.5):
        import threading

        self.every, self.samples, self._stop = every, [], threading.Event()
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.wait(self.every):
            self.samples.append((time.perf_counter() - self._t0, _rss_mb()))

    def stop(self, n=12):
        """``n`` (seconds, MB) points: the largest RSS in each of ``n`` equal stretches of the run."""
        self._stop.set()
        self._thread.join()
        if not self.samples:
            return []
        t_end = self.samples[-1][0] or 1.0
        bins = {}
        for t, mb in self.samples:
            b = min(int(n * t / t_end), n - 1)
            bins[b] = max(bins.get(b, (t, 0.0)), (t, mb), key=lambda x: x[1])
        return [[round(t, 1), round(mb, 1)] for t, mb in (bins[b] for b in sorted(bins))]


def run_perframe(kind, path):
    """Subprocess: open the case, run Reconstruct from Bundles (Fit + Residual) or Solve Performance (markers +
    corrective, no contours) once through the pipeline; wall, CPU, peak RSS (and an RSS timeline), .blend
    growth, keys vs cache. ``recon_cache``: Reconstruct with a key budget of 2, so the correction (which needs
    15 keys) is written as a PC2 cache beside the .blend."""
    import bpy

    from facelab_addon.blender.tracking import View

    bpy.ops.wm.open_mainfile(filepath=str(path))
    scene = bpy.context.scene
    obj = bpy.data.objects["Face"]
    before = Path(path).stat().st_size / 1e6
    if kind == "recon_cache":
        scene.facelab_store.key_budget = 2
    rss0 = _rss_mb()
    load = _uptime()
    ru0 = resource.getrusage(resource.RUSAGE_SELF)
    sampler = _RssSampler()
    t0 = time.perf_counter()
    if kind in ("recon", "recon_cache"):
        from facelab_addon.pipeline.reconstruct import ReconstructSettings, reconstruct_from_bundles

        empties = list(bpy.data.collections["Bundles"].objects)
        r = reconstruct_from_bundles(scene, obj, ReconstructSettings(bind_frame=0, selected=tuple(empties)))
    else:
        from facelab_addon.pipeline.solve import SolveSettings, solve_performance

        views = [View(v.camera, v.clip) for v in scene.facelab_solve.views]
        r = solve_performance(scene, obj, SolveSettings(views=views, use_contours=False, use_corrective=True))
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_SELF)
    timeline = sampler.stop()
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    peak = _peak_mb()
    out = Path(path).with_name(Path(path).stem + "_after.blend")
    bpy.ops.wm.save_as_mainfile(filepath=str(out), compress=False, copy=True)
    growth = out.stat().st_size / 1e6 - before
    out.unlink()
    st = getattr(r.keys, "storage", None)
    cache_mb = round(Path(st.cache_path).stat().st_size / 1e6, 1) if st is not None and st.cache_path else 0.0
    return dict(kind=kind, wall_s=round(wall, 2), cpu_s=round(cpu, 2), rss_before_mb=round(rss0, 1),
                peak_rss_mb=round(peak, 1), peak_growth_mb=round(peak - rss0, 1), rss_timeline_s_mb=timeline,
                blend_growth_mb=round(growth, 2), keys=len(r.keys),
                stored_as=st.mode if st is not None else "", storage_note=st.note if st is not None else "",
                storage_max_error_mm=None if st is None else round(float(st.max_error_mm), 5),
                cache_file_mb=cache_mb, load_during=load, frames=len(r.frames))


# --------------------------------------------------------------------------- driver
def _sub(args, timeout=3600):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, env=env, timeout=timeout)
    if p.returncode:
        raise RuntimeError(f"{args}: exit {p.returncode}\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def _note(out):
    def span(rows):
        loads = [float(x) for r in rows for x in r.get("load_during", [])[:1]]
        return f"{min(loads):.0f}-{max(loads):.0f}" if loads else "?"

    note = f"Propagate operator (10 training frames), shared {out['machine']['cpus']}-core machine, 1-min load " \
           f"{span(out['cases'])}"
    if out.get("perframe"):
        note += f"; Reconstruct and Solve: load {span(out['perframe'])}"
    return note


def plot(results, png, note="", perframe=(), pc2_policy=()):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 5))
    for (size, source), mk, col in zip([("26k", "keys"), ("26k", "pc2"), ("105k", "keys"), ("105k", "pc2")],
                                       ["o-", "s--", "o-", "s--"], ["C0", "C0", "C2", "C2"]):
        rows = [r for r in results if r["size"] == size and r["source"] == source]
        if not rows:
            continue
        f = [r["frames"] for r in rows]
        lab = f"{size} vertices, {'shape keys' if source == 'keys' else 'PC2 input, correction to a point cache'}"
        ax[0].plot(f, [r["wall_s"] for r in rows], mk, color=col, label=lab)
        ax[1].plot(f, [r["peak_rss_mb"] / 1000 for r in rows], mk, color=col, label=lab)
    for r in pc2_policy:
        col = "C0" if r["size"] == "26k" else "C2"
        lab = f"{r['size']} vertices, PC2 input, correction to a point cache"
        ax[0].plot([r["frames"]], [r["wall_s"]], "s", mfc="none", color=col, label=lab)
        ax[1].plot([r["frames"]], [r["peak_rss_mb"] / 1000], "s", mfc="none", color=col, label=lab)
    names = {"recon": "Reconstruct from Bundles, 26.7k (keys)", "solve": "Solve Performance, 26.7k (keys)",
             "recon_cache": "Reconstruct from Bundles, 26.7k (point cache)"}
    for kind, mk, col in (("recon", "^-", "C3"), ("recon_cache", "^--", "C3"), ("solve", "v-", "C4")):
        rows = sorted([r for r in perframe if "failed" not in r and r["kind"] == kind], key=lambda r: r["frames"])
        if rows:
            f = [r["frames"] for r in rows]
            ax[0].plot(f, [r["wall_s"] for r in rows], mk, color=col, label=names[kind])
            ax[1].plot(f, [r["peak_rss_mb"] / 1000 for r in rows], mk, color=col, label=names[kind])
    fmax = max(r["frames"] for r in results)
    ax[0].axhline(TARGET["wall_s"], color="r", lw=0.8, ls=":", label="target at 10k frames, 105k vertices")
    ax[0].text(0.98, 0.05, f"paper (Dinev et al. 2018): {PAPER_S_PER_FRAME} s a frame\n= {PAPER_S_PER_FRAME * fmax / 3600:.0f} h "
               f"for {fmax:,} frames", transform=ax[0].transAxes, va="bottom", ha="right", fontsize=8)
    ax[1].axhline(TARGET["peak_mb"] / 1000, color="r", lw=0.8, ls=":", label="target peak 2 GB")
    ax[0].set(xlabel="frames", ylabel="wall time (s, log scale)", title="Time", yscale="log")
    ax[1].set(xlabel="frames", ylabel="process peak RSS (GB)", title="Peak memory", ylim=(0, None))
    for a in ax:
        a.grid(alpha=0.3)
    h, lab = ax[0].get_legend_handles_labels()
    h1, lab1 = ax[1].get_legend_handles_labels()
    h, lab = h + [x for x, y in zip(h1, lab1) if y not in lab], lab + [y for y in lab1 if y not in lab]
    fig.legend(h, lab, fontsize=7, loc="lower center", ncol=3)
    if note:
        fig.suptitle(note, fontsize=9)
    fig.tight_layout(rect=(0, 0.17, 1, 1))
    fig.savefig(png, dpi=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="1k and 2k frames at 26.7k vertices, shape keys and PC2")
    ap.add_argument("--png", default=str(ROOT / "docs" / "images" / "scale.png"))
    ap.add_argument("--repeats", type=int, default=3, help="runs of each 1,000-frame case (median reported)")
    ap.add_argument("--sizes", default=None, help="comma list of 26k,105k (default: both; --quick: 26k)")
    ap.add_argument("--frames", default=None, help="comma list of frame counts (default 1000,5000,10000)")
    ap.add_argument("--sources", default="keys,pc2", help="comma list of keys,pc2")
    ap.add_argument("--pc2-max-frames", type=int, default=10000,
                    help="skip PC2 cases longer than this (a 10k-frame 105k PC2 is 12 GB to write)")
    ap.add_argument("--replot", metavar="JSON", help="only redraw the plot from a saved result")
    ap.add_argument("--_build", nargs=4, help=argparse.SUPPRESS)
    ap.add_argument("--_run", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--_core", nargs=1, help=argparse.SUPPRESS)
    ap.add_argument("--_refine", nargs=1, help=argparse.SUPPRESS)
    ap.add_argument("--core-only", action="store_true", help="only core predict and Refine at both sizes (JSON)")
    ap.add_argument("--perframe", metavar="FRAMES",
                    help="only Reconstruct from Bundles and Solve Performance on FRAMES (a comma list) frames of the "
                         "26.7k face (JSON)")
    ap.add_argument("--perframe-kinds", default="recon,solve",
                    help="with --perframe: comma list of recon, solve, recon_cache (Reconstruct into a PC2 cache)")
    ap.add_argument("--_build_pf", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--_run_pf", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.replot:
        d = json.loads(Path(a.replot).read_text())
        plot([r for r in d["cases"] if "failed" not in r], a.png, _note(d), d.get("perframe", ()),
             d.get("cases_pc2_after_policy", ()))
        return
    # subprocess modes; those that use Blender run with the add-on registered (``_harness.blender_session``)
    if a._build:
        size, n, source, path = a._build
        with blender_session():
            r = build(size, int(n), source, path)
        print(json.dumps(r))
        return
    if a._run:
        with blender_session():
            r = run(*a._run)
        print(json.dumps(r))
        return
    if a._core:
        print(json.dumps(core_predict(a._core[0])))
        return
    if a._build_pf:
        kind, n, path = a._build_pf
        with blender_session():
            r = build_perframe(kind, int(n), path)
        print(json.dumps(r))
        return
    if a._run_pf:
        with blender_session():
            r = run_perframe(*a._run_pf)
        print(json.dumps(r))
        return
    if a.perframe:
        out = dict(machine=dict(cpus=os.cpu_count(), load_before=_uptime()), perframe=[])
        for n in [int(x) for x in str(a.perframe).split(",")]:
            for kind in a.perframe_kinds.split(","):
                with tempfile.TemporaryDirectory(prefix="facelab_scale_pf_") as tmp:
                    path = Path(tmp) / f"{kind}.blend"
                    try:
                        b = _sub(["--_build_pf", "recon" if kind == "recon_cache" else kind, str(n), str(path)])
                        r = _sub(["--_run_pf", kind, str(path)])
                    except RuntimeError as e:
                        out["perframe"].append(dict(kind=kind, frames=n, failed=str(e)[-800:]))
                        continue
                    r.update(build=b, ms_per_frame=round(1e3 * r["wall_s"] / n, 2))
                    out["perframe"].append(r)
                    print(json.dumps({k: r[k] for k in ("kind", "frames", "wall_s", "cpu_s", "peak_rss_mb",
                                                        "peak_growth_mb", "blend_growth_mb", "keys", "stored_as",
                                                        "cache_file_mb")}), file=sys.stderr)
        out["machine"]["load_after"] = _uptime()
        print(json.dumps(out, indent=1))
        return
    if a._refine:
        print(json.dumps(refine_time(a._refine[0])))
        return

    sizes = a.sizes.split(",") if a.sizes else (["26k"] if a.quick else ["26k", "105k"])
    counts = [int(x) for x in a.frames.split(",")] if a.frames else ([1000, 2000] if a.quick else [1000, 5000, 10000])
    out = dict(machine=dict(cpus=os.cpu_count(), load_before=_uptime()), targets=TARGET, cases=[], core_predict={})
    t_all = time.perf_counter()
    out["refine"] = {}
    for size in sizes:
        out["core_predict"][size] = _sub(["--_core", size])
        out["refine"][size] = _sub(["--_refine", size])
    if a.core_only:
        print(json.dumps({k: out[k] for k in ("machine", "core_predict", "refine")}, indent=1))
        return
    with tempfile.TemporaryDirectory(prefix="facelab_scale_") as tmp:
        for size in sizes:
            for source in a.sources.split(","):
                for n in counts:
                    if source == "pc2" and n > a.pc2_max_frames:
                        continue
                    path = Path(tmp) / f"{size}_{source}_{n}.blend"
                    try:
                        b = _sub(["--_build", size, str(n), source, str(path)])
                        reps = a.repeats if n <= 1000 and source == "keys" else 1
                        runs = [_sub(["--_run", str(path), size, source]) for _ in range(reps)]
                    except RuntimeError as e:  # reported, not hidden
                        out["cases"].append(dict(size=size, source=source, frames=n, failed=str(e)[-800:]))
                        print(f"{size} {source} {n}: FAILED", file=sys.stderr)
                        continue
                    r = dict(runs[0])
                    for k in ("wall_s", "cpu_s", "peak_rss_mb", "peak_growth_mb"):
                        if k in runs[0]:
                            r[k] = float(np.median([x[k] for x in runs]))
                    r.update(size=size, source=source, frames=n, vertices=b["vertices"], build=b, repeats=reps,
                             wall_s_all=[x["wall_s"] for x in runs], ms_per_frame=round(1e3 * r["wall_s"] / n, 2),
                             speedup_vs_paper=round(PAPER_S_PER_FRAME * n / r["wall_s"]))
                    out["cases"].append(r)
                    print(json.dumps({k: r[k] for k in ("size", "source", "frames", "wall_s", "peak_rss_mb",
                                                        "blend_growth_mb", "keys")}), file=sys.stderr)
                    for ext in (".blend", ".pc2", ".npz"):
                        path.with_suffix(ext).unlink(missing_ok=True)
    ok = [r for r in out["cases"] if "failed" not in r]
    big = [r for r in ok if r["frames"] == max(counts) and r["size"] == sizes[-1]]
    for r in ok:
        same = [x for x in ok if x["size"] == r["size"] and x["source"] == r["source"]]
        r["ms_per_frame_vs_smallest_shot"] = round(r["ms_per_frame"] / same[0]["ms_per_frame"], 2)
    out["summary"] = dict(
        largest=[{k: r[k] for k in ("size", "source", "frames", "wall_s", "peak_rss_mb", "blend_growth_mb")}
                 for r in big],
        meets_wall=all(r["wall_s"] <= TARGET["wall_s"] for r in big) if not a.quick else None,
        meets_peak=all(r["peak_rss_mb"] <= TARGET["peak_mb"] for r in big) if not a.quick else None,
    )
    out["machine"]["load_after"] = _uptime()
    out["seconds"] = round(time.perf_counter() - t_all, 1)
    if a.png:
        plot(ok, a.png, _note(out))
        out["png"] = os.path.relpath(a.png, ROOT)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
