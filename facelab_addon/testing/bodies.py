"""Whole-body-like test meshes for Auto Regions: the ICT head with fingers and eyelid folds in one piece.

On a whole body, eyelids, fingers and toes are bigger "contact" groups (facing surfaces a fraction
of a millimetre apart that are far apart on the mesh) than the lips. :func:`head_with_folds` adds
such groups to the ICT-FaceKit head as one connected mesh: two hands of U-shaped "fingers" (a tube
bent back on itself, its two arms ``gap`` apart) beside the head, and two closed "eyelid" folds (a
U-tube lying flat, its arms one above the other, like closed lids) in front of the eyes, each
denser than the lips. Thin bridge triangles join every fold to the head, so the mesh is one piece
as a body is. The ICT mouth bag stays attached to the lips (ICT's ``M_BackHead``), the teeth and
tongue stay separate parts. Units: the ICT model's (centimetres unless loaded with ``scale``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["u_tube", "head_with_folds"]


def u_tube(length, radius, gap, *, n_around=24, n_along=80, n_bend=24):
    """A tube bent back on itself (U shape) in the xy plane: two arms along +x, ``gap`` apart.

    The arms' axes are at ``y = ±(radius + gap / 2)``, from ``x = 0`` to ``x = length``, joined by a
    half circle at ``x = length``. Open at both ends; normals point out of the tube.

    Returns
    -------
    V : (n,3) float64
    F : (f,3) int64
    """
    h = radius + 0.5 * gap
    xs = np.linspace(0.0, length, n_along)
    path = [np.c_[xs, np.full(n_along, h), np.zeros(n_along)]]
    a = np.linspace(0.5 * np.pi, -0.5 * np.pi, n_bend + 2)[1:-1]
    path.append(np.c_[length + h * np.cos(a), h * np.sin(a), np.zeros(len(a))])
    path.append(np.c_[xs[::-1], np.full(n_along, -h), np.zeros(n_along)])
    P = np.vstack(path)
    T = np.gradient(P, axis=0)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    B = np.array([0.0, 0.0, 1.0])
    N = np.cross(B, T)
    t = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    V = (P[:, None, :] + radius * (np.cos(t)[None, :, None] * N[:, None, :] + np.sin(t)[None, :, None] * B)).reshape(
        -1, 3)
    F = []
    m = n_around
    for i in range(len(P) - 1):
        for j in range(m):
            a0, a1 = i * m + j, i * m + (j + 1) % m
            b0, b1 = a0 + m, a1 + m
            F += [[a0, a1, b1], [a0, b1, b0]]
    F = np.asarray(F, dtype=np.int64)
    # orient outwards: the normal of the first triangle points away from its ring's axis point
    n = np.cross(V[F[0, 1]] - V[F[0, 0]], V[F[0, 2]] - V[F[0, 0]])
    if n @ (V[F[0, 0]] - P[0]) < 0:
        F = F[:, ::-1]
    return V, F


def _rotz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def head_with_folds(ict, *, gap=None, fingers: int = 4, eyelids: bool = True, hands: int = 2):
    """The ICT head (face, mouth bag, teeth, tongue, eyes) plus fingers and eyelid folds, one piece with the face.

    Parameters
    ----------
    ict : ICTModel
        The model; positions in its units (centimetres times ``ict.scale``).
    gap : float, optional
        Distance between the facing surfaces of every fold, model units (default 0.4 mm).
    fingers : int
        Fingers per hand (U-tubes, 8 cm long, 8 mm radius, next to one another).
    eyelids : bool
        Add two closed eyelid folds (flat U-tubes, 3.5 cm wide) in front of the eyes.
    hands : int
        0, 1 (left of the head only: the mesh is no longer mirror-symmetric) or 2.

    Returns
    -------
    V : (n,3) float64
        Positions, model units; the first ``len(ict.neutral)`` are ICT's, in its order.
    F : (f,3) int64
        Triangles; the first ``len(ict.faces)`` are ICT's.
    fold_vertices : (n,) bool
        The added fold vertices.
    """
    cm = float(ict.scale)  # model units per centimetre
    gap = 0.04 * cm if gap is None else float(gap)
    V0 = np.asarray(ict.neutral, dtype=np.float64)
    F0 = np.asarray(ict.faces, dtype=np.int64)
    face = ict.part_vertex_mask("M_Face")
    anchor = int(np.flatnonzero(face)[np.argmin(V0[face, 1])])  # a face vertex under the chin
    parts_V, parts_F = [V0], [F0]
    bridges = []
    n = len(V0)

    def add(Vp, Fp):
        nonlocal n
        parts_V.append(Vp)
        parts_F.append(Fp + n)
        bridges.append([anchor, n, n + 1])  # a thin triangle joins the fold to the head
        n += len(Vp)

    mouth_y = float(V0[face, 1].min() + 0.3 * np.ptp(V0[face, 1]))
    for side in ([-1, 1] if hands == 2 else [-1] if hands == 1 else []):
        for k in range(fingers):
            Vt, Ft = u_tube(8.0 * cm, 0.8 * cm, gap, n_around=24, n_along=90, n_bend=20)
            # point away from the head along x, fingers stacked along z (front-back)
            Vt = Vt @ _rotz(0 if side > 0 else 180).T
            Vt += np.array([side * 14.0 * cm, mouth_y, (k - fingers / 2) * 3.8 * cm])
            add(Vt, Ft)
    if eyelids:
        for side in (-1, 1):
            Vt, Ft = u_tube(3.0 * cm, 0.25 * cm, gap, n_around=20, n_along=110, n_bend=16)
            # lying flat: arms one above the other (contact along y), width along x, in front of the eye
            Vt[:, 0] = side * (Vt[:, 0] + 1.2 * cm)
            Vt += np.array([0.0, mouth_y + 6.0 * cm, float(V0[:, 2].max()) + 1.0 * cm])
            if side < 0:
                Ft = Ft[:, ::-1]  # mirrored: keep the normals outward
            add(Vt, Ft)
    V = np.vstack(parts_V)
    F = np.vstack(parts_F + [np.asarray(bridges, dtype=np.int64).reshape(-1, 3)])
    folds = np.zeros(len(V), dtype=bool)
    folds[len(V0):] = True
    return V, F, folds
