import numpy as np
import pytest

from facelab_addon.core.capture.ict import find_ict_dir, load_ict
from facelab_addon.core.errors import DataMissingError
from facelab_addon.core.geometry.mesh import validate_mesh


def test_ict_layout_and_counts(ict):
    assert ict.neutral.shape == (26719, 3)
    assert len(ict.expressions) == 57 and len(ict.identities) == 10
    assert "jawOpen" in ict.expressions and "mouthClose" in ict.expressions
    assert len(ict.poly_offsets) - 1 == 26384  # upstream polygons
    validate_mesh(ict.neutral, ict.faces)  # triangulation is clean
    # fan triangulation keeps every polygon's area
    quad = np.flatnonzero(np.diff(ict.poly_offsets) == 4)[0]
    tris = ict.faces[ict.tri_poly == quad]
    assert len(tris) == 2 and set(tris.ravel()) == set(ict.poly_verts[ict.poly_offsets[quad] : ict.poly_offsets[quad] + 4])
    assert ict.landmarks.shape == (68,)
    assert ict.part_vertex_mask("M_Teeth").sum() > 1000


def test_ict_pose_is_linear_and_scale_applies(ict):
    d = ict.expressions["jawOpen"] - ict.neutral
    np.testing.assert_allclose(ict.pose({"jawOpen": 0.3}), ict.neutral + 0.3 * d)
    m = load_ict(scale=0.01, expressions=["jawOpen"])
    np.testing.assert_allclose(m.neutral, ict.neutral * 0.01)
    np.testing.assert_allclose(m.pose({"jawOpen": 1}), ict.expressions["jawOpen"] * 0.01)
    with pytest.raises(KeyError):
        ict.pose({"noSuchShape": 1})


def test_ict_missing_data_says_how_to_get_it(tmp_path, monkeypatch):
    monkeypatch.setenv("FACELAB_ICT_DIR", str(tmp_path / "nowhere"))
    with pytest.raises(DataMissingError, match="git clone https://github.com/ICT-VGL/ICT-FaceKit"):
        find_ict_dir()
    with pytest.raises(DataMissingError, match="nowhere"):
        load_ict(tmp_path / "also-nowhere")


@pytest.mark.slow
@pytest.mark.ict
def test_ict_cache_is_outside_the_repo(tmp_path, monkeypatch):
    monkeypatch.setenv("FACELAB_CACHE_DIR", str(tmp_path / "cache"))
    m = load_ict(expressions=["jawOpen"])
    files = list((tmp_path / "cache").glob("ict-*.npz"))
    assert len(files) == 1
    m2 = load_ict(expressions=["jawOpen"])  # from the cache
    np.testing.assert_array_equal(m.neutral, m2.neutral)
    np.testing.assert_array_equal(m.faces, m2.faces)
