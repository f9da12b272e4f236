"""Fixtures of the core tests."""

import pytest


@pytest.fixture(scope="session")
def ict_zoo():
    """The ICT-FaceKit model as an error-zoo face (``testing.error_zoo.ZooFace``); skipped without ICT data."""
    from facelab_addon.core.capture.ict import load_ict
    from facelab_addon.testing.error_zoo import zoo_face

    try:
        ict = load_ict()
    except Exception as e:  # noqa: BLE001
        pytest.skip(f"ICT-FaceKit not available: {e}")
    return zoo_face(ict, "ICT")
