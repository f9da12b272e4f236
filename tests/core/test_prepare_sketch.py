"""core.lips.views.prepare_sketch: strokes drawn in pieces, with a tap of the pen among them."""
import numpy as np
import pytest

from facelab_addon.core.capture.camera import Camera
from facelab_addon.core.errors import SketchError
from facelab_addon.core.lips.views import prepare_sketch


def _cam():
    K = np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])
    return Camera(K, np.eye(3), np.zeros(3), 1920, 1080)


def _arc(x0, x1, y, sag):
    x = np.linspace(x0, x1, 60)
    return np.c_[x, y + sag * (1 - ((x - (x0 + x1) / 2) / ((x1 - x0) / 2)) ** 2)]


def test_a_dot_among_the_pieces_is_left_out_not_refused():
    """The lower lip drawn in two pieces plus a 1.5 px dot: the dot is left out and the rest is read exactly as
    without it (the hand of the error zoo leaves such pieces)."""
    up = _arc(800, 1100, 500, -20)
    lo_a, lo_b = _arc(800, 1100, 560, 25)[:30], _arc(800, 1100, 560, 25)[30:]
    dot = np.array([[950.0, 590.0], [951.0, 591.0]])  # 1.41 px across
    U0, L0 = prepare_sketch(_cam(), up, [lo_a, lo_b])
    U1, L1 = prepare_sketch(_cam(), up, [lo_a, dot, lo_b])
    assert np.array_equal(U0, U1) and np.array_equal(L0, L1)


def test_a_lip_drawn_only_as_dots_is_refused():
    up = _arc(800, 1100, 500, -20)
    dots = [np.array([[950.0, 590.0], [951.0, 591.0]]), np.array([[990.0, 590.0]])]
    with pytest.raises(SketchError, match="lower-lip stroke is too short"):
        prepare_sketch(_cam(), up, dots)
