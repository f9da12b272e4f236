"""Refine Lips on sketched frames (Dinev et al. 2018 §5), like the sidebar's Sketch & Refine:
for every frame, the inner-lip strokes of the lip sketch (Grease Pencil 'Upper lip' / 'Lower lip'
layers, or annotations) pull the lips' silhouettes onto them; each result is a new corrective key
``FL_Refine_<frame>`` keyed on its frame and recorded as a training frame.

Needs a .blend with the face, the scene camera and the sketch.

    python -m facelab_addon refine SHOT.blend --object Face --out SHOT_refined.blend      # every sketched frame
    python -m facelab_addon refine SHOT.blend --object Face --frames 40,88 --out SHOT_refined.blend
"""

from __future__ import annotations

from ._common import CliError, parse_frames

HELP = "refine the lips on sketched frames (one corrective shape key per frame)"
INPUTS = ("blend",)


def add_arguments(p) -> None:
    p.add_argument("--sketch", metavar="NAME",
                   help="the Grease Pencil sketch object (default: Setup > Sketch, else found by its lip layers)")


def sketched_frames(scene, gp) -> list[int]:
    """Frames holding a keyframe on the sketch's lip layers."""
    from ..blender.strokes import _lip_layers

    frames = set()
    lips = _lip_layers(gp.data.layers, lambda lay: lay.name)
    for layer in lips["upper"] + lips["lower"]:
        frames.update(int(fr.frame_number) for fr in layer.frames)
    return sorted(frames)


def run(args, session) -> dict:
    import time

    bpy = session.bpy
    scene = session.scene
    obj = session.face()
    if scene.camera is None:
        raise CliError("The scene has no camera; set the camera the plate was shot with (Scene > Camera).")
    gp = None
    if args.sketch:
        gp = bpy.data.objects.get(args.sketch)
        if gp is None or gp.type != "GREASEPENCIL":
            raise CliError(f"--sketch {args.sketch!r}: no Grease Pencil object of that name.")
        scene.facelab.sketch = gp
    from ..blender.strokes import _sketch_object

    gp = _sketch_object(scene, gp or scene.facelab.sketch)
    if args.frames:
        frames = parse_frames(args.frames, scene)
    elif gp is not None:
        frames = sketched_frames(scene, gp)
    else:
        frames = []
    if not frames:
        raise CliError("No sketched frame: draw the inner lips with New Lip Sketch in Blender, or give --frames "
                       "of frames that have annotation strokes.")
    if gp is not None:
        scene.facelab.sketch = gp
    done = []
    t0 = time.perf_counter()
    for i, f in enumerate(frames):
        scene.frame_set(f)
        before = {kb.name for kb in obj.data.shape_keys.key_blocks} if obj.data.shape_keys else set()
        t = time.perf_counter()
        try:
            session.call("refine_lips")
        except CliError as e:
            raise CliError(f"frame {f}: {e}", e.code) from None
        keys = obj.data.shape_keys
        new = [kb.name for kb in keys.key_blocks if kb.name not in before and kb != keys.reference_key]
        done.append({"frame": f, "shape_key": new[0] if new else None, "seconds": round(time.perf_counter() - t, 3)})
        session.log(f"refine {i + 1}/{len(frames)}: frame {f} -> {new[0] if new else '?'} "
                    f"({time.perf_counter() - t:.2f} s)")
    session.log(f"Refined {len(frames)} frames in {time.perf_counter() - t0:.1f} s")
    return {
        "object": obj.name,
        "sketch": gp.name if gp is not None else None,
        "refined": done,
        "training_frames": sorted({t.frame for t in obj.facelab.training_frames}),
        "saved": session.save(args.out),
    }
