"""Render one frame of a .blend with Cycles on the CPU (run in a subprocess).

Workbench and EEVEE need an OpenGL/EGL context that headless machines often
lack (the process aborts), so FaceLab's demo and tests render with Cycles in a
separate process:

    python scripts/render_blend.py SCENE.blend OUT.png --frame 12 \
        --hide Truth --border 0.3 0.7 0.35 0.6 --samples 16
"""

import argparse
import os
import sys
import tempfile


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("blend")
    ap.add_argument("out")
    ap.add_argument("--frame", type=int, default=None)
    ap.add_argument("--hide", nargs="*", default=[], help="objects hidden from the render")
    ap.add_argument("--show", nargs="*", default=[], help="objects shown in the render")
    ap.add_argument("--border", nargs=4, type=float, default=None, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                    help="render region in 0..1 camera-frame coordinates (y up), cropped")
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--mute-keys", nargs="*", default=[], metavar="PREFIX",
                    help="mute shape keys whose names start with these prefixes (e.g. FL_ for 'before')")
    ap.add_argument("--no-backplate", action="store_true", help="transparent film instead of the world")
    a = ap.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-render-"))
    import bpy

    bpy.ops.wm.open_mainfile(filepath=a.blend)
    sc = bpy.context.scene
    if a.frame is not None:
        sc.frame_set(a.frame)
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
    for ob in bpy.data.objects:  # sketches are overlays, not geometry
        if ob.type in {"GREASEPENCIL", "GPENCIL"}:
            ob.hide_render = True
    r = sc.render
    r.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = a.samples
    sc.cycles.use_denoising = False
    r.film_transparent = a.no_backplate
    r.image_settings.file_format = "PNG"
    if a.border:
        r.use_border = True
        r.use_crop_to_border = True
        r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = a.border
    r.filepath = os.path.abspath(a.out)
    bpy.ops.render.render(write_still=True)
    print(f"rendered {a.out}")


if __name__ == "__main__":
    sys.exit(main())
