"""Which Grease Pencil / annotation layers hold the lip sketch: one resolution for every stroke reader.

The artist sketches the inner lips on two layers named "Upper lip" and "Lower lip"
(:mod:`facelab_addon.blender.strokes` creates them). A layer whose name contains "upper"
(case-insensitive) is an upper lip layer, "lower" a lower lip layer (:func:`lip_label`).
:func:`live_lip_layers` decides which of them are read, for the stroke reader, the keyframe checks and
the views of several cameras (:mod:`.sketch_views`): only shown layers (a hidden one is stale to the
artist); an exact name wins over partial matches; several partial matches are concatenated; two shown
layers among the exact name and its copies ("Upper lip.001", what Duplicate Layer gives) are ambiguous
and refused. Hidden sketch objects (:func:`hidden_object`) are not read either.
"""

from __future__ import annotations

import re

from ..core.errors import SketchError

__all__ = ["UPPER_LAYER", "LOWER_LAYER", "lip_label", "labelled_lip_layers", "live_lip_layers", "hidden_lip_layers",
           "missing_layer_error", "has_lip_layers", "hidden_object"]

UPPER_LAYER = "Upper lip"
LOWER_LAYER = "Lower lip"


def lip_label(name: str):
    """'upper', 'lower' or None for a layer name (the name holds "upper" or "lower", not both)."""
    n = name.lower()
    up, lo = "upper" in n, "lower" in n
    if up and not lo:
        return "upper"
    if lo and not up:
        return "lower"
    return None


def labelled_lip_layers(layers, name_of):
    """{'upper': [layers], 'lower': [layers]} by name alone, shown or hidden (where New Lip Sketch adds its
    keyframes); an exact name wins over partial matches. Readers use :func:`live_lip_layers`."""
    out = {"upper": [], "lower": []}
    for layer in layers:
        lab = lip_label(name_of(layer))
        if lab is not None:
            out[lab].append(layer)
    for lab, exact in (("upper", UPPER_LAYER.lower()), ("lower", LOWER_LAYER.lower())):
        hits = [lay for lay in out[lab] if name_of(lay).strip().lower() == exact]
        if hits:
            out[lab] = hits[:1]
    return out


def _hidden(layer) -> bool:
    """Whether a Grease Pencil or annotation layer is hidden (its eye icon off)."""
    return bool(getattr(layer, "hide", False) or getattr(layer, "annotation_hide", False))


def _copy_of(name: str, exact: str) -> bool:
    """Whether ``name`` is ``exact`` or a Blender copy of it (``Upper lip.001``), case-insensitively."""
    return re.fullmatch(re.escape(exact) + r"(\.\d{3,})?", name.strip(), flags=re.IGNORECASE) is not None


def live_lip_layers(layers, name_of, where: str) -> dict:
    """The lip layers a sketch is read from: ``{'upper': [layers], 'lower': [layers]}``, one resolution for
    every reader (strokes, keyframes, the views of several cameras).

    Only visible layers count: a hidden layer (eye icon off) is not what the artist sees. Of the visible
    layers labelled for a lip (the name holds "upper" / "lower"), the one named exactly "Upper lip" /
    "Lower lip" wins over partial matches, several partial matches are concatenated (strokes split over
    layers), except copies of the exact name (``Upper lip.001``, what duplicating the layer gives): two
    visible layers of one lip among the exact name and its copies are ambiguous. A lip whose only layers
    are hidden gets an empty list (the reader says so, :func:`hidden_lip_layers`).

    Raises
    ------
    SketchError
        Two or more visible layers of the exact name or its copies, naming them (in ``where``) and the fix.
    """
    out = {"upper": [], "lower": []}
    for layer in layers:
        lab = lip_label(name_of(layer))
        if lab is not None and not _hidden(layer):
            out[lab].append(layer)
    for lab, exact in (("upper", UPPER_LAYER), ("lower", LOWER_LAYER)):
        copies = [lay for lay in out[lab] if _copy_of(name_of(lay), exact)]
        if len(copies) > 1:
            names = ", ".join(f"'{name_of(lay)}'" for lay in copies)
            raise SketchError(
                f"{where} has {len(copies)} visible {exact.lower()} layers ({names}), so it is not clear which "
                f"holds the sketch. Delete (or hide) the ones you do not draw on, and name the one you do "
                f"'{exact}'."
            )
        hits = [lay for lay in copies if name_of(lay).strip().lower() == exact.lower()] or copies
        if hits:
            out[lab] = hits[:1]
    return out


def hidden_lip_layers(layers, name_of) -> dict:
    """``{'upper': [names], 'lower': [names]}`` of the hidden layers labelled for each lip."""
    out = {"upper": [], "lower": []}
    for layer in layers:
        lab = lip_label(name_of(layer))
        if lab is not None and _hidden(layer):
            out[lab].append(name_of(layer))
    return out


def missing_layer_error(layers, name_of, lab: str, where: str, fix: str) -> SketchError:
    """The message for a lip with no live layer: hidden ones named, else missing."""
    nice = UPPER_LAYER if lab == "upper" else LOWER_LAYER
    hidden = hidden_lip_layers(layers, name_of)[lab]
    if hidden:
        names = ", ".join(f"'{n}'" for n in hidden)
        return SketchError(
            f"{where} has its {nice.lower()} layer hidden ({names}); FaceLab reads only the layers shown. "
            f"Show the layer you drew the {nice.lower()} on (its eye icon), or delete the stale one."
        )
    return SketchError(f"{where} has no '{nice}' layer; {fix}")


def hidden_object(obj) -> bool:
    """Whether a sketch object is hidden in the viewport (hidden objects' strokes are not read)."""
    if obj.hide_viewport:
        return True
    try:
        return bool(obj.hide_get())
    except RuntimeError:  # not in the context's view layer
        return False


def has_lip_layers(gp_data) -> bool:
    """Whether Grease Pencil data has a layer labelled for a lip (shown or hidden)."""
    lips = labelled_lip_layers(gp_data.layers, lambda lay: lay.name)
    return bool(lips["upper"] or lips["lower"])
