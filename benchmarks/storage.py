"""Benchmark: how per-frame corrections are stored (``pipeline.correctives``), keys vs point cache.

Scene: a grid of ~26.9k vertices (the ICT-FaceKit face's size) in metres, saved to a temporary
.blend. Three corrections over N frames are stored with ``CorrectionWriter`` in chunks of 64 frames:

- ``low_rank``: 6 smooth shapes with smooth weights, plus noise below the 0.01 mm tolerance (a
  Propagate-like correction): expected as keys;
- ``low_rank_product``: the same 6 shapes given as basis + weights (``add_low_rank``, no spool);
- ``full_rank``: a smooth field that changes shape every frame (a Reconstruct-like correction):
  expected as a PC2 point cache beside the .blend.

Reported per case: storage mode, keys, wall time of ``add`` + ``finish`` (including making the
synthetic chunks), the peak of the memory NumPy and Python allocate meanwhile (``tracemalloc``; the
input chunks included), the process's peak RSS so far, cache file size, .blend size, and the largest error of the evaluated mesh on 8 sampled frames
(depsgraph) against the correction, in mm. Also the unit check of issue 11: the keys the previous
policy (tolerance from the unit scale only) and this one write for the same correction at 0.01, 1 and
100 object scale.

Usage: ``PYTHONPATH=. python benchmarks/storage.py [--frames 1000] > benchmarks/results/storage.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
import tracemalloc

import numpy as np


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


def grid(bpy, n=164):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=n - 1, y_subdivisions=n - 1, size=0.2)
    return bpy.context.scene, bpy.context.object


def fields(co, k, seed):
    rng = np.random.default_rng(seed)
    out = np.empty((k, len(co), 3), np.float32)
    for i in range(k):
        c = co[rng.integers(len(co))]
        w = np.exp(-np.sum((co - c) ** 2, axis=1) / 0.03**2)
        out[i] = (w[:, None] * rng.normal(0, 1, 3) * 1e-3).astype(np.float32)
    return out


def run_case(bpy, name, frames, chunk_fn, lowrank=None):
    from facelab_addon.blender import caches
    from facelab_addon.names import PROPAGATE_PREFIX
    from facelab_addon.pipeline.correctives import CorrectionWriter

    scene, obj = grid(bpy)
    tmp = tempfile.mkdtemp(prefix="facelab-storage-")
    blend = os.path.join(tmp, "shot.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    size0 = os.path.getsize(blend)
    co = np.array([v.co[:] for v in obj.data.vertices])
    tracemalloc.start()
    t0 = time.perf_counter()
    with CorrectionWriter(scene, obj, PROPAGATE_PREFIX) as w:
        if lowrank is not None:
            w.add_low_rank(frames, *lowrank(co))
        else:
            for i in range(0, len(frames), 64):
                w.add(frames[i:i + 64], chunk_fn(co, i, min(len(frames), i + 64)))
        res = w.finish()
    wall = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    sample = frames[np.linspace(0, len(frames) - 1, 8).astype(int)]
    got = caches.evaluate_frames(obj, sample, mute_shape_keys_prefix=()).astype(np.float64) - co[None]
    idx = np.searchsorted(frames, sample)
    want = np.concatenate([chunk_fn(co, i, i + 1) for i in idx]) if lowrank is None else \
        np.einsum("tr,rvc->tvc", lowrank(co)[1][idx], lowrank(co)[0])
    err_mm = float(np.linalg.norm(got - want, axis=2).max() * 1e3)
    return dict(case=name, frames=len(frames), vertices=len(co), mode=res.mode, keys=len(res.keys),
                cache_mb=round(os.path.getsize(res.cache_path) / 1e6, 1) if res.cache_path else 0.0,
                blend_mb_before=round(size0 / 1e6, 2), blend_mb_after=round(os.path.getsize(blend) / 1e6, 2),
                seconds=round(wall, 2), peak_python_mb=round(peak, 1), process_peak_rss_mb=round(rss_mb()),
                max_error_mm=round(err_mm, 5), tolerance_mm=res.tolerance_mm, note=res.note)


def units_check(bpy, frames):
    """Keys for one correction at object scale 0.01, 1, 100 (scene Unit Scale matching): old vs new."""
    from facelab_addon.core.geometry.compress import compress
    from facelab_addon.names import PROPAGATE_PREFIX
    from facelab_addon.pipeline.correctives import write_corrective_keys

    out = []
    for units in (0.01, 1.0, 100.0):
        scene, obj = grid(bpy, n=60)
        scene.unit_settings.scale_length = 1.0 / units
        obj.scale = (units,) * 3
        co = np.array([v.co[:] for v in obj.data.vertices])
        rng = np.random.default_rng(7)
        B = fields(co, 10, 7).astype(np.float64)
        W = rng.normal(0, 1, (len(frames), 10)) * 0.5 ** np.arange(10)
        D = np.einsum("tr,rvc->tvc", W, B)
        old = compress(D, metres_per_unit=scene.unit_settings.scale_length)[0].shape[0]
        new = len(write_corrective_keys(obj, PROPAGATE_PREFIX, D, frames, scene=scene))
        out.append(dict(object_scale=units, unit_scale=1.0 / units, keys_before=old, keys_after=new))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=1000)
    args = ap.parse_args(argv)
    out_fd = os.dup(1)
    os.dup2(2, 1)  # Blender's own output (``Info: Saved ...``) goes to stderr; the JSON to stdout
    import bpy

    T = args.frames
    frames = np.arange(1, T + 1)
    rng = np.random.default_rng(0)
    k = 6
    W = np.sin(np.outer(frames, rng.uniform(0.02, 0.2, k)) + rng.uniform(0, 3, k)).astype(np.float32)

    def low(co, i, j):
        B = fields(co, k, 1)
        noise = np.random.default_rng(i).normal(0, 1e-7, (j - i, len(co), 3)).astype(np.float32)
        return np.einsum("tr,rvc->tvc", W[i:j], B) + noise

    def dense(co, i, j):
        out = np.empty((j - i, len(co), 3), np.float32)
        for t in range(i, j):
            out[t - i] = fields(co, 1, 1000 + t)[0]
        return out

    cases = [run_case(bpy, "low_rank", frames, low),
             run_case(bpy, "low_rank_product", frames, low, lowrank=lambda co: (fields(co, k, 1), W)),
             run_case(bpy, "full_rank", frames, dense)]
    out = dict(benchmark="storage", machine=dict(platform=platform.platform(), cpus=os.cpu_count(),
                                                 load=os.getloadavg()[0], python=sys.version.split()[0],
                                                 blender=bpy.app.version_string),
               cases=cases, units=units_check(bpy, frames[:30]))
    sys.stdout.flush()
    os.write(out_fd, (json.dumps(out, indent=1) + "\n").encode())


if __name__ == "__main__":
    main()
