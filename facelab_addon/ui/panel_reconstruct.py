"""Drawing of the sidebar's Reconstruct from Bundles section (Cong, Lan & Fedkiw, local geometric indexing).

``draw_reconstruct_section(layout, context)`` is called by ``ui/panel.py``;
the settings live in ``scene.facelab_recon`` (``ui/props_reconstruct.py``).
"""

from ..names import BUNDLES_COLLECTION
from .common import face_object


def draw_reconstruct_section(layout, context):
    """Bundles, bind frame, method and noise, jaw and smoothing; Reconstruct; the corrective-shape tool."""
    r = getattr(context.scene, "facelab_recon", None)
    col = layout.column()
    if r is None:  # not registered (partial reload)
        col.label(text="Reconstruct settings are not registered", icon="ERROR")
        return
    face = face_object(context)
    if face is None:
        col.label(text="No face mesh selected", icon="INFO")
    col.label(text="Dataset: the face's shape keys", icon="SHAPEKEY_DATA")

    box = col.box()
    box.prop(r, "bundle_source")
    if r.bundle_source == "COLLECTION":
        box.prop(r, "bundle_collection")
    elif r.bundle_source == "MESH":
        box.prop(r, "bundle_mesh")
    else:
        box.label(text=f"Select the bundle empties (or use '{BUNDLES_COLLECTION}')", icon="EMPTY_DATA")
    box.operator("facelab.bundles_from_clip", icon="TRACKER")
    row = box.row(align=True)
    row.prop(r, "bind_scene_start", text="Bind on Scene Start")
    if not r.bind_scene_start:
        row.prop(r, "bind_frame")

    box = col.box()
    box.prop(r, "method")
    if r.method == "FIT_RESIDUAL":
        box.prop(r, "noise")

    box = col.box()
    box.prop(r, "jaw_source")
    if r.jaw_source == "BONE":
        box.prop(r, "jaw_armature")
        if r.jaw_armature is not None and r.jaw_armature.type == "ARMATURE":
            box.prop_search(r, "jaw_bone", r.jaw_armature.data, "bones")
        else:
            box.prop(r, "jaw_bone")
    elif r.jaw_source == "OBJECT":
        box.prop(r, "jaw_object")
    if r.jaw_source != "NONE" and r.method != "INDEXING":
        box.label(text="The jaw drives Local Indexing only", icon="INFO")
    if r.jaw_source != "NONE":
        if face is not None:
            box.prop_search(r, "jaw_group", face, "vertex_groups")
        else:
            box.prop(r, "jaw_group")

    col.prop(r, "smooth")
    col.operator("facelab.reconstruct_from_bundles", icon="EMPTY_DATA")

    box = col.box()
    box.label(text="Actor-specific correctives (rig combinations)")
    box.prop(r, "rig_object")
    box.prop(r, "combinations", text="")
    box.operator("facelab.generate_correctives", icon="SHAPEKEY_DATA")
