"""A creature for retargeting tests, benchmarks and demos: a face with a widened mouth.

The lip-sync heuristic (Bhat et al. 2013, §5.1) matters when the creature's
mouth is much wider than the actor's; :func:`widen_mouth` makes such a
creature from the actor's own mesh (same topology) by a smooth, one-to-one
warp around the mouth.
"""

from __future__ import annotations

import numpy as np

from ..core.geometry.axes import unit_axis

__all__ = ["widen_mouth"]


def widen_mouth(vertices, center, *, factor: float = 1.6, sigma=(0.022, 0.015, 0.02), lateral=(1.0, 0.0, 0.0)):
    """A creature made from a face by a smooth warp that widens the mouth.

    ``x' = x + (factor - 1) * g(x) * ((x - c) . l) l`` with the Gaussian falloff
    ``g = exp(-1/2 sum_k ((x - c)_k / sigma_k)^2)`` around the mouth centre
    ``c``: points near the mouth move apart along ``l`` (the mouth's width
    axis), far points do not move. The warp is one-to-one for
    ``factor < 1 + e^1.5 / 2`` (about 3.2).

    Parameters
    ----------
    vertices : (V,3) array_like
        Face positions, scene units.
    center : (3,) array_like
        Mouth centre, scene units.
    factor : float
        Stretch at the centre (1.6: the mouth corners move out by roughly a
        third of the mouth width on ICT in metres with the default sigma).
    sigma : (3,) float
        Falloff radii along x, y, z, scene units (defaults for ICT in metres).
    lateral : (3,) float
        Width axis of the mouth (ICT: +X).

    Returns
    -------
    (V,3) float64 ndarray
    """
    X = np.asarray(vertices, dtype=np.float64)
    c = np.asarray(center, dtype=np.float64).reshape(3)
    l = unit_axis(lateral)
    d = X - c
    g = np.exp(-0.5 * ((d / np.asarray(sigma, dtype=np.float64)) ** 2).sum(axis=1))
    return X + (float(factor) - 1.0) * (g * (d @ l))[:, None] * l[None, :]
