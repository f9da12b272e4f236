"""Shared test setup: import path, a private Blender user folder, the ICT model, FaceLab in Blender.

Fixtures
--------
ict
    The ICT-FaceKit model (centimetres), parsed once per session. Without the data, every test
    that uses it (directly or through another fixture), or is marked ``ict``, is skipped with a
    message saying how to get it.
empty_scene
    A factory-fresh, empty Blender scene.
addon
    FaceLab registered (in a factory-fresh Blender) for the tests of one module.

``bpy`` is imported inside the Blender fixtures only, so core tests never load it.
"""

import os
import re
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Blender must never touch the real user's config while testing.
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="facelab-bl-user-"))


# Blender API that the running Blender deprecates (e.g. ``Material.use_nodes`` in 5.x) fails the run: the
# supported versions' differences belong in facelab_addon/blender/compat.py. (An "error" warning filter
# does not work here: bpy raises it as a SystemError at some later, unrelated call.)
BLENDER_DEPRECATION = re.compile(r"'[\w.]+' is expected to be removed in Blender")
_blender_deprecations = {}


def pytest_configure(config):
    config.addinivalue_line("filterwarnings", "always:.*expected to be removed in Blender:DeprecationWarning")
    config.addinivalue_line("markers", "ict: needs the ICT-FaceKit data (skipped with a how-to when it is absent)")


def ict_missing():
    """Why the ICT-FaceKit data cannot be found (the message says how to get it), or None."""
    from facelab_addon.core.capture.ict import find_ict_dir
    from facelab_addon.core.errors import DataMissingError

    try:
        find_ict_dir()
    except DataMissingError as e:
        return str(e)
    return None


def pytest_collection_modifyitems(config, items):
    """Skip the tests that need the ICT data (the ``ict`` fixture anywhere in their fixtures, or the
    ``ict`` marker) when it is absent, before any of their setup runs."""
    why = ict_missing()
    if why is None:
        return
    skip = pytest.mark.skip(reason=f"needs the ICT-FaceKit data: {why}")
    for item in items:
        if "ict" in getattr(item, "fixturenames", ()) or item.get_closest_marker("ict"):
            item.add_marker(skip)


def pytest_warning_recorded(warning_message, when, nodeid, location):
    text = str(warning_message.message)
    if BLENDER_DEPRECATION.search(text):
        _blender_deprecations.setdefault(text, nodeid or when)


def pytest_sessionfinish(session, exitstatus):
    if _blender_deprecations:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter):
    if _blender_deprecations:
        terminalreporter.section("deprecated Blender API (fails the run; use facelab_addon/blender/compat.py)")
        for msg, where in _blender_deprecations.items():
            terminalreporter.line(f"{msg}  (first in {where})")


@pytest.fixture(scope="session")
def ict():
    """The ICT-FaceKit model (centimetres), parsed once per test session."""
    from facelab_addon.core.capture.ict import load_ict

    return load_ict()


@pytest.fixture
def empty_scene():
    """A factory-fresh, empty Blender scene (``bpy.types.Scene``); FaceLab stays registered if it was."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


@pytest.fixture(scope="module")
def addon():
    """FaceLab registered for the tests of one module, starting from a factory-fresh Blender; unregistered after."""
    import bpy

    import facelab_addon

    bpy.ops.wm.read_factory_settings(use_empty=True)
    facelab_addon.register()
    yield
    facelab_addon.unregister()
