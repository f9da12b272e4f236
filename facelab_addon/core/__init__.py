"""FaceLab core: the solvers, in plain NumPy/SciPy (and libigl where it helps).

Nothing below this package imports ``bpy``. Conventions (``docs/conventions.md``):
vertices are float64 ``(V,3)`` in scene units, triangles int64 ``(F,3)``,
sequences ``(T,V,3)``; pixels have their origin at the image's top-left with y
down; cameras follow OpenCV (``x_c = R @ X + t``, +z forward).
"""
