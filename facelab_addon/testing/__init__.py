"""Test, benchmark and demo support: synthetic lip scenarios, capture simulators and shape
datasets built from the ICT-FaceKit face.

Not part of the shipped extension (``blender_manifest.toml`` excludes this folder); nothing in
``core``, ``blender``, ``pipeline``, ``ui`` or ``cli`` imports it.
"""
