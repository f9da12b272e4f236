"""Regenerate the shipped sample shot ``assets/sample/`` from the ICT-FaceKit checkout.

    python scripts/make_sample.py                # face.npz + 48 plate frames (Cycles CPU, a few minutes)
    python scripts/make_sample.py --no-render    # face.npz only (keeps the plate frames)
    python scripts/make_sample.py --figure docs/images/sample_shot.png   # the README's picture of it

What it writes (read by ``facelab_addon.blender.sample``; Load Sample builds the scene from it):

* ``face.npz`` -- the ICT-FaceKit ``M_Face`` part (the skin of the face, mouth and eye openings are
  holes), un-subdivided once with Blender's Decimate modifier (*Un-Subdivide*: every kept vertex is
  an upstream vertex, at its upstream position, so the expressions carry over exactly): about 4,700
  vertices, in metres. A 48-frame performance of 8 mouth expressions (``testing.weights.
  rectified_sine_weights``, seed 7), and the capture's error: the inner lips fail to close by up to
  2.5 mm, more when the jaw is closed (as in the propagate demo). The camera: 1280x720, 50 mm lens on
  a 36 mm sensor, 45 cm in front of the mouth.
* ``plate/plate_0001.jpg`` ... -- the truth (performance without the capture error) rendered with
  Cycles on the CPU from that camera, JPEG quality 85.
* ``LICENSE-ICT-FaceKit.txt`` -- the upstream MIT licence (the sample is a reduced copy of its face).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
OUT = ROOT / "assets" / "sample"

EXPR = ["jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthSmile_L", "mouthSmile_R", "mouthPress_L",
        "mouthPress_R"]
N_FRAMES = 48
FPS = 24
SCALE = 0.01  # ICT centimetres -> metres
UNITS_PER_MM = 0.001
GAP_MM = 2.5
IMAGE = (1280, 720)
DISTANCE = 0.45
SAMPLES = 12


def reduced_face(ict):
    """The M_Face polygons un-subdivided once: (kept upstream vertex ids (V,), poly_verts, poly_offsets)."""
    import bpy
    from scipy.spatial import cKDTree

    from facelab_addon.blender.scene import new_mesh_object

    part = ict.parts.index("M_Face")
    off = ict.poly_offsets
    polys = [ict.poly_verts[off[p]:off[p + 1]] for p in np.flatnonzero(ict.poly_part == part)]
    used = np.unique(np.concatenate(polys))
    remap = np.full(len(ict.neutral), -1)
    remap[used] = np.arange(len(used))
    pv = np.concatenate([remap[p] for p in polys])
    po = np.r_[0, np.cumsum([len(p) for p in polys])]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ob = new_mesh_object("M_Face", ict.neutral[used], poly_verts=pv, poly_offsets=po)
    md = ob.modifiers.new("Un-Subdivide", "DECIMATE")
    md.decimate_type, md.iterations = "UNSUBDIV", 1
    me = ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    n = len(me.vertices)
    co = np.empty(n * 3, np.float32)
    me.vertices.foreach_get("co", co)
    dist, idx = cKDTree(ict.neutral[used].astype(np.float32)).query(co.reshape(-1, 3))
    if dist.max() > 0 or len(np.unique(idx)) != n:
        raise SystemExit("Un-Subdivide moved or merged vertices; the sample needs upstream vertices.")
    loop_start = np.empty(len(me.polygons), np.int32)
    loop_total = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_start", loop_start)
    me.polygons.foreach_get("loop_total", loop_total)
    corners = np.empty(len(me.loops), np.int32)
    me.loops.foreach_get("vertex_index", corners)
    poly_verts = np.concatenate([corners[s:s + k] for s, k in zip(loop_start, loop_total)])
    poly_offsets = np.r_[0, np.cumsum(loop_total)]
    return used[idx], poly_verts, poly_offsets


def build_npz(ict) -> dict:
    from facelab_addon.core.lips.lip_loop import inner_lip_loop
    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as syn
    from facelab_addon.testing.weights import rectified_sine_weights

    keep, poly_verts, poly_offsets = reduced_face(ict)
    F = ict.faces
    neutral = ict.neutral * SCALE
    deltas = np.stack([(ict.expressions[n] - ict.neutral) * SCALE for n in EXPR])
    W = rectified_sine_weights(N_FRAMES, len(EXPR), seed=7)
    fixed = ~ict.part_vertex_mask("M_Face")
    mouth = find_mouth(neutral, F, fixed, loop=syn.ICT_MOUTH_LOOP, units_per_mm=UNITS_PER_MM)
    w, side = syn.lip_error_weights(neutral, F, fixed, mouth=mouth)
    err = np.zeros_like(neutral)
    err[:, 1] = side * w * 0.5 * GAP_MM * UNITS_PER_MM  # each lip moves half the gap
    strength = np.clip(1.0 - W[:, 0] / 0.35, 0.2, 1.0)  # worst when the jaw is closed
    cam = syn.frontal_camera(neutral, mouth.center, distance=DISTANCE, width=IMAGE[0], height=IMAGE[1])

    V = neutral[keep]
    tris = np.concatenate([[p[0], p[k], p[k + 1]] for s, e in zip(poly_offsets[:-1], poly_offsets[1:])
                           for p in [poly_verts[s:e]] for k in range(1, len(p) - 1)]).reshape(-1, 3)
    loop = inner_lip_loop(V, tris)
    return dict(
        vertices=V.astype(np.float32), poly_verts=poly_verts.astype(np.int32),
        poly_offsets=poly_offsets.astype(np.int32), expression_names=np.array(EXPR),
        expression_deltas=deltas[:, keep].astype(np.float32), weights=W.astype(np.float32),
        capture_error=err[keep].astype(np.float32), capture_error_weights=strength.astype(np.float32),
        frame_start=np.int64(1), fps=np.int64(FPS), K=cam.K, R=cam.R, t=cam.t,
        image_size=np.array(IMAGE, np.int64), inner_lip_loop=loop.astype(np.int32),
        source_vertices=keep.astype(np.int32))


def render_plate(npz: Path, plate_dir: Path, samples: int) -> None:
    """Render the truth (capture error muted) on every frame into plate_dir (JPEG), Cycles CPU, one subprocess."""
    with tempfile.TemporaryDirectory(prefix="facelab-sample-") as tmp:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--render-worker", str(npz), tmp, "--samples",
               str(samples)]
        env = dict(os.environ, BLENDER_USER_RESOURCES=tmp)
        log = Path(tmp) / "render.log"
        with open(log, "w") as fh:
            r = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=env)
        if r.returncode != 0:
            raise SystemExit(f"rendering the plate failed:\n{log.read_text()[-3000:]}")
        from PIL import Image

        if plate_dir.exists():
            shutil.rmtree(plate_dir)
        plate_dir.mkdir(parents=True)
        for png in sorted(Path(tmp).glob("plate_*.png")):
            Image.open(png).convert("RGB").save(plate_dir / (png.stem + ".jpg"), quality=85, optimize=True)


def render_worker(npz: str, out: str, samples: int) -> int:
    import bpy

    from facelab_addon.blender.sample import ERROR_KEY, build_sample, read_sample

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    data = read_sample(npz)
    objs = build_sample(scene, data)
    objs["face"].data.shape_keys.key_blocks[ERROR_KEY].mute = True  # the plate shows the truth
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    r.image_settings.file_format = "PNG"
    for f in data.frames:
        scene.frame_set(int(f))
        r.filepath = str(Path(out) / f"plate_{int(f):04d}.png")
        bpy.ops.render.render(write_still=True)
        print(f"rendered frame {f}", flush=True)
    return 0


def figure(path: Path, n: int = 3) -> None:
    """The sample as an artist sees it: plate frames with the capture's inner-lip contours (the mesh) and
    the plate's own (the truth the plate was rendered from), on the frames where the capture is worst."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from facelab_addon.core.lips.mouth import find_mouth
    from facelab_addon.testing import synthetic as syn

    with np.load(OUT / "face.npz") as z:
        a = {k: z[k] for k in z.files}
    from facelab_addon.core.capture.camera import Camera

    W, H = (int(v) for v in a["image_size"])
    cam = Camera(a["K"], a["R"], a["t"], W, H)
    V, pv, po = a["vertices"].astype(float), a["poly_verts"], a["poly_offsets"]
    F = np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])
    truth = V[None] + np.einsum("tk,kvd->tvd", a["weights"].astype(float), a["expression_deltas"].astype(float))
    captured = truth + a["capture_error_weights"][:, None, None] * a["capture_error"][None].astype(float)
    mouth = find_mouth(V, F, None, near=V[a["inner_lip_loop"]].mean(0), units_per_mm=UNITS_PER_MM)
    from facelab_addon.core.geometry.polyline import y_at

    def drawable(t):  # the plate's upper lip above its lower lip (frames where the lips overlap are skipped)
        up, low = syn.lip_contours(truth[t], F, cam, mouth=mouth)
        ly = y_at(up[:, 0], low)
        ok = np.isfinite(ly)
        return ok.any() and bool((ly[ok] >= up[ok, 1] - 2.0).all())

    bad = np.flatnonzero(a["capture_error_weights"] >= 0.8 * a["capture_error_weights"].max())
    good = [int(t) for t in bad if drawable(t)]
    frames = [good[i] for i in np.linspace(0, len(good) - 1, n).round().astype(int)]
    gap = 2 * np.abs(a["capture_error"][:, 1]).max() * a["capture_error_weights"]  # metres, both lips
    c = cam.project(V[a["inner_lip_loop"]]).mean(0)
    lo, hi = c - [150, 70], c + [150, 70]
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 2.9))
    for ax, t in zip(np.atleast_1d(axes), frames):
        ax.imshow(plt.imread(OUT / "plate" / f"plate_{t + 1:04d}.jpg"))
        for X, col, ls, lab in ((captured[t], "#ffd60a", "-", "capture (the mesh)"),
                                (truth[t], "#0a84ff", "--", "the plate's lips (what to sketch)")):
            for k, P in enumerate(syn.lip_contours(X, F, cam, mouth=mouth)):
                ax.plot(P[:, 0], P[:, 1], color=col, ls=ls, lw=1.4, label=lab if k == 0 else None)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(hi[1], lo[1])
        ax.set_title(f"frame {t + 1}: the capture's lips stay {1e3 * gap[t]:.1f} mm further apart", fontsize=10)
        ax.axis("off")
    np.atleast_1d(axes)[0].legend(loc="lower left", fontsize=8, framealpha=0.85)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    print(f"wrote {path}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--no-render", action="store_true", help="write face.npz only, keep the plate frames")
    ap.add_argument("--samples", type=int, default=SAMPLES, help="Cycles samples per plate frame")
    ap.add_argument("--figure", type=Path, default=None,
                    help="only draw the sample's figure (plate + capture vs plate lip contours) into this PNG")
    ap.add_argument("--render-worker", nargs=2, metavar=("NPZ", "OUT"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.render_worker:
        return render_worker(*a.render_worker, a.samples)
    if a.figure:
        figure(a.figure)
        return 0
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-sample-"))
    from facelab_addon.core.capture.ict import find_ict_dir, load_ict

    t0 = time.perf_counter()
    ict = load_ict(expressions=EXPR)
    OUT.mkdir(parents=True, exist_ok=True)
    arrays = build_npz(ict)
    npz = OUT / "face.npz"
    np.savez_compressed(npz, **arrays)
    shutil.copyfile(find_ict_dir() / "LICENSE", OUT / "LICENSE-ICT-FaceKit.txt")
    print(f"wrote {npz} ({npz.stat().st_size / 1e6:.2f} MB, {len(arrays['vertices'])} vertices)", flush=True)
    if not a.no_render:
        render_plate(npz, OUT / "plate", a.samples)
    total = sum(p.stat().st_size for p in OUT.rglob("*") if p.is_file())
    print(f"assets/sample: {total / 1e6:.2f} MB in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
