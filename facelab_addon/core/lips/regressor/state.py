"""The state of a lip regressor as plain data: its settings, its fixed operators and its fit.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance Capture", §4. A
:class:`~.lip_regressor.LipRegressor` holds one :class:`Settings`, one :class:`LipOperators`
(built once from the rest mesh and the regions, :func:`.operators.lip_operators`) and, once
fitted, one :class:`TrainedModel` (:func:`.training.train`). The functions of the other modules
of this package take these objects as arguments; nothing here computes anything. Notation:
``V`` vertices, ``m`` mouth and ``n`` inner-lip triangles, ``nv`` mouth vertices, ``nL`` lip
vertices, ``nI`` interior and ``nB`` border lip vertices, ``k`` training frames, ``R`` reduced
mouth coefficients over all patches. Positions are scene units; gradients and features are
unitless.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Settings", "LipOperators", "TrainingSet", "TrainedModel"]


@dataclass(frozen=True)
class Settings:
    """What is regressed and how (the keyword arguments of ``LipRegressor``, checked).

    Attributes
    ----------
    center : {"rest", None}
        ``"rest"``: features are gradients minus the identity; ``None``: the paper's plain gradients.
    ridge : float or "loo"
        Tikhonov weight of each reduced map (relative to the mean squared mouth singular value).
    rtol, atol : float
        Relative and absolute rank cut-offs of the thin SVDs (:func:`.reduced.thin_svd`).
    model : {"auto", "whole", "correction"}
        The regressed quantity (:mod:`.model_choice`).
    damping : bool
        Scale each frame's correction by its expected error (:func:`.model_choice.damping_weights`).
    """

    center: str | None
    ridge: Any
    rtol: float
    atol: float
    model: str
    damping: bool


@dataclass
class LipOperators:
    """Everything fixed by the rest mesh and the regions: indexing, rest-pose inverses, Poisson system, patches.

    Attributes
    ----------
    rest : (V,3) float64 ndarray
        Rest positions, scene units.
    faces : (F,3) int64 ndarray
        Triangles.
    center : {"rest", None}
        As :class:`Settings` (the operators fold the identity in when ``"rest"``).
    mouth_faces, lip_faces : (m,), (n,) int64 ndarray
        Triangles of the trusted mouth and of the inner-lip region.
    mouth_verts, lip_verts : (nv,), (nL,) int64 ndarray
        Sorted vertices of those triangles.
    mouth_local, lip_local : (m,3), (n,3) int64 ndarray
        The triangles in indices into ``mouth_verts`` and ``lip_verts``.
    mouth_rinv, lip_rinv : (m,3,3), (n,3,3) float64 ndarray
        Inverse rest shape matrices (1 / scene units).
    mouth_P : (m,3,3) float64 ndarray
        ``D_r⁻¹ D_r⁻ᵀ`` per mouth triangle: ``||D D_r⁻¹||² = <DᵀD, P>``.
    used : (nU,) int64 ndarray
        Vertices read per frame (mouth and lip vertices, sorted).
    mouth_u, iv_u, bv_u : int64 ndarray
        ``mouth_verts``, ``interior_vertices`` and ``border_vertices`` as indices into ``used``.
    mouth_size : float
        Largest extent of the mouth and lip vertices, scene units: the largest plausible correction.
    border_vertices, interior_vertices : (nB,), (nI,) int64 ndarray
        Lip vertices held at their captured positions, and those solved for.
    L_II : (nI,nI) sparse CSC, L_IB : (nI,nB) sparse CSR
        Blocks of the lip Poisson (cotangent) matrix, scene-unit areas.
    D_I : (nI, 3n) sparse CSR
        Divergence of per-triangle gradients (rows of ``Fᵀ`` stacked) on the interior vertices.
    factor : SPDFactor
        The factorised ``L_II`` (:class:`~facelab_addon.core.geometry.linsolve.SPDFactor`).
    b_ident : (nI,3) float64 ndarray
        ``D_I`` of the identity gradients (the constant term with ``center="rest"``).
    patches : list of (mouth_sel, lip_sel, weight)
        Per patch: indices into ``mouth_faces`` and ``lip_faces`` and the (n_p,) partition-of-unity
        weights of its lip triangles (:func:`.patches.lip_patches`).
    patch_spacing : float
        Spacing of the patch centres, scene units (``inf`` for one patch).
    D_patch : list of (nI, 3 n_p) sparse CSR
        ``D_I`` restricted to each patch's lip triangles.
    H : (nI,nB) float64 ndarray or None
        ``L_II⁻¹ L_IB``, computed on first use by :func:`.prediction.dense_solution`.
    """

    rest: np.ndarray
    faces: np.ndarray
    center: str | None
    mouth_faces: np.ndarray
    lip_faces: np.ndarray
    mouth_verts: np.ndarray
    lip_verts: np.ndarray
    mouth_local: np.ndarray
    lip_local: np.ndarray
    mouth_rinv: np.ndarray
    lip_rinv: np.ndarray
    mouth_P: np.ndarray
    used: np.ndarray
    mouth_u: np.ndarray
    mouth_size: float
    border_vertices: np.ndarray
    interior_vertices: np.ndarray
    iv_u: np.ndarray
    bv_u: np.ndarray
    L_II: Any
    L_IB: Any
    D_I: Any
    factor: Any
    b_ident: np.ndarray
    patches: list
    patch_spacing: float
    D_patch: list
    H: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_vertices(self) -> int:
        """``V``, the vertex count of the rest mesh."""
        return len(self.rest)


@dataclass
class TrainingSet:
    """The training features and their global span.

    Attributes
    ----------
    Y : (9m, k) float64 ndarray
        Mouth features of the training frames, one column per frame.
    X : (9n, k) float64 ndarray
        Lip features of the corrected frames.
    Xc : (9n, k) float64 ndarray or None
        Corrected minus captured lip features (None when the captured frames were not given).
    UY : (9m, r) float64 ndarray
        Orthonormal basis of ``Y`` (rank-cut, :func:`.reduced.thin_svd`).
    sigma : float
        RMS deformation of the training mouths (unitless), floored at the absolute rank cut.
    """

    Y: np.ndarray
    X: np.ndarray
    Xc: np.ndarray | None
    UY: np.ndarray
    sigma: float

    @property
    def k(self) -> int:
        """Number of training frames."""
        return self.Y.shape[1]


@dataclass
class TrainedModel:
    """A fit: the reduced maps of every patch and the prediction operators folded from them.

    Attributes
    ----------
    data : TrainingSet
        What was fitted.
    theta_bars : list of (rX, rY) float64 ndarray
        The whole-motion model's reduced map θ̄ of each patch.
    ridges_used : list of float
        The ridge weight of each patch.
    pfit : list of (U_X (9 n_p, r), θ̄ (r, rY), U_Y (9 m_p, rY))
        Per patch, the lip output per mouth coefficient of the blend.
    fit_mouth_sel : list of (m_p,) int64 ndarray
        The mouth triangles each patch reads.
    whole_weight : float
        ``α``: 1 is the whole-motion model, 0 the correction model.
    model_errors : dict of float
        Predicted RMS interior lip error of each model, scene units (``model="auto"``; else empty).
    expected_model : dict or None
        The expected-error model (:func:`.model_choice.error_model`).
    error_model : dict or None
        ``expected_model`` with ``damping``, else None (no damping).
    B : (n, 9) float64 ndarray
        The correction model's constant lip gradients, blended over patches.
    x_b : (nI, 3) float64 ndarray
        ``L_II⁻¹ D_I B``: the interior positions that constant adds, scene units.
    Zdiv : (3 nI, R) float64 ndarray
        Divergence on the interior vertices of the predicted lip gradients per unit coefficient.
    Mx, Mc : (3 nv, R), (3m, R) float64 ndarray
        The coefficients ``z = Mxᵀ X + Mcᵀ c - z_ident`` (:func:`.features.fold_coefficients`).
    z_ident : (R,) float64 ndarray
        Coefficients of the identity gradients (zeros unless ``center="rest"``).
    Mx_all, Mc_all : (3 nv, R + r + 1), (3m, R + r + 1) float64 ndarray
        ``Mx``, ``Mc`` with the global span ``U_Y`` and the identity folded beside them.
    span_ident : (r,) float64 ndarray
        ``U_Yᵀ`` of the identity gradients (zeros unless ``center="rest"``).
    cache : dict
        Operators derived from this fit on first use (:mod:`.prediction`).
    """

    data: TrainingSet
    theta_bars: list
    ridges_used: list
    pfit: list
    fit_mouth_sel: list
    whole_weight: float
    model_errors: dict
    expected_model: dict | None
    error_model: dict | None
    B: np.ndarray
    x_b: np.ndarray
    Zdiv: np.ndarray
    Mx: np.ndarray
    Mc: np.ndarray
    z_ident: np.ndarray
    Mx_all: np.ndarray
    Mc_all: np.ndarray
    span_ident: np.ndarray
    cache: dict = field(default_factory=dict, repr=False)
