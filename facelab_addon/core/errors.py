"""Errors raised by the FaceLab core.

Every message names the problem *and* the fix, so an operator can show it to
an artist verbatim (``self.report({'ERROR'}, str(err))``).
"""


class FaceLabError(Exception):
    """Base class of every error FaceLab raises on bad input."""


class UsageError(FaceLabError, ValueError):
    """An argument is not one the function accepts: an unknown option, or a wrong combination of arguments."""


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


class RegionMeshError(RegionError, MeshError):
    """The mesh given to a region finder is unusable (no triangles, bad indices, NaN positions)."""


class ObjFileError(MeshError, ValueError):
    """An OBJ file is malformed: a bad vertex, face or texture line, or a NaN coordinate (names file and line)."""


class CacheFileError(FaceLabError):
    """A PC2/MDD file is missing, truncated, of the wrong format or inconsistent."""


class CacheVertexCountError(CacheFileError, MeshError):
    """The cache stores a different number of points than the mesh has vertices."""


class BundleError(FaceLabError):
    """The bundles are unusable: off the mesh, NaN, unbound, or not moved by any shape."""


class DatasetError(FaceLabError):
    """The dataset of shapes is unusable: too few, duplicates, wrong vertex count, NaN."""


class FrameError(FaceLabError):
    """Specific frames are unusable: a training set with no motion, an implausible or non-finite result.

    ``frame_indices`` are positions in the frames the core function was
    given (``frame_index`` is the first, or None). The message names them as
    "frame index i"; a caller that knows the scene frames re-labels them with
    :meth:`for_frames` so the artist reads scene frame numbers.

    Parameters
    ----------
    template : str
        The message, with ``{frames}`` where the frames are named.
    frame_indices : sequence of int
        Positions of the offending frames in the frames given.
    """

    def __init__(self, template, frame_indices=()):
        self.template = str(template)
        self.frame_indices = tuple(int(i) for i in frame_indices)
        self.frame_index = self.frame_indices[0] if self.frame_indices else None
        super().__init__(self.template.format(frames=_name_frames(self.frame_indices, "frame index", "frame indices")))

    def for_frames(self, labels):
        """The same error naming ``labels[i]`` (e.g. scene frame numbers) instead of each index i.

        Parameters
        ----------
        labels : sequence
            One label per frame given to the core function (``labels[i]`` names frame index ``i``).

        Returns
        -------
        FrameError
            An error of the same class, with the same ``frame_indices`` and a message naming the labels.
        """
        new = type(self).__new__(type(self))
        new.template = self.template
        new.frame_indices = self.frame_indices
        new.frame_index = self.frame_index
        Exception.__init__(new, self.template.format(frames=_name_frames([labels[i] for i in self.frame_indices])))
        return new


class PredictionError(FrameError):
    """A prediction is not finite or not plausible (e.g. a correction larger than the mouth) on some frames."""


def _name_frames(labels, one="frame", many="frames", limit=8):
    """'frame a', 'frames a, b and c', or the first ``limit`` and a count of the rest."""
    names = [str(x) for x in labels]
    if not names:
        return f"no {many}"
    if len(names) == 1:
        return f"{one} {names[0]}"
    if len(names) > limit:
        return f"{many} " + ", ".join(names[:limit]) + f" and {len(names) - limit} more"
    return f"{many} " + ", ".join(names[:-1]) + f" and {names[-1]}"


class TooManyShapesError(FaceLabError):
    """Corrections that need more corrective shapes than allowed to stay within their tolerance
    (``core.lips.regressor.reduced.StreamingBasis``); the caller may store them another way."""


class OutputError(FaceLabError):
    """A file cannot be written: a read-only folder, a parent path that is a file, a full disk."""
