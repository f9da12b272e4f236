"""Default face axes: Y up, the face looks along +Z.

Every function that needs to know which way a face is oriented (mouth and eye
corners, upper against lower lip or lid, a frontal camera) takes ``up`` and
``forward`` arguments defaulting to these (the ICT-FaceKit frame); pass others
for a face modelled in a different frame.

Both are unit (3,) tuples of floats in scene axes.
"""

from __future__ import annotations

import numpy as np

from ..errors import FaceLabError

__all__ = ["Y_UP", "Z_FORWARD", "unit_axis"]

#: Default face up axis.
Y_UP = (0.0, 1.0, 0.0)
#: Default direction the face looks.
Z_FORWARD = (0.0, 0.0, 1.0)


def unit_axis(v, what: str = "axis") -> np.ndarray:
    """``v`` as a (3,) float64 unit vector.

    Parameters
    ----------
    v : (3,) array_like
        A direction in scene axes (any length).
    what : str
        Its name for the error message (``"up"``, ``"forward"``...).

    Raises
    ------
    FaceLabError
        ``v`` has (near) zero length.
    """
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not n > 1e-12:
        raise FaceLabError(f"The '{what}' direction is zero; pass a non-zero direction (default: up +Y, forward +Z).")
    return v / n
