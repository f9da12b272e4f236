"""Refine Lips on sketched frames (Dinev et al. 2018 §5), like the sidebar's Sketch & Refine:
for every frame, the inner-lip strokes of the lip sketch (Grease Pencil 'Upper lip' / 'Lower lip'
layers, or annotations) pull the lips' silhouettes onto them; each result is a new corrective key
``FL_Refine_<frame>`` keyed on its frame and recorded as a training frame.

Needs a .blend with the face, the scene camera and the sketch.

Without ``--frames`` every sketched frame that has no refine key yet is refined; frames already
refined are skipped (listed in the summary's ``skipped``), so running the command again adds
nothing. A frame of ``--frames`` that is already refined is refused unless ``--again``, which
refines it again from what the frame shows now: a new key ``FL_Refine_<frame>.001`` becomes the frame's
training shape and the earlier key is switched off on that frame (kept, as Refine Lips does in the panel).

    python -m facelab_addon refine SHOT.blend --object Face --out SHOT_refined.blend      # sketched, not yet refined
    python -m facelab_addon refine SHOT.blend --object Face --frames 40,88 --out SHOT_refined.blend
    python -m facelab_addon refine SHOT.blend --object Face --frames 40 --again --out SHOT_refined.blend
"""

from __future__ import annotations

import re

from ..names import REFINE_PREFIX
from ._common import exit_code_for
from ._errors import CliError
from ._frames import parse_frames

HELP = "refine the lips on sketched frames (one corrective shape key per frame)"
INPUTS = ("blend",)


def add_arguments(p) -> None:
    p.add_argument("--sketch", metavar="NAME",
                   help="the Grease Pencil sketch object (default: Setup > Sketch, else found by its lip layers)")
    p.add_argument("--again", action="store_true",
                   help="refine frames of --frames that already have a refine key again: a new key "
                        "FL_Refine_<frame>.001 replaces the earlier one on that frame (kept, keyed off); "
                        "without it they are refused")


def refine_keys(obj) -> dict:
    """``{frame: [key names]}`` of the refine keys ``obj`` already has (``FL_Refine_0012``, ``FL_Refine_0012.001``)."""
    pat = re.compile(re.escape(REFINE_PREFIX) + r"(-?\d{4,})(\.\d{3})?")
    out: dict = {}
    for kb in (obj.data.shape_keys.key_blocks if obj.data.shape_keys else ()):
        m = pat.fullmatch(kb.name)
        if m:
            out.setdefault(int(m.group(1)), []).append(kb.name)
    return out


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
    done_before = refine_keys(obj)
    skipped = []
    if args.frames:
        frames = parse_frames(args.frames, scene)
        again = [f for f in frames if f in done_before]
        if again and not args.again:
            keys = [k for f in again for k in done_before[f]]
            raise CliError(f"--frames {args.frames}: frames {again} are already refined ({', '.join(keys[:6])}); "
                           "refining them again would replace their correction with a new key. Give --again to do that "
                           "on purpose, or leave them out of --frames.")
    elif gp is not None:
        sketched = sketch_keyframes(gp)
        frames = [f for f in sketched if f not in done_before]
        skipped = [{"frame": f, "why": f"already refined ({', '.join(done_before[f])})"}
                   for f in sketched if f in done_before]
        if skipped:
            shown = [d["frame"] for d in skipped][:12]
            session.note(f"skipped {len(skipped)} sketched frames already refined ({shown}); to refine one again, "
                         "give --frames N --again")
        if sketched and not frames:
            session.log("every sketched frame is already refined; nothing to do")
            return {"object": obj.name, "sketch": gp.name, "refined": [], "skipped": skipped,
                    "training_frames": sorted({t.frame for t in obj.facelab.training_frames}),
                    "saved": session.save(args.out)}
    else:
        frames = []
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
        for w in r.warnings:
            session.note(f"frame {f}: {w}")
        if f in done_before:
            session.note(f"frame {f} refined again (--again): '{r.shape_key}' replaces {done_before[f]} on that frame "
                         "(kept, keyed off there)")
        session.log(f"refine {i + 1}/{len(frames)}: frame {f} -> {r.shape_key} ({time.perf_counter() - t:.2f} s)")
    session.log(f"Refined {len(frames)} frames in {time.perf_counter() - t0:.1f} s")
    return {
        "object": obj.name,
        "sketch": gp.name if gp is not None else None,
        "refined": done,
        "skipped": skipped,
        "training_frames": sorted({t.frame for t in obj.facelab.training_frames}),
        "saved": session.save(args.out),
    }
