"""Retarget the solved performance to a creature (Bhat et al. 2013 §5.1), like the sidebar's
Retarget: the face's rig is carried to the creature by deformation transfer (creature keys with
the rig's names, created when missing), the keyed weights are copied, the actor's correctives
become ``FL_Retarget_*`` keys, and the lip-sync heuristic keeps a wider mouth lip-readable.

Run it on a solved .blend (``solve`` first: it keys the rig's weights).

    python -m facelab_addon retarget SHOT_solved.blend --object Face --creature Creature --out SHOT_creature.blend
    python -m facelab_addon retarget SHOT_solved.blend --object Face --creature Troll --no-lip-sync --frames 1-120
"""

from __future__ import annotations

import time

from ._errors import EXIT_FAILED, EXIT_OBJECT, EXIT_USAGE, CliError
from .solve import progress, set_range

HELP = "carry the solved performance to a creature mesh (shape keys, weights, correctives, lip sync)"
INPUTS = ("blend",)


def add_arguments(p) -> None:
    import argparse

    p.add_argument("--creature", metavar="NAME",
                   help="the creature mesh (default: FaceLab > Retarget > Creature of the scene)")
    p.add_argument("--lip-sync", action=argparse.BooleanOptionalAction, default=None,
                   help="seal the creature's lip corners so its talking portion is as long as the actor's lips "
                        "(default: the scene's Lip Sync setting, on unless changed)")
    p.add_argument("--threshold", type=float, default=None, metavar="MM",
                   help="lip sync: extra talking length allowed before the corners are sealed, in millimetres "
                        "(default: the scene's setting)")
    p.add_argument("--correspondence", choices=("auto", "topology", "markers"), default=None,
                   help="how creature points match the actor's: same topology, Creature Markers empties, or auto "
                        "(default: the scene's setting)")
    p.add_argument("--creature-markers", metavar="COLLECTION",
                   help="collection of empties on the creature named like the actor's bound tracks "
                        "(for --correspondence markers)")


def _mesh(session, name, what):
    bpy = session.bpy
    meshes = [o.name for o in session.scene.objects if o.type == "MESH"]
    obj = bpy.data.objects.get(name)
    if obj is None:
        raise CliError(f"{what} {name!r}: no such object; meshes in the scene: {meshes[:20]}.", EXIT_OBJECT)
    if obj.type != "MESH":
        raise CliError(f"{what} {name!r} is a {obj.type.lower()}, not a mesh; give the creature mesh "
                       f"({meshes[:20]}).", EXIT_OBJECT)
    return obj


def run(args, session) -> dict:
    import numpy as np

    from ..blender.actions import animated_keys
    from ..blender.rig import rig_shapes
    from ..core.errors import FaceLabError
    from ..pipeline.retarget import retarget
    from ..pipeline.shot_settings import retarget_settings

    bpy = session.bpy
    scene = session.scene
    s = scene.facelab_solve
    obj = session.face()
    if args.creature:
        cre = _mesh(session, args.creature, "--creature")
    elif s.creature is not None:
        cre = s.creature
    else:
        raise CliError("Which mesh is the creature? Give --creature NAME (or set FaceLab > Retarget > Creature).",
                       EXIT_OBJECT)
    if cre == obj:
        raise CliError(f"--creature {cre.name!r} is the face itself; give the creature mesh.", EXIT_USAGE)
    try:
        names, _, _ = rig_shapes(obj)
    except FaceLabError as e:
        raise CliError(str(e), EXIT_FAILED) from None
    if not animated_keys(obj.data.shape_keys, names):
        raise CliError(f"'{obj.name}' has no solved performance: none of its {len(names)} rig keys is animated. "
                       "Run 'python -m facelab_addon solve' on the shot first (or key the weights).", EXIT_FAILED)
    frames = set_range(session, args, "retarget")
    s.creature = cre
    if args.lip_sync is not None:
        s.lip_sync = args.lip_sync
    if args.threshold is not None:
        if not args.threshold >= 0:
            raise CliError(f"--threshold {args.threshold}: give a distance >= 0 in millimetres.", EXIT_USAGE)
        s.lip_threshold = args.threshold * 1e-3 / (scene.unit_settings.scale_length or 1.0)
    if args.correspondence:
        s.correspondence = args.correspondence.upper()
    if args.creature_markers:
        coll = bpy.data.collections.get(args.creature_markers)
        if coll is None:
            raise CliError(f"--creature-markers {args.creature_markers!r}: no such collection.", EXIT_OBJECT)
        s.creature_markers = coll
    session.log(f"retargeting '{obj.name}' -> '{cre.name}', frames {frames[0]}-{frames[-1]} ({len(frames):,}), "
                f"lip sync {'on' if s.lip_sync else 'off'}")
    t0 = time.perf_counter()
    with progress(session, len(frames), "retarget") as prog:
        r = retarget(scene, obj, cre, retarget_settings(scene), progress=prog)
    dt = time.perf_counter() - t0
    res = r.core
    ck = cre.data.shape_keys
    msg = (f"Retargeted {len(frames):,} frames to '{cre.name}' in {dt:.1f} s ({r.correspondence}): "
           f"{len(r.created)} shape keys transferred, {len(r.keys)} corrective shapes")
    session.log(msg)
    if r.action_note:
        session.log(f"note: {r.action_note}")
    eps = res.end_points
    lip = None
    if s.lip_sync and eps:
        up = np.array([e.upper for e in eps])
        lo = np.array([e.lower for e in eps])
        sealed = [int(f) for f, u, l in zip(frames, up, lo)
                  if u[0] > 1e-6 or u[1] < 1 - 1e-6 or l[0] > 1e-6 or l[1] < 1 - 1e-6]
        lip = {"custom_end_points": bool(s.use_end_points),
               "upper_mean": [round(float(x), 4) for x in up.mean(0)],
               "lower_mean": [round(float(x), 4) for x in lo.mean(0)],
               "frames_sealed": len(sealed)}
    unit_mm = 1e3 * (scene.unit_settings.scale_length or 1.0)
    return {
        "object": obj.name,
        "creature": cre.name,
        "frames": [int(frames[0]), int(frames[-1])],
        "frame_count": len(frames),
        "correspondence": r.correspondence,
        "lip_sync": bool(s.lip_sync),
        "threshold_mm": round(s.lip_threshold * unit_mm, 4),
        "lip_sync_end_points": lip,
        "shape_keys_created": r.created,
        "shape_keys_kept": r.kept,
        "corrective_keys": r.keys,
        "action": ck.animation_data.action.name if ck.animation_data and ck.animation_data.action else None,
        "notes": [r.action_note] if r.action_note else [],
        "timings": {"retarget_seconds": round(dt, 3),
                    **{f"{k}": round(float(v), 3) for k, v in (res.info or {}).items()
                       if isinstance(v, (int, float)) and k.endswith("_s")}},
        "saved": session.save(args.out),
    }
