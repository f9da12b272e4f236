"""The artist's loop, driven headless through the pipeline functions the operators call: sketch the truth's
inner-lip silhouettes on a few frames and Refine Lips, Propagate, sketch and Refine the frames FaceLab suggests,
Propagate again, and so on.

:class:`LoopFace` is a face scene with its known truth (the shipped sample, :func:`sample_face`, or a route
scene of ``testing.route``, :func:`route_face`); :func:`run_loop` walks the loop and measures each round
(held-out inner-lip RMS, the worst frame, frames worse than their capture, how far each training frame has
moved from what Refine gave it). ``benchmarks/artist_loop.py`` and ``tests/blender/test_artist_loop.py`` use it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["LoopFace", "sample_face", "route_face", "refine_frame", "run_loop", "shown_frames", "pick_next",
           "save_and_reload"]

#: A held-out frame is "worse than its capture" when its inner-lip RMS exceeds the capture's by more than this (mm).
WORSE_MM = 0.01


@dataclass
class LoopFace:
    """A face scene with a known truth, ready for the loop (regions made).

    Attributes
    ----------
    name : str
    scene, obj
        The Blender scene and face object.
    frames : (T,) int
    truth, capture : (T,V,3) float64
        Object-local evaluated truth and capture, scene units.
    lips : (V,) bool
        The vertices whose error is measured (the inner lips).
    mm_per_unit : float
    sketch : callable(scene, frame) -> Grease Pencil object or None
        Draws the truth's silhouettes on the frame (None where an artist could not draw them).
    first : list of int
        The frames sketched before the first Propagate.
    """

    name: str
    scene: object
    obj: object
    frames: np.ndarray
    truth: np.ndarray
    capture: np.ndarray
    lips: np.ndarray
    mm_per_unit: float
    sketch: object
    first: list = field(default_factory=list)

    def errors(self, X) -> np.ndarray:
        """(T,) inner-lip RMS (mm) of frames ``X`` (T,V,3) against the truth."""
        d = np.linalg.norm(np.asarray(X, np.float64) - self.truth, axis=2)[:, self.lips]
        return np.sqrt(np.mean(d * d, axis=1)) * self.mm_per_unit


def shown_frames(face: LoopFace, frames=None) -> np.ndarray:
    """(T,V,3) float64 the face as the viewport shows it on ``frames`` (default all), object-local."""
    from ..blender import caches

    f = face.frames if frames is None else frames
    return caches.evaluate_frames(face.obj, list(f), mute_shape_keys_prefix=()).astype(np.float64)


def _drawable(upper, lower, tol_px=2.0) -> bool:
    """Whether an artist would draw these truth contours as they are: the upper above the lower one."""
    from ..core.geometry.polyline import y_at  # the same reading as Refine's

    if len(upper) < 2 or len(lower) < 2:
        return False
    ly = y_at(upper[:, 0], lower)
    ok = np.isfinite(ly)
    return bool(ok.any()) and bool((ly[ok] >= upper[ok, 1] - tol_px).all())


def sample_face(first=(11, 37, 44)) -> LoopFace:
    """The shipped sample in a new scene (Load Sample), Auto Regions run; ``first``: the README's frames."""
    import bpy

    from ..blender.camera import camera_from_blender
    from ..blender.sample import read_sample
    from ..blender.strokes import new_lip_sketch, write_stroke_pixels
    from ..core.capture.camera import Camera
    from ..core.lips.mouth import find_mouth
    from ..pipeline.regions import RegionSettings, auto_regions
    from ..pipeline.sample import SampleSettings, load_sample
    from . import synthetic as syn

    data = read_sample()
    r = load_sample(SampleSettings(plate=False))
    scene, obj = r.scene, r.face
    scene.facelab.face = obj
    bpy.context.window.scene = scene
    bpy.context.view_layer.objects.active = obj
    auto_regions(obj, RegionSettings())
    pv, po = data.poly_verts, data.poly_offsets
    F = np.array([[pv[s], pv[s + k], pv[s + k + 1]] for s, e in zip(po[:-1], po[1:]) for k in range(1, e - s - 1)])
    truth = data.truth().astype(np.float64)
    mouth = find_mouth(data.vertices, F, None, near=data.vertices[data.inner_lip_loop].mean(0),
                       units_per_mm=0.001)
    cam = Camera(data.camera.K, data.camera.R, data.camera.t, data.camera.width, data.camera.height)
    frames = np.asarray(data.frames)

    def sketch(scene, f):
        try:
            upper, lower = syn.lip_contours(truth[int(f) - frames[0]], F, cam, mouth=mouth)
        except Exception:
            return None
        if not _drawable(upper, lower):
            return None
        scene.frame_set(int(f))
        gp = new_lip_sketch(scene, scene.camera)
        scene.facelab.sketch = gp
        bcam = camera_from_blender(scene)
        write_stroke_pixels(gp, "Upper lip", int(f), [upper], bcam)
        write_stroke_pixels(gp, "Lower lip", int(f), [lower], bcam)
        return gp

    lips = np.linalg.norm(data.capture_error, axis=1) > 2e-4  # where the capture is off by more than 0.2 mm
    return LoopFace("sample", scene, obj, frames, truth, data.captured().astype(np.float64), lips, 1e3, sketch,
                    list(first))


def route_face(face, name: str, frames=None, first=None) -> LoopFace:
    """A route scene of ``testing.route`` (metres, at rest, one frontal view) of ``face`` (ICT or remeshed),
    Auto Regions run; ``first``: default three frames spread over the shot."""
    import bpy

    from ..blender import caches
    from ..pipeline.regions import RegionSettings, auto_regions
    from .route import build_route_scene, sketch_truth

    frames = np.arange(1, 41) if frames is None else np.asarray(frames)
    rs = build_route_scene(face, units="m", armature=True, pose=False, frames=frames)
    scene, obj = rs.scene, rs.obj
    scene.facelab.face = obj
    bpy.context.view_layer.objects.active = obj
    auto_regions(obj, RegionSettings())
    capture = caches.evaluate_frames(obj, list(frames)).astype(np.float64)
    truth = rs.evaluated_truth(frames)

    def sketch(scene, f):
        gp, up, lo = sketch_truth(rs, int(f), rs.cameras[0])
        if len(up) < 2 or len(lo) < 2:
            return None
        scene.facelab.sketch = gp
        return gp

    if first is None:
        first = [int(frames[i]) for i in np.linspace(0, len(frames) - 1, 5).round().astype(int)[1:4]]
    return LoopFace(name, scene, obj, frames, truth, capture, rs.inner_lips, rs.mm_per_unit, sketch, list(first))


def refine_frame(face: LoopFace, f: int, settings=None):
    """Sketch the truth on ``f`` and Refine Lips (the pipeline call the operator makes); the shape the frame
    shows right after (V,3), or None where the truth cannot be drawn."""
    from ..pipeline.refine import RefineSettings, refine

    gp = face.sketch(face.scene, f)
    if gp is None:
        return None
    face.scene.frame_set(int(f))
    refine(face.scene, face.obj, int(f), settings or RefineSettings(), sketch=gp)
    return shown_frames(face, [f])[0]


def pick_next(strategy: str, result, frames, train, count: int) -> list:
    """Candidate frames to correct next, best first: ``"facelab"`` (Propagate's suggestions, then the most
    extrapolated), ``"worse"`` (the frames Propagate expects worse than their capture first, then as
    ``"facelab"``), ``"extrapolated"`` (the highest extrapolation score) or ``"even"`` (farthest in time from the
    training frames)."""
    frames = np.asarray(frames)
    free = [int(f) for f in frames if f not in set(train)]
    score = dict(zip(frames.tolist(), np.asarray(result.extrapolation, np.float64).tolist()))
    by_score = sorted(free, key=lambda f: -score[f])
    if strategy == "facelab":
        out = [f for f in result.suggested if f in free]
        return out + [f for f in by_score if f not in out]
    if strategy == "worse":  # the frames expected worse than their capture first, then Propagate's suggestions
        out = [f for f in result.expected_worse if f in free]
        out += [f for f in result.suggested if f in free and f not in out]
        return out + [f for f in by_score if f not in out]
    if strategy == "extrapolated":
        return by_score
    if strategy == "even":
        picked, out = list(train), []
        rest = list(free)
        while rest:
            f = max(rest, key=lambda g: (min(abs(g - t) for t in picked), -g))
            out.append(f)
            picked.append(f)
            rest.remove(f)
        return out
    raise ValueError(f"unknown strategy {strategy!r}")


def _round_stats(face, X, train, refined, held, named=()):
    e, e0 = face.errors(X), face.errors(face.capture)
    idx = np.searchsorted(face.frames, held)
    worse = [int(face.frames[i]) for i in idx if e[i] > e0[i] + WORSE_MM]
    named = [int(f) for f in named if f in set(held.tolist())]
    drift = {int(f): float(np.linalg.norm(X[np.searchsorted(face.frames, f)] - s, axis=1).max() * face.mm_per_unit)
             for f, s in refined.items()}
    w = int(idx[np.argmax(e[idx])])
    return dict(training=sorted(int(f) for f in train), held_out_rms_mm=float(np.sqrt(np.mean(e[idx] ** 2))),
                worst_frame=int(face.frames[w]), worst_mm=float(e[w]), worse_than_capture=worse,
                max_training_drift_mm=max(drift.values()) if drift else 0.0, drift_mm=drift,
                expected_worse=named, worse_not_named=[f for f in worse if f not in named])


def run_loop(face: LoopFace, *, settings=None, per_round: int = 3, total: int = 12, strategy: str = "facelab",
             between=None, plan=None):
    """Walk the loop on ``face``: Refine ``face.first``, then rounds of Propagate and Refine the next ``per_round``
    frames (``strategy``, see :func:`pick_next`) until ``total`` frames are training frames, and a last Propagate.

    ``between(face)``: called after each Propagate but the last (a save and reload; it may return a new
    ``LoopFace`` to continue with). ``plan``: a list of training sets per round to refine instead of choosing
    (a replay). Returns ``{"rounds": [round stats...], "order": [[frames refined per round]...],
    "result": the last PropagateResult}``; the round stats are measured on the frames never refined
    (held-out), ``drift_mm`` per training frame from its shape right after its Refine.
    """
    from ..pipeline.propagate import PropagateSettings, propagate

    settings = settings or PropagateSettings()
    train, refined, order, snaps, results = [], {}, [], [], []

    def refine_some(cands, n):
        done = []
        for f in cands:
            if len(done) == n:
                break
            if f in train:
                continue
            s = refine_frame(face, f)
            if s is not None:
                train.append(int(f))
                refined[int(f)] = s
                done.append(int(f))
        return done

    order.append(refine_some(plan[0] if plan else face.first, len(plan[0]) if plan else len(face.first)))
    rnd = 0
    while True:
        rnd += 1
        r = propagate(face.scene, face.obj, face.frames, settings)
        results.append(r)
        snaps.append((shown_frames(face), list(train), dict(refined), list(getattr(r, "expected_worse", []))))
        if len(train) >= total or (plan is not None and rnd >= len(plan)):
            break
        if between is not None:
            face = between(face) or face
        if plan is not None:
            cands, n = plan[rnd], len(plan[rnd])
        else:
            cands, n = pick_next(strategy, r, face.frames, train, per_round), min(per_round, total - len(train))
        got = refine_some(cands, n)
        if not got:
            break
        order.append(got)
    held = np.setdiff1d(face.frames, train)
    rounds = [_round_stats(face, X, t, ref, held, named) for X, t, ref, named in snaps]
    return dict(rounds=rounds, order=order, result=results[-1], face=face)


def save_and_reload(path):
    """A ``between`` for :func:`run_loop`: save the .blend to ``path``, open it again and continue on the reloaded
    scene and face (the sample's sketches follow the scene)."""
    import dataclasses

    import bpy

    def between(face):
        name = face.scene.name
        bpy.ops.wm.save_as_mainfile(filepath=str(path))
        bpy.ops.wm.open_mainfile(filepath=str(path))
        scene = bpy.data.scenes[name]
        bpy.context.window.scene = scene
        obj = scene.facelab.face
        bpy.context.view_layer.objects.active = obj
        return dataclasses.replace(face, scene=scene, obj=obj)

    return between
