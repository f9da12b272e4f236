"""The set-up every benchmark that runs Blender (the ``bpy`` module) in its own process shares.

A benchmark prints one JSON object on stdout, so that ``python benchmarks/X.py > benchmarks/results/X.json``
saves exactly the result; Blender, its add-ons and the libraries print to stdout too. The pieces:

* :func:`json_stdout`: keep the process's stdout for the JSON alone and send everything else printed to
  it (Python's ``print`` and Blender's own C-level output alike) to stderr; the returned
  :class:`JsonOut` writes the one JSON object at the end.
* :func:`user_resources`: point ``BLENDER_USER_RESOURCES`` at a fresh temporary folder (unless it is set
  already), so a benchmark neither reads nor writes the user's Blender configuration.
* :func:`blender_session`: :func:`user_resources`, ``import bpy`` and register the FaceLab add-on; the
  add-on is unregistered on the way out, also after an error (bpy 4.5 hangs at exit while a
  ``PointerProperty(poll=...)`` is registered). It leaves stdout alone: call :func:`json_stdout` first.
* :func:`log` (progress to stderr) and :func:`since` (rounded wall seconds since a ``perf_counter``).

Typical use (``benchmarks/route_sweep.py``)::

    out_json = json_stdout()
    t_all = time.perf_counter()
    with blender_session() as bpy:
        out = dict(bpy_version=bpy.app.version_string, ...)
        ...
        out["total_s"] = since(t_all, 1)
        out_json.emit(out)

Import it from a benchmark with ``sys.path`` holding ``benchmarks/`` (``from _harness import ...``).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import tempfile
import time


def log(msg):
    """Print one progress line to stderr (stdout is the JSON's), flushed at once.

    Parameters
    ----------
    msg : object
        What to print (``str()`` of it).
    """
    print(msg, file=sys.stderr, flush=True)


def since(t0, digits=2):
    """Wall seconds since ``t0`` (a ``time.perf_counter()`` value), rounded.

    Parameters
    ----------
    t0 : float
        The start, from ``time.perf_counter()``.
    digits : int
        Decimal places kept.

    Returns
    -------
    float
        Seconds.
    """
    return round(time.perf_counter() - t0, digits)


def user_resources(prefix="facelab-bl-user-"):
    """Point ``BLENDER_USER_RESOURCES`` at a new temporary folder, unless the environment already sets it.

    Call it before ``import bpy``: Blender reads the variable when it starts.

    Parameters
    ----------
    prefix : str
        Name prefix of the temporary folder.

    Returns
    -------
    str
        The folder Blender will use for its user resources.
    """
    if not os.environ.get("BLENDER_USER_RESOURCES"):
        os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix=prefix)
    return os.environ["BLENDER_USER_RESOURCES"]


class JsonOut:
    """The original stdout of the process, kept for the one JSON object (made by :func:`json_stdout`).

    Parameters
    ----------
    fd : int
        A duplicate of file descriptor 1 taken before stdout was pointed at stderr.
    """

    def __init__(self, fd):
        self.fd = fd

    def emit(self, obj, **dumps_kw):
        """Write ``obj`` as JSON (``indent=1`` unless given) and a newline to the kept stdout.

        Parameters
        ----------
        obj : object
            Anything ``json.dumps`` takes.
        **dumps_kw
            More keyword arguments for ``json.dumps`` (e.g. ``ensure_ascii=False``).
        """
        dumps_kw.setdefault("indent", 1)
        sys.stdout.flush()
        os.write(self.fd, (json.dumps(obj, **dumps_kw) + "\n").encode())


def json_stdout():
    """Keep stdout for the JSON: what is printed to file descriptor 1 from now on goes to stderr.

    Returns
    -------
    JsonOut
        Writes the JSON object to the original stdout (:meth:`JsonOut.emit`).
    """
    sys.stdout.flush()
    fd = os.dup(1)
    os.dup2(2, 1)
    return JsonOut(fd)


@contextlib.contextmanager
def blender_session(prefix="facelab-bl-user-"):
    """Blender with the FaceLab add-on registered, for the ``with`` block.

    Sets up :func:`user_resources`, imports ``bpy`` and ``facelab_addon`` (the repository root must be on
    ``sys.path``), registers the add-on, and unregisters it when the block ends, also when it raises.
    Stdout is left alone: call :func:`json_stdout` first where stdout must carry only the JSON.

    Parameters
    ----------
    prefix : str
        Name prefix of the temporary user-resources folder.

    Yields
    ------
    module
        ``bpy``.
    """
    user_resources(prefix)
    import bpy

    import facelab_addon

    facelab_addon.register()
    try:
        yield bpy
    finally:
        facelab_addon.unregister()
