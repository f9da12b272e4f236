"""The CLI's exit codes and its one exception (a message for the user and an exit code)."""

from __future__ import annotations

EXIT_OK = 0
EXIT_FAILED = 1  # FaceLab refused the data (operator error / FaceLabError)
EXIT_USAGE = 2  # bad arguments (argparse uses 2 too)
EXIT_INPUT = 3  # input file missing or unreadable
EXIT_OBJECT = 4  # object missing or not a mesh
EXIT_OUTPUT = 5  # output not writable
EXIT_BPY = 6  # bpy, or a module FaceLab needs (SciPy...), not importable
EXIT_INTERNAL = 70  # a bug

class CliError(Exception):
    """A failure with a message for the user (problem + fix) and an exit code."""

    def __init__(self, message: str, code: int = EXIT_FAILED, *, json_to_stdout: bool = False):
        super().__init__(message)
        self.code = code
        #: The refusal is about the outputs themselves: the JSON summary goes to stdout, not to ``--json``
        #: (which may be the input, the saved .blend or a file the scene reads).
        self.json_to_stdout = json_to_stdout
