"""Shared test setup: import path, a private Blender user folder, ICT fixtures."""

import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Blender must never touch the real user's config while testing.
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-bl-user-"))


@pytest.fixture(scope="session")
def ict():
    """The ICT-FaceKit model (centimetres), parsed once per test session."""
    from facelab_addon.core.capture.ict import load_ict

    return load_ict()
