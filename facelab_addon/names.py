"""Every name FaceLab gives to things it creates in a Blender scene.

One place for the ``FL_*`` prefixes of shape keys, vertex groups, actions,
collections, objects and timeline markers, so the operators, the pipelines,
the adapters and the CLI agree on them. Plain strings; no ``bpy``.
"""

from __future__ import annotations

import hashlib
import unicodedata

#: Prefix shared by everything FaceLab creates (muted when reading the capture).
PREFIX = "FL_"

# --- vertex groups ---------------------------------------------------------------------------
#: Trusted mouth region (input of the regression, Dinev et al. 2018 §4).
MOUTH_GROUP = "FL_mouth"
#: Inner-lip region the regression predicts.
LIPS_GROUP = "FL_lips"
#: Hidden vertices that must never move (mouth bag, teeth, back of the head).
FIXED_GROUP = "FL_fixed"
#: Eyeball vertex groups used by the eyelid contours.
EYEBALL_GROUPS = {"left": "FL_eyeball_left", "right": "FL_eyeball_right"}

# --- shape keys (prefixes; a frame number or index follows) ----------------------------------
REFINE_PREFIX = "FL_Refine_"
CORRECTED_PREFIX = "FL_Corrected_"
PROPAGATE_PREFIX = "FL_Prop_"
SOLVE_PREFIX = "FL_Solve_"
RETARGET_PREFIX = "FL_Retarget_"
RECONSTRUCT_PREFIX = "FL_Recon_"
RIG_CORRECTIVE_PREFIX = "FL_Corr_"

#: ID property on a mesh's shape-key datablock (``mesh.shape_keys``) listing the names of the
#: keys FaceLab created there: only these are ever replaced or removed by FaceLab.
OWNED_KEYS_PROP = "facelab_owned"
#: Key names FaceLab generated before :data:`OWNED_KEYS_PROP` existed (regular expressions): such
#: keys are adopted into the registry when it is first created on a datablock (older files), when
#: they also carry FaceLab's set-up (``blender.shapekeys``: slider range -10..10 for the numbered
#: keys, keyed 0, 1, 0 around the frame for the frame keys); an artist's key of the name is not.
LEGACY_KEY_PATTERNS = (
    r"FL_(Prop|Solve|Retarget|Recon)_\d{2}(\.\d{3})?",
    r"FL_(Refine|Corrected)_-?\d{4,}(\.\d{3})?",
)

#: Live Refine's preview shape key (value 1 while a session is open); never recorded as FaceLab's output
#: and left out wherever the capture is read.
LIVE_PREVIEW_KEY = "FL_LivePreview"
#: Sketch object custom property (bool): read its strokes snapped to the plate (the strokes drawn stay as they are).
SNAP_PROP = "facelab_snap"
#: Grease Pencil drawing attribute (INT8, per stroke): +1 read this stroke snapped to the plate, -1 never,
#: 0 (or no attribute) as the sketch's :data:`SNAP_PROP` says.
SNAP_ATTR = "facelab_snap"
#: Sketch object custom property (str): what the last snapping did (points snapped, left alone, and why).
SNAP_REPORT_PROP = "facelab_snap_report"
#: Temporary shape keys (``x``, ``y``, ``z``, ``c`` follow) that measure the modifier stack's
#: Jacobian in ``blender.rest_space``; removed before it returns.
REST_SPACE_KEY = "FL_tmp_rest_"

# --- correction caches (dense corrections that do not fit the key budget) -----------------------
#: Name of the Mesh Cache modifier playing a correction cache; ``{prefix}`` is the key prefix.
CORRECTION_CACHE_MODIFIER = "{prefix}Cache"
#: ID property on the object recording, per key prefix, the correction-cache modifier FaceLab
#: added and the files it wrote: only these are ever replaced or deleted by FaceLab.
CORRECTION_CACHES_PROP = "facelab_caches"

# --- actions, properties, objects, collections, markers --------------------------------------
SOLVE_ACTION = "FL_Solve"
RETARGET_ACTION = "FL_Retarget"
CORRECTIVES_ACTION = "FL_Correctives"
#: The face object's action keying :data:`EXTRAPOLATION_PROP` (an object's own action, not the shape keys').
EXTRAPOLATION_ACTION = "FL_Extrapolation"
#: Object custom property keyed by Propagate: how far each frame is from the training frames.
EXTRAPOLATION_PROP = "FL_extrapolation"
SKETCH_OBJECT = "FL_LipSketch"
#: Point color attribute of the review heat map: correction magnitude on the current frame.
CORRECTION_ATTR = "FL_correction"
#: Mesh custom property: the heat map's legend range ``[0, max]`` in millimetres and its frame.
CORRECTION_RANGE_PROP = "FL_correction_range_mm"
#: Object custom property holding the artist's mutes while Review shows the capture (JSON).
REVIEW_SAVED_PROP = "FL_review_saved"
BUNDLES_COLLECTION = "FL_bundles"
TRACK_EMPTY_PREFIX = "FL_track_"
TRAIN_MARKER = "FL train"
SUGGEST_MARKER = "FL suggest"

#: Scene property group holding the shot's :class:`~facelab_addon.pipeline.correctives.StorageSettings`
#: (registered by ``ui/scene_settings.py``, read by the correction writer when no settings are passed).
STORE_SETTINGS_ATTR = "facelab_store"


# --- file names -------------------------------------------------------------------------------
#: Most UTF-8 bytes of the part of a generated file name taken from one of the artist's names (the
#: .blend's or the object's), so that ``<blend>_<object>_<prefix>.001.pc2.tmp`` stays well inside
#: the 255-byte file-name limit of common file systems however long or non-ASCII the names are.
NAME_PART_BYTES = 80


def file_name_part(name: str, max_bytes: int = NAME_PART_BYTES) -> str:
    """The one sanitiser of every file name FaceLab generates from an artist's name.

    Letters and digits of any script are kept (``'Лицо'``, ``'visage_é'``: NFC-normalised, so an
    'é' typed as 'e' + accent is one letter), ``-`` and ``_`` too; every other character (spaces,
    dots, slashes, punctuation, control characters) becomes ``_``. A result longer than
    ``max_bytes`` UTF-8 bytes is cut on a character boundary and ends in ``~`` and 8 hex digits of
    a hash of the whole name, so two long names that share their start still give two files.

    Only new files are named with it: files FaceLab wrote before are found by the path stored in
    the .blend (the modifier's file path and the ``facelab_caches`` record), never by re-deriving
    their name, so older files keep working.

    Parameters
    ----------
    name : str
    max_bytes : int
        At least 16.

    Returns
    -------
    str
        Non-empty (``'_'`` for an empty name).
    """
    text = unicodedata.normalize("NFC", str(name))
    out = "".join(c if (c.isalnum() or c in "-_") else "_" for c in text) or "_"
    raw = out.encode("utf-8")
    if len(raw) <= max_bytes:
        return out
    tag = "~" + hashlib.sha1(text.encode("utf-8")).hexdigest()[:8]
    head = raw[: max(1, max_bytes - len(tag))].decode("utf-8", "ignore")
    return head + tag
