"""Operators that bring material into a scene: Load Plate (real footage behind the camera) and Load
Sample (the shipped sample shot). The work is in :mod:`facelab_addon.pipeline.plate` and
:mod:`facelab_addon.pipeline.sample`."""

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty

from ..core.errors import FaceLabError
from ..pipeline.plate import PlateSettings, load_plate
from ..pipeline.sample import SampleSettings, load_sample
from ..pipeline.settings import describe

_P = {d["name"]: d for d in describe(PlateSettings)}  # labels and tooltips of the plate settings


def _footage_glob() -> str:
    exts = sorted(set(bpy.path.extensions_movie) | set(bpy.path.extensions_image))
    return ";".join(f"*{e}" for e in exts)


class FACELAB_OT_load_plate(bpy.types.Operator):
    """Load a movie or image sequence as a Movie Clip behind the scene camera and match the scene's frame range, frame rate, resolution (and the lens, when the clip's tracking camera is set) to it"""

    bl_idname = "facelab.load_plate"
    bl_label = "Load Plate"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(name="Footage", subtype="FILE_PATH",
                             description="A movie, or the first image of a numbered image sequence")
    filter_glob: StringProperty(default="", options={"HIDDEN"})
    clip: StringProperty(name="Movie Clip", default="",
                         description="Use this Movie Clip of the file instead of loading footage (for footage "
                                     "already tracked in Blender: its solved lens is taken)")
    match_frame_range: BoolProperty(name=_P["match_frame_range"]["label"], default=True,
                                    description=_P["match_frame_range"]["description"])
    match_fps: BoolProperty(name=_P["match_fps"]["label"], default=True, description=_P["match_fps"]["description"])
    match_resolution: BoolProperty(name=_P["match_resolution"]["label"], default=True,
                                   description=_P["match_resolution"]["description"])
    lens_from_clip: BoolProperty(name=_P["lens_from_clip"]["label"], default=True,
                                 description=_P["lens_from_clip"]["description"])
    frame_start: IntProperty(name=_P["frame_start"]["label"], default=1, description=_P["frame_start"]["description"])
    alpha: FloatProperty(name=_P["alpha"]["label"], default=1.0, min=0.0, max=1.0,
                         description=_P["alpha"]["description"])

    @classmethod
    def poll(cls, context):
        cam = context.scene.camera
        if cam is None or cam.type != "CAMERA":
            cls.poll_message_set("Set a scene camera first: the plate goes behind the camera the footage was shot with")
            return False
        return True

    def invoke(self, context, event):
        if self.clip or self.filepath:
            return self.execute(context)
        self.filter_glob = _footage_glob()
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        scene = context.scene
        settings = PlateSettings(match_frame_range=self.match_frame_range, match_fps=self.match_fps,
                                 match_resolution=self.match_resolution, lens_from_clip=self.lens_from_clip,
                                 frame_start=self.frame_start, alpha=self.alpha)
        clip = None
        if self.clip:
            clip = bpy.data.movieclips.get(self.clip)
            if clip is None:
                self.report({"ERROR"}, f"No Movie Clip named '{self.clip}' in this file; pick footage instead, or "
                                       "give the name of a clip in the Movie Clip Editor")
                return {"CANCELLED"}
        try:
            r = load_plate(scene, self.filepath or None, settings, clip=clip)
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        i = r.info
        done = [f"{k.replace('_', ' ')} {v}" for k, v in r.changed.items() if k != "lens"]
        if "lens" in r.changed:
            done.append(f"lens {r.changed['lens']['lens_mm']:.1f} mm from the clip")
        self.report({"INFO"}, f"Plate '{r.clip}' ({i.width}x{i.height}, {i.frames} frames) behind camera '{r.camera}' "
                              f"(background {r.backgrounds}); set " + (", ".join(done) or "nothing") +
                    ("; " + "; ".join(r.skipped) if r.skipped else ""))
        return {"FINISHED"}


class FACELAB_OT_load_sample(bpy.types.Operator):
    """Build the sample shot in a new scene: a reduced ICT-FaceKit face with a 48-frame capture whose inner lips fail to close, its camera and plate. Try Auto Regions, a sketch, Refine Lips and Propagate on it"""

    bl_idname = "facelab.load_sample"
    bl_label = "Load Sample"
    bl_options = {"REGISTER", "UNDO"}

    plate: BoolProperty(name="With Plate", default=True,
                        description="Load the sample's footage behind the camera (48 JPEG frames)")

    def execute(self, context):
        try:
            r = load_sample(SampleSettings(plate=self.plate))
        except FaceLabError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        window = getattr(context, "window", None)
        if window is not None:
            window.scene = r.scene
        scene = r.scene
        if hasattr(scene, "facelab"):
            scene.facelab.face = r.face
        for ob in scene.objects:
            ob.select_set(False)
        r.face.select_set(True)
        view_layer = scene.view_layers[0]
        view_layer.objects.active = r.face
        self.report({"INFO"}, f"Sample shot in new scene '{scene.name}': face '{r.face.name}' ({r.vertices} vertices, "
                              f"frames {r.frames[0]}-{r.frames[1]}), camera '{r.camera.name}'"
                              + (f", plate '{r.clip}'" if r.clip else "") +
                    f". The capture's inner lips fail to close (shape key '{r.error_key}'; mute it to see the "
                    "truth). Next: Auto Regions, then New Lip Sketch on a frame where the lips gap")
        return {"FINISHED"}


def menu_import(self, context):
    """File > Import: the plate and the sample shot."""
    self.layout.operator(FACELAB_OT_load_plate.bl_idname, text="FaceLab Plate (movie / image sequence)")
    self.layout.operator(FACELAB_OT_load_sample.bl_idname, text="FaceLab Sample Shot")


classes = (FACELAB_OT_load_plate, FACELAB_OT_load_sample)

_register, _unregister = bpy.utils.register_classes_factory(classes)


def register():
    _register()
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
    _unregister()
