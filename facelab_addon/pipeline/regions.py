"""Auto Regions: the trusted mouth region and the inner-lip region Propagate predicts (Dinev et al. 2018 §4).

The regions are two vertex groups on the face, :data:`~facelab_addon.names.MOUTH_GROUP`
(the mouth area the regression trusts) and :data:`~facelab_addon.names.LIPS_GROUP` (the
inner lips it predicts). :func:`auto_regions` proposes them as geodesic bands around the
inner-lip contact loop (:func:`facelab_addon.core.lips.regions.auto_regions`);
:func:`region_faces` reads them back, validated, for Propagate.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from ..assets import load_preset
from ..blender.mesh import (
    mesh_triangles,
    require_mesh,
    selected_vertices,
    set_vertex_group,
    vertex_group_mask,
)
from ..blender.objects import require_editable
from ..blender.shapekeys import rest_vertices
from ..core.errors import RegionError
from ..core.lips import regions as core_regions
from ..core.lips.lip_loop import inner_lip_loop, loop_width
from ..names import LIPS_GROUP, MOUTH_GROUP
from .settings import setting

__all__ = ["REGION_DEFAULTS", "RegionSettings", "RegionsResult", "auto_regions", "region_faces"]

#: Band widths of ``assets/presets/regions.json`` as fractions of the mouth width
#: (``core.lips.lip_loop.loop_width``): ``lip_width`` (inner-lip band half-width) and
#: ``mouth_width`` (trusted band outside it). The defaults of :class:`RegionSettings`.
REGION_DEFAULTS = load_preset("regions", {"lip_width": float, "mouth_width": float})


@dataclass
class RegionSettings:
    """How :func:`auto_regions` proposes the regions.

    Attributes
    ----------
    replace : bool
        Overwrite existing region groups (otherwise refuse).
    use_selection : bool
        Take the inner-lip loop from the selected vertices instead of finding it.
    lip_width, mouth_width : float
        Widths of the inner-lip band and of the mouth band around it, as
        fractions of the mouth width (corner to corner along the loop);
        the add-on's defaults come from ``assets/presets/regions.json``.
    """

    replace: bool = False
    use_selection: bool = False
    lip_width: float = setting(REGION_DEFAULTS["lip_width"], label="Lip Band", min=0.01, max=1.0, unit="mouth",
                               description="Half-width of the inner-lip band FL_lips, in mouth widths")
    mouth_width: float = setting(REGION_DEFAULTS["mouth_width"], label="Mouth Band", min=0.01, max=3.0,
                                 unit="mouth",
                                 description="Width of the trusted mouth band FL_mouth around the lips, in mouth widths")


@dataclass
class RegionsResult:
    """What :func:`auto_regions` wrote.

    Attributes
    ----------
    object : str
        The face object's name.
    mouth_vertices, lip_vertices : int
        Vertices in the mouth and inner-lip groups.
    groups : tuple of str
        The vertex groups written (mouth, lips).
    replaced : list of str
        Groups that existed and were overwritten.
    seconds : float
    """

    object: str
    mouth_vertices: int
    lip_vertices: int
    groups: tuple = (MOUTH_GROUP, LIPS_GROUP)
    replaced: list = field(default_factory=list)
    seconds: float = 0.0


def auto_regions(obj, settings: RegionSettings | None = None) -> RegionsResult:
    """Propose and write the mouth and inner-lip vertex groups of the face ``obj``.

    Reads the rest pose (Basis key, else the mesh) and its triangles, runs
    :func:`facelab_addon.core.lips.regions.auto_regions` and writes the two
    groups with weight 1. ``obj`` must be in Object Mode (the selection of an
    edited mesh is read from its mesh data).

    Parameters
    ----------
    obj : bpy.types.Object
        The face mesh.
    settings : RegionSettings, optional

    Returns
    -------
    RegionsResult

    Raises
    ------
    RegionError
        The groups exist and ``settings.replace`` is off, fewer than 4 vertices
        are selected with ``use_selection``, or no inner-lip loop is found.
    MeshError
        ``obj`` is not a mesh with faces.
    """
    settings = settings or RegionSettings()
    t0 = time.perf_counter()
    existing = [g for g in (MOUTH_GROUP, LIPS_GROUP) if obj.vertex_groups.get(g) is not None]
    if existing and not settings.replace:
        raise RegionError(f"{', '.join(existing)} already exist on '{obj.name}'; enable 'Replace Existing "
                          "Groups' to overwrite them, or edit them by weight painting.")
    require_mesh(obj)
    require_editable(obj, "Auto Regions")
    tris = mesh_triangles(obj.data)
    V = rest_vertices(obj)
    loop = None
    if settings.use_selection:
        loop = selected_vertices(obj)
        if len(loop) < 4:
            raise RegionError("Select the inner-lip edge loop (at least 4 vertices) in Edit Mode first.")
    loop = inner_lip_loop(V, tris, loop)
    width = loop_width(V, loop)
    mouth, lips = core_regions.auto_regions(V, tris, loop=loop, lip_width=settings.lip_width * width,
                                            mouth_width=settings.mouth_width * width)
    for name, mask in ((MOUTH_GROUP, mouth), (LIPS_GROUP, lips)):
        set_vertex_group(obj, name, mask)
    return RegionsResult(object=obj.name, mouth_vertices=int(mouth.sum()), lip_vertices=int(lips.sum()),
                         replaced=existing, seconds=time.perf_counter() - t0)


def region_faces(obj, tris) -> tuple:
    """The mouth and inner-lip triangles of ``obj``, from its region vertex groups, validated.

    Parameters
    ----------
    obj : bpy.types.Object
    tris : (F,3) int array
        ``mesh_triangles(obj.data)``.

    Returns
    -------
    mouth_faces, lip_faces : (m,), (l,) int64 ndarray
        Indices into ``tris``.

    Raises
    ------
    RegionError
        A group is missing, or the regions are empty, overlap or leave the
        inner lips without a border (``core.lips.regions.validate_regions``).
    """
    mouth = vertex_group_mask(obj, MOUTH_GROUP)
    lips = vertex_group_mask(obj, LIPS_GROUP)
    missing = [g for g, m in ((MOUTH_GROUP, mouth), (LIPS_GROUP, lips)) if m is None]
    if missing:
        raise RegionError(
            f"'{obj.name}' has no vertex group {' or '.join(missing)}; press Auto Regions (or paint the "
            f"groups: {MOUTH_GROUP} = trusted mouth area, {LIPS_GROUP} = inner lips to predict)."
        )
    mf = core_regions.faces_in_region(tris, mouth)
    lf = core_regions.faces_in_region(tris, lips)
    core_regions.validate_regions(tris, mf, lf, len(obj.data.vertices))
    return mf, lf
