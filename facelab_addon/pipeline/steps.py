"""Long pipelines as generators of progress steps, and the two ways to run them.

A long pipeline (Propagate, a point-cache bake) is written as a generator that
yields ``(label, done, total)`` between two steps and *returns* its result
(``StopIteration.value``). Nothing in the scene changes between two steps in a
way a cancel would leave half done. :func:`run_steps` runs such a generator to
the end at once (scripts, ``blender -b``, the CLI, the synchronous wrappers);
:class:`StepJob` runs it one step per call, so a modal operator can drive it on
timer events and cancel between steps. Plain Python: no ``bpy``.
"""

from __future__ import annotations

__all__ = ["StepJob", "run_steps"]


class StepJob:
    """Drives a generator of ``(label, done, total)`` steps one step per :meth:`step` call.

    Attributes
    ----------
    stage : str
        Label of the last step (``"starting"`` before the first).
    done, total : int
        Progress units of the last step.
    result : object
        The generator's return value once :attr:`finished`.
    finished : bool
    """

    def __init__(self, steps):
        self._steps = steps
        self.stage, self.done, self.total = "starting", 0, 1
        self.result = None
        self.finished = False

    @property
    def factor(self) -> float:
        """Fraction done, in [0, 1]."""
        return min(1.0, self.done / self.total) if self.total else 0.0

    def step(self) -> bool:
        """Run one step; False once the job has finished (``result`` holds its return value)."""
        try:
            self.stage, self.done, self.total = next(self._steps)
            return True
        except StopIteration as stop:
            self.result, self.finished = stop.value, True
            return False

    def run(self, progress=None):
        """Run every remaining step; ``progress(done, total)`` after each. Returns the result."""
        while self.step():
            if progress is not None:
                progress(self.done, self.total)
        return self.result

    def cancel(self) -> None:
        """Stop between two steps (the generator's ``finally`` blocks run)."""
        self._steps.close()


def run_steps(steps, progress=None):
    """Run a generator of steps to the end and return its result.

    Parameters
    ----------
    steps : generator
        Yields ``(label, done, total)``; returns the result.
    progress : callable(label, done, total), optional
        Called after each step.
    """
    job = StepJob(steps)
    while job.step():
        if progress is not None:
            progress(job.stage, job.done, job.total)
    return job.result
