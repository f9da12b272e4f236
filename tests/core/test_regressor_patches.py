"""Local patches of the lip region (core/lips/regressor/patches.py) on a grid with a lip strip."""

import numpy as np
import pytest

from facelab_addon.core.lips.regions import faces_in_region
from facelab_addon.core.lips.regressor.patches import lip_patches
from facelab_addon.testing.meshes import grid_mesh


def strip():
    """A 21 x 9 unit grid: rows 3..5 the lip strip, the rest the mouth."""
    V, F = grid_mesh(np.arange(21, dtype=float), np.arange(9, dtype=float))
    y = V[:, 1]
    return V, F, faces_in_region(F, (y <= 3) | (y >= 5)), faces_in_region(F, (y >= 3) & (y <= 5))


def test_one_patch_is_the_whole_region():
    V, F, mouth, lips = strip()
    (p,), spacing = lip_patches(V, F, mouth, lips, 1, None)
    np.testing.assert_array_equal(p[0], np.arange(len(mouth)))
    np.testing.assert_array_equal(p[1], np.arange(len(lips)))
    np.testing.assert_array_equal(p[2], np.ones(len(lips)))
    assert spacing == np.inf


@pytest.mark.parametrize("count", [2, 4, 7])
def test_patches_are_a_partition_of_unity_with_nearby_mouth_inputs(count):
    V, F, mouth, lips = strip()
    patches, spacing = lip_patches(V, F, mouth, lips, count, None)
    assert len(patches) == count
    total = np.zeros(len(lips))
    for mouth_sel, lip_sel, w in patches:
        assert np.all(w > 0) and np.all(w <= 1)
        total[lip_sel] += w
        assert len(mouth_sel) >= 3 and mouth_sel.max() < len(mouth)
        # the mouth input lies within the spacing (edge-path) of the patch: never the far end of the strip
        lx = V[F[lips[lip_sel]]][..., 0]
        mx = V[F[mouth[mouth_sel]]][..., 0]
        assert mx.min() >= lx.min() - spacing - 1e-9 and mx.max() <= lx.max() + spacing + 1e-9
    np.testing.assert_allclose(total, 1.0, atol=1e-12)
    # centres spread along the 20-unit strip: about 20 / (count - 1) apart
    assert 0.6 * 20 / (count - 1) <= spacing <= 1.6 * 20 / (count - 1) + 1.5


def test_the_input_radius_sets_the_mouth_input():
    V, F, mouth, lips = strip()
    wide, _ = lip_patches(V, F, mouth, lips, 3, 100.0)
    assert all(len(p[0]) == len(mouth) for p in wide)  # the whole mouth is within reach
    narrow, _ = lip_patches(V, F, mouth, lips, 3, 3.0)
    assert all(len(p[0]) < len(mouth) for p in narrow)
    for mouth_sel, _, _ in narrow:  # only the mouth rows next to the strip (y = 1..3 and 5..7) are read
        y = V[F[mouth[mouth_sel]]][..., 1]
        assert y.min() >= 1 and y.max() <= 7
    # a reach that takes in fewer than 3 mouth triangles falls back to the whole mouth
    tiny, _ = lip_patches(V, F, mouth, lips, 3, 0.5)
    assert all(len(p[0]) == len(mouth) for p in tiny)
