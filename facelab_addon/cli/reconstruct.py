"""Reconstruct from Bundles (Cong, Lan & Fedkiw, local geometric indexing), like the sidebar's
section 4: rebuild the face on every frame from animated 3D bundles (the selected empties or a
``FL_bundles`` collection) and the face's own shape keys; the result is a few corrective keys
``FL_Recon_*`` keyed on every frame.

    python -m facelab_addon reconstruct SHOT.blend --object Face --frames 1-300 --out SHOT_recon.blend
"""

from __future__ import annotations

from ..names import BUNDLES_COLLECTION
from ._errors import CliError
from ._frames import contiguous, parse_frames

HELP = "rebuild the face from animated 3D bundles (corrective shape keys)"
INPUTS = ("blend",)


def add_arguments(p) -> None:
    p.add_argument("--bind-frame", type=int, default=-1, metavar="F",
                   help="frame where the face is neutral (bundles are bound there); default: the first frame")
    p.add_argument("--smooth", type=int, default=1, metavar="N",
                   help="moving average of the barycentric weights over N frames (1 = off)")
    p.add_argument("--bundles", metavar="COLLECTION",
                   help=f"collection holding the bundle empties (default: '{BUNDLES_COLLECTION}', else the selected "
                        "empties)")


def run(args, session) -> dict:
    import time

    from ..pipeline.reconstruct import reconstruct_from_bundles
    from ..pipeline.shot_settings import reconstruct_settings
    from .solve import progress

    bpy = session.bpy
    scene = session.scene
    obj = session.face()
    frames = parse_frames(args.frames, scene)
    f0, f1 = contiguous(frames, "reconstruct")
    if args.bundles:
        coll = bpy.data.collections.get(args.bundles)
        if coll is None:
            raise CliError(f"--bundles {args.bundles!r}: no such collection.")
        for o in scene.objects:
            o.select_set(False)
        for o in coll.all_objects:
            if bpy.context.view_layer.objects.get(o.name) is not None:
                o.select_set(True)
        bpy.context.view_layer.objects.active = obj
    session.log(f"reconstructing frames {f0}-{f1} ({len(frames):,})")
    settings = reconstruct_settings(scene, bpy.context.selected_objects, frame_start=f0, frame_end=f1,
                                    bind_frame=args.bind_frame, smooth=max(1, args.smooth))
    t0 = time.perf_counter()
    with progress(session, len(frames), "reconstruct") as prog:
        r = reconstruct_from_bundles(scene, obj, settings, progress=prog)
    dt = time.perf_counter() - t0
    keys = r.keys
    session.log(f"Reconstructed {len(frames):,} frames in {dt:.1f} s, {len(keys)} corrective shapes")
    if r.skipped:
        session.log(f"note: skipped {len(r.skipped)} frames with missing bundles (shown neutral): {r.skipped[:10]} "
                    f"({r.missing})")
    if r.live_keys:
        session.log(f"note: dataset keys {r.live_keys[:5]} are not zero and add on top")
    return {
        "object": obj.name,
        "frames": [f0, f1],
        "frame_count": len(frames),
        "corrective_keys": keys,
        "reconstruct_seconds": round(dt, 3),
        "saved": session.save(args.out),
    }
