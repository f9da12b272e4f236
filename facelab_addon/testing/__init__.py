"""Test, benchmark and demo support: every synthetic input the tests, benchmarks and demos use.

* ``synthetic``: ground-truth lip scenarios (sketch contours, injected inner-lip errors);
* ``capture_sim``: a simulated helmet stereo capture of a rig performance;
* ``datasets``: nonlinear ICT shape datasets and held-out poses for local geometric indexing;
* ``weights``: expression-weight curves (speech-like, smooth random, periodic, visemes);
* ``scenes``: the ICT face as a Blender object with keyed shape keys, bundle empties (imports bpy lazily);
* ``meshes``: small analytic grid meshes.

Not part of the shipped extension (``blender_manifest.toml`` excludes this folder); nothing in
``core``, ``blender``, ``pipeline``, ``ui`` or ``cli`` imports it.
"""
