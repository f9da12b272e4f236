"""How FaceLab's results read to an artist: the words the panel, the operator reports and the CLI share.

Pure functions of plain numbers and strings (no ``bpy``), so every front end says the same thing:

* :func:`extrapolation_word` / :func:`extrapolation_tooltip`: the extrapolation score keyed per frame
  by Propagate as *reliable*, *uncertain* or *guessing*;
* :func:`mm`: a length in millimetres, with a sensible number of digits;
* :func:`held_fixed`: what a solve held fixed, by name;
* :func:`model_sentence` / :func:`propagate_headline`: what Propagate learnt, in one plain sentence.

Reports are assembled as a list of parts joined by ``"; "`` (:func:`join`), so a step can add a part.
"""

from __future__ import annotations

__all__ = ["EXTRAPOLATING", "GUESSING", "extrapolation_word", "extrapolation_tooltip", "mm", "held_fixed",
           "model_sentence", "forced_whole_reason", "propagate_headline", "expected_worse", "frame_list", "join"]

#: Extrapolation scores above this are flagged: the frame's mouth lies well outside the training poses.
EXTRAPOLATING = 0.5
#: Above this the frame departs from the training poses more than a typical training pose departs from
#: rest (the score's unit, :meth:`facelab_addon.core.lips.regressor.LipRegressor.extrapolation`).
GUESSING = 1.0


def extrapolation_word(score: float) -> str:
    """``"reliable"`` (score up to :data:`EXTRAPOLATING`), ``"uncertain"`` (up to :data:`GUESSING`) or
    ``"guessing"`` (beyond), for a frame's extrapolation score (unitless, 0 on training frames)."""
    if score <= EXTRAPOLATING:
        return "reliable"
    return "uncertain" if score <= GUESSING else "guessing"


def extrapolation_tooltip(score: float) -> str:
    """The score and what its bands mean, for a tooltip."""
    return (f"Extrapolation {score:.2f} on this frame: how far its mouth lies outside the corrected frames' poses "
            f"(reliable up to {EXTRAPOLATING:g}, uncertain up to {GUESSING:g}, guessing beyond; 0 on a corrected "
            "frame). Correct an uncertain or guessing frame and propagate again")


def mm(metres: float) -> str:
    """``"0.94 mm"``: a length given in metres, in millimetres with 2 significant decimals below 10 mm."""
    v = 1000.0 * float(metres)
    if abs(v) >= 10:
        return f"{v:.0f} mm"
    if abs(v) >= 0.1 or v == 0:
        return f"{v:.2f} mm"
    return f"{v:.2g} mm"


def held_fixed(source: str, group: str) -> str:
    """What a solve held fixed, by name.

    Parameters
    ----------
    source : str
        :func:`facelab_addon.blender.mesh.default_fixed_mask`'s source: ``"vertex group '<name>'"`` or
        ``"separate mesh parts"``.
    group : str
        The fixed vertex group the settings name (FaceLab > Setup > Fixed Group).
    """
    if source.startswith("vertex group"):
        return f"held fixed: the {source}"
    return (f"held fixed: every mesh part not joined to the face (teeth, tongue, eyes), as the face has no "
            f"vertex group '{group}'")


def model_sentence(whole_weight: float, reason: str = "") -> str:
    """What the fitted model does, in words: ``whole_weight`` is the share (0-1) of the model that predicts
    the lips' whole motion from the mouth; the rest adds the learnt correction to the captured lips.
    ``reason``: why the whole motion was forced (training frames sculpted in place), if it was."""
    w = float(whole_weight)
    if reason:
        return f"predicting the lips' whole motion from the mouth ({reason})"
    if w >= 0.995:
        return "predicting the lips' whole motion from the mouth"
    if w <= 0.005:
        return "adding the learnt correction to the captured lips"
    return (f"{100 * (1 - w):.0f} % adding the learnt correction to the captured lips, "
            f"{100 * w:.0f} % predicting their whole motion from the mouth")


def forced_whole_reason(model: str) -> str:
    """Why Propagate fell back to the whole motion, from its result's ``model`` label
    (:func:`facelab_addon.pipeline.propagate.model_summary`: ``"whole motion: <reason>"``); empty otherwise."""
    head, _, reason = model.partition(": ")
    return reason if head == "whole motion" else ""


def propagate_headline(frames: int, seconds: float, shapes: int, training: int, whole_weight: float,
                       reason: str = "") -> str:
    """``"Propagated to 48 frames in 2.1 s: 9 corrective shapes learnt from 3 corrected frames, 78 % adding
    the learnt correction to the captured lips, 22 % predicting their whole motion from the mouth"``."""
    return (f"Propagated to {frames:,} frames in {seconds:.1f} s: {shapes} corrective shape{'s' * (shapes != 1)} "
            f"learnt from {training} corrected frame{'s' * (training != 1)}, {model_sentence(whole_weight, reason)}")


def frame_list(frames, most: int = 12) -> str:
    """``"3, 4, 9"`` (``", ..."`` past ``most`` frames)."""
    frames = [int(f) for f in frames]
    return ", ".join(map(str, frames[:most])) + (", ..." if len(frames) > most else "")


def expected_worse(frames) -> str:
    """What Propagate expects to end worse than the capture (``frames``: scene frames, may be empty)."""
    n = len(frames)
    if not n:
        return "the model expects no frame worse than the capture"
    return (f"{n} frame{'s' * (n != 1)} expected worse than the capture: {frame_list(frames)} "
            "(check them, or correct one)")


def join(parts) -> str:
    """A report from its parts (empty ones left out), separated by ``"; "``."""
    return "; ".join(p for p in parts if p)
