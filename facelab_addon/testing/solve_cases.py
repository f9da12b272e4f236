"""Unseen actors and camera rigs for the contour solve (tests and benchmark).

Bhat et al. 2013 (§4) solve a performance from markers and contours; to check
that defaults chosen on one capture carry over, the benchmark and the tests
solve captures of other faces filmed by other camera rigs:

* :func:`identity_model`: an ICT-FaceKit model of another person (the neutral
  and every expression target moved by a multiple of an ICT identity target,
  so the rig is that person's: same expression deltas, another face shape);
* :data:`CAMERA_LAYOUTS` / :func:`layout_cameras`: helmet rigs with the
  cameras at other distances, heights and baselines (a wide stereo pair, a
  close low pair, a pair above and below the mouth);
* :data:`TUNING_CASES` / :data:`HELD_OUT_CASES`: (identity, layout) pairs; the
  solve's defaults are chosen on the first, reported on the second.

Units: the model's scene units (``model.scale`` per centimetre); camera
distances are given in centimetres.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.capture.camera import Camera

__all__ = ["identity_model", "CAMERA_LAYOUTS", "layout_cameras", "TUNING_CASES", "HELD_OUT_CASES"]

#: Camera rigs, in centimetres from the face centre (0, -1, 8) cm of ICT-FaceKit (the face looks along +z):
#: ``eyes`` (C,3) camera positions relative to the centre, ``focal_px``, ``size`` (width, height).
CAMERA_LAYOUTS = {
    # the benchmark's default helmet pair: left and right of the mouth, 19 cm out, 3 cm below
    "helmet": dict(eyes=[(-6.0, -3.0, 19.0), (6.0, -3.0, 19.0)], focal_px=1200.0, size=(1080, 1920)),
    # a wide, farther pair (longer lenses), level with the face centre
    "wide": dict(eyes=[(-10.0, 0.0, 26.0), (10.0, 0.0, 26.0)], focal_px=1700.0, size=(1080, 1920)),
    # a close pair low under the chin, narrow baseline
    "low": dict(eyes=[(-4.0, -7.0, 15.0), (4.0, -7.0, 15.0)], focal_px=1000.0, size=(1080, 1920)),
    # one camera above the mouth, one below (vertical baseline), landscape
    "vertical": dict(eyes=[(1.0, 4.0, 21.0), (-1.0, -7.0, 20.0)], focal_px=1400.0, size=(1920, 1080)),
}

#: (identity target, amount, camera layout) the solve's defaults are tuned on.
TUNING_CASES = [("neutral", 0.0, "helmet"), ("identity001", 1.0, "helmet")]
#: (identity target, amount, camera layout) held out: other faces, other rigs.
HELD_OUT_CASES = [("identity003", 1.0, "wide"), ("identity006", -1.0, "low"), ("identity004", 1.0, "vertical")]


def identity_model(model, identity: str = "neutral", amount: float = 1.0):
    """An ICT-FaceKit model of another person.

    Parameters
    ----------
    model : core.capture.ict.ICTModel
    identity : str
        An identity target (``"identity000"`` ... ``"identity009"``), or
        ``"neutral"`` for ``model`` itself.
    amount : float
        Multiple of ``identity - neutral`` added to the neutral and to every
        expression target (ICT's identity PCA coefficients are of order 1).

    Returns
    -------
    ICTModel
        A copy sharing the topology and parts; ``identities`` is left empty.
    """
    if identity == "neutral" or amount == 0.0:
        return model
    if identity not in model.identities:
        raise KeyError(f"unknown ICT identity {identity!r}; use one of {sorted(model.identities)}")
    d = float(amount) * (model.identities[identity] - model.neutral)
    return dataclasses.replace(model, neutral=model.neutral + d,
                               expressions={k: v + d for k, v in model.expressions.items()}, identities={})


def layout_cameras(model, layout: str = "helmet"):
    """The cameras of a :data:`CAMERA_LAYOUTS` rig for ``model`` (scene units from ``model.scale``).

    Returns
    -------
    list of Camera
        Looking at the face centre (0, -1, 8) cm, y up.
    """
    spec = CAMERA_LAYOUTS[layout]
    cm = float(model.scale)
    c = np.array([0.0, -1.0, 8.0]) * cm
    w, h = spec["size"]
    sensor = 36.0
    focal_mm = spec["focal_px"] / w * sensor
    return [Camera.look_at(c + cm * np.asarray(e, float), c, (0.0, 1.0, 0.0), focal_mm, sensor, w, h)
            for e in spec["eyes"]]
