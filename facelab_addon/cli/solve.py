"""Solve Performance from markers (Bhat et al. 2013 §4), like the sidebar's Solve from Markers:
the scene's views (FaceLab > Solve > Views: camera + Movie Clip, optional Mask / Grease Pencil
contours) drive the face's shape-key rig; the weights are keyed as ordinary F-curves and the
per-frame corrective becomes a few ``FL_Solve_*`` keys. Bind Tracks runs first when the face has
no bindings (or with ``--rebind``, or a ``--bind-frame`` other than the stored one).

    python -m facelab_addon solve SHOT.blend --object Face --frames 1-120 --out SHOT_solved.blend
    python -m facelab_addon solve SHOT.blend --object Face --bind-frame 1 --rebind --no-corrective --json s.json
"""

from __future__ import annotations

import contextlib
import math
import time

from ..names import SOLVE_PREFIX
from ._errors import EXIT_FAILED, CliError
from ._frames import contiguous, parse_frames
from ._stdout import quiet_stdout

HELP = "solve shape-key weights (+ correctives) from the tracked markers of the scene's views"
INPUTS = ("blend",)


def add_arguments(p) -> None:
    p.add_argument("--bind-frame", type=int, default=None, metavar="F",
                   help="frame where the face matches the footage, for Bind Tracks (default: FaceLab > Solve > "
                        "Bind Frame, else the first frame of --frames); giving one other than the face's stored "
                        "bind frame rebinds")
    p.add_argument("--rebind", action="store_true",
                   help="run Bind Tracks even if the face already has bindings")
    p.add_argument("--no-corrective", action="store_true",
                   help=f"weights only: no out-of-subspace corrective ({SOLVE_PREFIX}* keys)")
    p.add_argument("--no-contours", action="store_true",
                   help="ignore the views' Mask / Grease Pencil / annotation contours (markers and bundles only)")
    p.add_argument("--brief", action="store_true",
                   help="leave the per-frame weights and reprojection errors out of the JSON summary")


# --------------------------------------------------------------------------- shared with retarget.py
@contextlib.contextmanager
def progress(session, total: int, label: str):
    """A ``progress(done, n=total)`` callback for the pipelines (``done`` frames finished): a
    ``label: done/n (p %)`` line about every 10 %, in the CLI's one format; Blender's own output
    meanwhile stays off stdout (which carries the JSON)."""
    step = session.progress(label, total)
    with quiet_stdout():
        yield lambda done, n=total: step(done - 1, n)


def set_range(session, args, what: str):
    """``--frames`` -> FaceLab > Solve > Start/End (the range the pipelines read); returns the frames array."""
    from ..core.errors import FaceLabError
    from ..pipeline.frames import frame_range

    scene = session.scene
    s = scene.facelab_solve
    if args.frames:
        f0, f1 = contiguous(parse_frames(args.frames, scene), what)
        s.frame_start, s.frame_end = f0, f1
    try:
        return frame_range(scene, s.frame_start, s.frame_end)
    except FaceLabError as e:
        raise CliError(str(e), EXIT_FAILED) from None


def check_views(session) -> list:
    """Every view has a camera, a clip and a readable calibration; returns their descriptions."""
    from ..blender import tracking
    from ..core.errors import FaceLabError
    from ..pipeline.shot_settings import scene_views
    from ..pipeline.solve import require_views

    scene = session.scene
    try:
        views = require_views(scene_views(scene))
    except FaceLabError as e:
        raise CliError(f"{e} Save the .blend with its views set up, then run the command again.", EXIT_FAILED) \
            from None
    out = []
    for v in views:
        try:
            cam, warnings = tracking.clip_camera(scene, v.camera, v.clip)
        except FaceLabError as e:
            raise CliError(str(e), EXIT_FAILED) from None
        out.append({"camera": v.camera.name, "clip": v.clip.name, "mask": v.mask.name if v.mask else None,
                    "sketch": v.sketch.name if v.sketch else None, "size": [int(cam.width), int(cam.height)],
                    "focal_px": round(float(cam.K[0, 0]), 3), "tracks": len(v.clip.tracking.tracks),
                    "warnings": list(warnings)})
    return out


def _stats(values, frames):
    vals = [(f, v) for f, v in zip(frames, values) if v is not None and math.isfinite(v)]
    if not vals:
        return None
    worst = max(vals, key=lambda x: x[1])
    return {"mean": round(sum(v for _, v in vals) / len(vals), 4), "max": round(worst[1], 4), "max_frame": worst[0]}


# --------------------------------------------------------------------------- the command
def bind(session, args, obj, frames) -> dict:
    """Bind Tracks when needed; returns the bind part of the summary."""
    from ..pipeline.shot_settings import bind_settings
    from ..pipeline.solve import bind_tracks

    scene = session.scene
    s = scene.facelab_solve
    have = len(obj.facelab_solve.bindings)
    stored = obj.facelab_solve.bind_frame
    if args.bind_frame is not None:
        frame = args.bind_frame
    elif s.bind_frame >= 0:
        frame = s.bind_frame
    else:
        frame = int(frames[0])
    if not have:
        why = "the face had no bindings"
    elif args.rebind:
        why = "--rebind"
    elif args.bind_frame is not None and args.bind_frame != stored:
        why = f"--bind-frame {args.bind_frame} (the bindings were made on frame {stored})"
    else:
        session.log(f"using the {have} bindings of '{obj.name}' made on frame {stored} (--rebind to bind again)")
        return {"performed": False, "frame": stored, "bindings": have}
    session.log(f"binding tracks on frame {frame} ({why})")
    with quiet_stdout():
        r = bind_tracks(scene, obj, frame, bind_settings(scene))
    info = {"performed": True, "why": why, "frame": frame, "bound": len(r.bound), "bundles": r.bundles,
            "untracked": r.untracked, "missed": r.missed, "disagree": r.disagree,
            "max_disagreement_px": round(r.max_err_px, 4), "warnings": r.warnings, "seconds": round(r.time_s, 3)}
    n_all = info["bound"] + len(info["missed"]) + len(info["untracked"])
    if not (info["bound"] or info["bundles"]):
        raise CliError(
            f"Bind Tracks bound none of the {n_all} tracks to '{obj.name}' on frame {frame} "
            f"({len(info['untracked'])} have no marker there, {len(info['missed'])} rays missed the face): give "
            "--bind-frame F, a frame where the tracks are tracked and the mesh matches the footage (the neutral "
            "pose is usual).", EXIT_FAILED)
    session.log(f"bound {info['bound']} of {n_all} tracks in {r.time_s:.1f} s"
                + (f", {info['bundles']} bundles" if info["bundles"] else "")
                + (f"; views disagree on {', '.join(info['disagree'][:6])}" if info["disagree"] else ""))
    return info


def run(args, session) -> dict:
    import numpy as np

    from ..blender.actions import curve_values
    from ..blender.rig import rig_shapes
    from ..core.errors import FaceLabError
    from ..pipeline.shot_settings import solve_settings
    from ..pipeline.solve import solve_performance, summarise_skips

    scene = session.scene
    s = scene.facelab_solve
    obj = session.face()
    try:
        names, _, _ = rig_shapes(obj)
    except FaceLabError as e:
        raise CliError(str(e), EXIT_FAILED) from None
    frames = set_range(session, args, "solve")
    views = check_views(session)
    if args.no_corrective:
        s.use_corrective = False
    if args.no_contours:
        s.use_contours = False
    session.log(f"'{obj.name}': {len(names)} rig keys, {len(views)} views "
                f"({', '.join(v['camera'] + '/' + v['clip'] for v in views)})")
    bind_info = bind(session, args, obj, frames)

    session.log(f"solving frames {frames[0]}-{frames[-1]} ({len(frames):,})")
    t0 = time.perf_counter()
    with progress(session, len(frames), "solve") as prog:
        r = solve_performance(scene, obj, solve_settings(scene), progress=prog)
    dt = time.perf_counter() - t0
    solved = [int(f) for f in r.solved]
    skipped = {int(f): str(why) for f, why in r.skipped.items()}
    key = obj.data.shape_keys
    corrective = [kb.name for kb in key.key_blocks if kb.name.startswith(SOLVE_PREFIX)]
    # what was keyed, read back from the F-curves
    W = curve_values(key, names, solved) if solved else np.zeros((0, len(names)))
    per_frame = r.core.info.get("frames", [])
    m_rms = [fi.get("marker_rms_px") if fi else None for fi in per_frame]
    c_rms = [fi.get("contour_rms_px") if fi else None for fi in per_frame]
    fr = [int(f) for f in r.frames]
    msg = f"Solved {len(solved):,} frames in {dt:.1f} s"
    if skipped:
        msg += f" ({summarise_skips(skipped)})"
    if s.use_corrective:
        msg += f", {len(corrective)} corrective shapes"
    session.log(msg)
    for n in [r.action_note] + list(r.notes):
        if n:
            session.log(f"note: {n}")
    out = {
        "object": obj.name,
        "frames": [int(frames[0]), int(frames[-1])],
        "frame_count": len(frames),
        "views": views,
        "bind": bind_info,
        "frames_solved": len(solved),
        "skipped": {str(f): why for f, why in skipped.items()},
        "markers_missing": {str(f): n for f, n in r.missing.items()},
        "rig_keys": names,
        "action": key.animation_data.action.name if key.animation_data and key.animation_data.action else None,
        "weight_range": {n: [round(float(W[:, k].min()), 5) + 0.0, round(float(W[:, k].max()), 5) + 0.0]
                         for k, n in enumerate(names)} if len(solved) else {},
        "corrective": bool(s.use_corrective),
        "corrective_keys": corrective,
        "contours": bool(s.use_contours and r.curve_stats and r.curve_stats.get("frames_with_curves")),
        "markers_bound": r.n_markers,
        "reprojection": {
            "what": "RMS pixel distance of the rig fit (weights, before the corrective) to the markers / contours",
            "marker_rms_px": _stats(m_rms, fr),
            "contour_rms_px": _stats(c_rms, fr),
        },
        "timings": {"solve_seconds": round(dt, 3), "gather_seconds": round(r.gather_s, 3),
                    "fit_seconds": round(r.fit_s, 3), "ms_per_frame": round(1000 * r.fit_s / max(len(solved), 1), 2)},
        "notes": [n for n in [r.action_note] + list(r.notes) if n],
    }
    if bind_info.get("performed"):
        out["timings"]["bind_seconds"] = bind_info["seconds"]
    if not args.brief:
        out["weights"] = {"frames": solved,
                          "values": {n: [round(float(x), 6) + 0.0 for x in W[:, k]] for k, n in enumerate(names)}}
        out["reprojection"]["per_frame"] = {
            str(f): {"marker_rms_px": _round(m), "contour_rms_px": _round(c)}
            for f, m, c in zip(fr, m_rms, c_rms) if f in set(solved)}
    out["saved"] = session.save(args.out)
    return out


def _round(x, nd=4):
    return None if x is None or not math.isfinite(x) else round(float(x), nd)
