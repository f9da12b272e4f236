"""Errors raised by the FaceLab core.

Every message names the problem *and* the fix, so an operator can show it to
an artist verbatim (``self.report({'ERROR'}, str(err))``).
"""


class FaceLabError(Exception):
    """Base class of every error FaceLab raises on bad input."""


class MeshError(FaceLabError):
    """The mesh is unusable: NaNs, bad indices, degenerate faces, wrong topology."""


class CameraError(FaceLabError):
    """The camera is missing, not calibrated, or cannot see the face."""


class SketchError(FaceLabError):
    """The lip sketch is missing, incomplete or outside the camera frame."""


class DataMissingError(FaceLabError):
    """External data (for example the ICT-FaceKit model) could not be found."""


class RegionError(FaceLabError):
    """The mouth/lip regions are unusable: empty, overlapping, no border, no loop."""


class CacheFileError(FaceLabError):
    """A PC2/MDD file is missing, truncated, of the wrong format or inconsistent."""


class CacheVertexCountError(CacheFileError, MeshError):
    """The cache stores a different number of points than the mesh has vertices."""


class BundleError(FaceLabError):
    """The bundles are unusable: off the mesh, NaN, unbound, or not moved by any shape."""


class DatasetError(FaceLabError):
    """The dataset of shapes is unusable: too few, duplicates, wrong vertex count, NaN."""


class ObjFileError(MeshError, ValueError):
    """An OBJ file is unreadable: a malformed line, a NaN or infinite coordinate, a face index out of range."""


class OutputError(FaceLabError):
    """A file cannot be written: a read-only folder, a parent path that is a file, a full disk."""
