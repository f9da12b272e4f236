"""Jaw articulation for local geometric indexing (Cong, Lan and Fedkiw 2019, §6, Eq. 2).

:class:`JawRig` is a hinge joint with linear-blend-skinning weights. With a
jaw rig the indexer unskins the dataset shapes
(``b* = T(theta_n)^-1 (x0 + b_n) - x0``, :meth:`JawRig.unskin_shape`), unskins
the bundles of every frame with the frame's jaw parameters (at the bundle's
skinning weight, :meth:`JawRig.unskin`) and skins the blend back
(:meth:`JawRig.skin`). :meth:`JawRig.fit_pose` estimates a dataset shape's jaw
pose from the vertices that follow the jaw rigidly.

Jaw parameters are ``(angle, tx, ty, tz)`` (4,) (radians, scene units) or a
rigid (4,4) matrix ``[R t]``. Positions are (N,3) in scene units; skinning
weights are unitless, in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DatasetError
from ..geometry.inv3 import inv3
from ..geometry.rigid import rigid_fit

__all__ = ["JawRig"]


def _axis_angle(axis, angle):
    """(...,3,3) rotation matrices about a unit ``axis`` (3,) by ``angle`` (...,) radians."""
    a = np.asarray(axis, dtype=np.float64)
    th = np.asarray(angle, dtype=np.float64)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    s, c = np.sin(th)[..., None, None], np.cos(th)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


@dataclass
class JawRig:
    """A jaw joint with linear-blend-skinning weights (Cong et al. 2019, §6).

    The jaw transform for parameters ``theta = (angle, tx, ty, tz)`` rotates
    by ``angle`` radians about ``axis`` through ``pivot`` and then translates
    by ``(tx, ty, tz)`` (scene units): ``T(x) = R (x - pivot) + pivot + t``.
    ``theta`` may also be a general rigid jaw pose, a (4,4) matrix ``[R t]``
    (for example a jaw bone's motion from its rest pose, in the mesh's
    space). Vertex ``v`` follows ``(1 - w_v) x + w_v T(x)`` (linear blend
    skinning with the skull, which stays put).

    Attributes
    ----------
    pivot : (3,) float64
        A point on the hinge axis, scene units.
    axis : (3,) float64
        Unit hinge axis.
    weights : (V,) float64
        Skinning weight of the jaw at every vertex, in [0, 1].
    """

    pivot: np.ndarray
    axis: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        self.pivot = np.asarray(self.pivot, dtype=np.float64).reshape(3)
        a = np.asarray(self.axis, dtype=np.float64).reshape(3)
        self.axis = a / np.linalg.norm(a)
        self.weights = np.clip(np.asarray(self.weights, dtype=np.float64).ravel(), 0.0, 1.0)

    def transform(self, theta):
        """Rigid jaw transform.

        Parameters
        ----------
        theta : (4,) or (4,4) array_like
            ``(angle rad, tx, ty, tz)``, or a rigid matrix.

        Returns
        -------
        R : (3,3) float64
        t : (3,) float64
            ``T(x) = R x + t``, scene units.
        """
        th = np.asarray(theta, dtype=np.float64)
        if th.shape == (4, 4):
            return th[:3, :3].copy(), th[:3, 3].copy()
        th = th.reshape(4)
        R = _axis_angle(self.axis, th[0])
        return R, self.pivot - R @ self.pivot + th[1:]

    def _affine(self, theta, w):
        R, t = self.transform(theta)
        w = np.asarray(w, dtype=np.float64)
        A = (1 - w)[:, None, None] * np.eye(3) + w[:, None, None] * R
        return A, w[:, None] * t

    def skin(self, X, theta, weights=None):
        """Linear blend skinning of points.

        Parameters
        ----------
        X : (N,3) array_like
            Points, scene units (default: one per mesh vertex).
        theta : (4,) array_like
            Jaw parameters.
        weights : (N,) array_like, optional
            Skinning weights of the points (default ``self.weights``).

        Returns
        -------
        (N,3) float64 ndarray
        """
        X = np.asarray(X, dtype=np.float64)
        w = self.weights if weights is None else np.asarray(weights, dtype=np.float64)
        R, t = self.transform(theta)
        # (X R^T + t - X) without BLAS: a (V,3)x(3,3) product would wake multithreaded BLAS, whose
        # spinning threads cost more than the product on a busy machine
        D = X[:, :1] * (R[:, 0] - [1, 0, 0]) + X[:, 1:2] * (R[:, 1] - [0, 1, 0]) + X[:, 2:] * (R[:, 2] - [0, 0, 1]) + t
        return X + w[:, None] * D

    def unskin(self, X, theta, weights=None):
        """Invert :meth:`skin`: ``T_v(theta)^-1 x`` at every point.

        Parameters
        ----------
        X : (N,3) array_like
            Skinned points, scene units.
        theta : (4,) array_like
        weights : (N,) array_like, optional

        Returns
        -------
        (N,3) float64 ndarray
        """
        X = np.asarray(X, dtype=np.float64)
        w = self.weights if weights is None else np.asarray(weights, dtype=np.float64)
        A, b = self._affine(theta, w)
        inv = inv3(A)
        return np.einsum("nij,nj->ni", inv, X - b)

    def fit_pose(self, shape, neutral, *, min_weight: float = 0.99):
        """Estimate a shape's jaw pose: the rigid motion of its jaw vertices (Kabsch fit).

        Every dataset shape needs its jaw parameters (§6); the vertices that
        follow the jaw rigidly (skinning weight >= ``min_weight``: lower teeth,
        chin) give them.

        Parameters
        ----------
        shape, neutral : (V,3) array_like
            Positions, scene units.
        min_weight : float

        Returns
        -------
        (4,4) float64 ndarray
            Rigid matrix ``[R t]`` (identity when the jaw did not move).

        Raises
        ------
        DatasetError
            When fewer than 3 vertices follow the jaw rigidly.
        """
        A = np.asarray(neutral, dtype=np.float64)
        Bp = np.asarray(shape, dtype=np.float64)
        m = self.weights >= min_weight
        if m.sum() < 3:
            raise DatasetError(
                f"Only {int(m.sum())} vertices follow the jaw rigidly (weight >= {min_weight}); paint the jaw "
                "vertex group to 1 on the lower teeth and chin."
            )
        R, t = rigid_fit(A[m], Bp[m])
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = t
        return M

    def unskin_shape(self, shape, neutral, theta):
        """Unskinned delta of a dataset shape (Eq. 2): ``T(theta)^-1 (x0 + b) - x0``.

        Parameters
        ----------
        shape : (V,3) array_like
            The dataset shape ``x0 + b`` (positions), scene units.
        neutral : (V,3) array_like
        theta : (4,) array_like
            The shape's jaw parameters.

        Returns
        -------
        (V,3) float64 ndarray
            ``b*``, scene units.
        """
        return self.unskin(shape, theta) - np.asarray(neutral, dtype=np.float64)
