"""Default face axes: Y up, the face looks along +Z.

Every function that needs to know which way a face is oriented (mouth and eye
corners, upper against lower lip or lid, a frontal camera) takes ``up`` and
``forward`` arguments defaulting to these (the ICT-FaceKit frame); pass others
for a face modelled in a different frame.

Both are unit (3,) tuples of floats in scene axes.
"""

from __future__ import annotations

__all__ = ["Y_UP", "Z_FORWARD"]

#: Default face up axis.
Y_UP = (0.0, 1.0, 0.0)
#: Default direction the face looks.
Z_FORWARD = (0.0, 0.0, 1.0)
