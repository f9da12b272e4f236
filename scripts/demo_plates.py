"""Render a frame range of a .blend as plate footage, Cycles on the CPU, in one process.

The demo's stand-in for real footage: the truth of a simulated capture rendered from the capture
camera, one numbered PNG per frame (``PREFIX_0001.png`` is the first frame), ready for
``bpy.data.movieclips.load`` or Load Plate. Run it in a subprocess (Cycles, no GPU context)::

    python scripts/demo_plates.py SCENE.blend OUTDIR --frames 1 48 --camera Camera --show Truth \
        --hide Face --scale 0.5 --samples 8 --prefix plate
"""

import argparse
import os
import sys
import tempfile
from pathlib import Path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("blend")
    ap.add_argument("out")
    ap.add_argument("--frames", nargs=2, type=int, required=True, metavar=("FIRST", "LAST"))
    ap.add_argument("--camera", default=None, help="camera object to render from (default: the scene camera)")
    ap.add_argument("--hide", nargs="*", default=[], help="objects hidden from the render")
    ap.add_argument("--show", nargs="*", default=[], help="objects shown in the render")
    ap.add_argument("--mute-keys", nargs="*", default=[], metavar="PREFIX", help="shape keys muted (name prefixes)")
    ap.add_argument("--scale", type=float, default=1.0, help="render size as a fraction of the scene's resolution")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--prefix", default="plate")
    a = ap.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-plates-"))
    import bpy

    bpy.ops.wm.open_mainfile(filepath=a.blend)
    sc = bpy.context.scene
    if a.camera:
        sc.camera = bpy.data.objects[a.camera]
    for name in a.hide:
        if name in bpy.data.objects:
            bpy.data.objects[name].hide_render = True
    for name in a.show:
        if name in bpy.data.objects:
            bpy.data.objects[name].hide_render = False
    for ob in bpy.data.objects:
        keys = getattr(getattr(ob, "data", None), "shape_keys", None)
        if keys is not None and a.mute_keys:
            for kb in keys.key_blocks:
                if kb.name.startswith(tuple(a.mute_keys)):
                    kb.mute = True
        if ob.type in {"GREASEPENCIL", "GPENCIL"}:
            ob.hide_render = True
    r = sc.render
    r.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = a.samples
    sc.cycles.use_denoising = False
    r.resolution_percentage = max(1, round(100 * a.scale))
    r.image_settings.file_format = "PNG"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    first, last = a.frames
    for f in range(first, last + 1):
        sc.frame_set(f)
        r.filepath = str(out / f"{a.prefix}_{f - first + 1:04d}.png")
        bpy.ops.render.render(write_still=True)
    print(f"rendered {last - first + 1} frames into {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
