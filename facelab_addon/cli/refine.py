"""Refine Lips on sketched frames (Dinev et al. 2018 §5), like the sidebar's Sketch & Refine:
for every frame, the inner-lip strokes of the lip sketch (Grease Pencil 'Upper lip' / 'Lower lip'
layers, or annotations) pull the lips' silhouettes onto them; each result is a new corrective key
``FL_Refine_<frame>`` keyed on its frame and recorded as a training frame.

Needs a .blend with the face, the scene camera and the sketch.

    python -m facelab_addon refine SHOT.blend --object Face --out SHOT_refined.blend      # every sketched frame
    python -m facelab_addon refine SHOT.blend --object Face --frames 40,88 --out SHOT_refined.blend
"""

from __future__ import annotations

from ._common import CliError, exit_code_for, parse_frames

HELP = "refine the lips on sketched frames (one corrective shape key per frame)"
INPUTS = ("blend",)


def add_arguments(p) -> None:
    p.add_argument("--sketch", metavar="NAME",
                   help="the Grease Pencil sketch object (default: Setup > Sketch, else found by its lip layers)")


def run(args, session) -> dict:
    import time

    from ..blender.strokes import find_sketch_object, sketch_keyframes
    from ..core.errors import FaceLabError
    from ..pipeline.refine import refine
    from ..pipeline.shot_settings import refine_settings

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
    gp = find_sketch_object(scene, gp or scene.facelab.sketch)
    if args.frames:
        frames = parse_frames(args.frames, scene)
    elif gp is not None:
        frames = sketch_keyframes(gp)
    else:
        frames = []
    if not frames:
        raise CliError("No sketched frame: draw the inner lips with New Lip Sketch in Blender, or give --frames "
                       "of frames that have annotation strokes.")
    if gp is not None:
        scene.facelab.sketch = gp
    settings = refine_settings(scene)
    done = []
    t0 = time.perf_counter()
    for i, f in enumerate(frames):
        t = time.perf_counter()
        try:
            r = refine(scene, obj, f, settings, sketch=scene.facelab.sketch)
        except FaceLabError as e:
            raise CliError(f"frame {f}: {e}", exit_code_for(e)) from None
        done.append({"frame": f, "shape_key": r.shape_key, "seconds": round(time.perf_counter() - t, 3)})
        session.log(f"refine {i + 1}/{len(frames)}: frame {f} -> {r.shape_key} ({time.perf_counter() - t:.2f} s)")
    session.log(f"Refined {len(frames)} frames in {time.perf_counter() - t0:.1f} s")
    return {
        "object": obj.name,
        "sketch": gp.name if gp is not None else None,
        "refined": done,
        "training_frames": sorted({t.frame for t in obj.facelab.training_frames}),
        "saved": session.save(args.out),
    }
