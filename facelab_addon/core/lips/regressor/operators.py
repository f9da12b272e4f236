"""The fixed operators of a lip regressor: region indexing, the lip Poisson system and the patches.

Dinev et al. 2018, "User-Guided Lip Correction for Facial Performance Capture", §4: predicted
inner-lip gradients become positions by the gradient-domain least squares
``min_x Σ_t a_t ||∇_t x - F_t||²`` over the lip triangles (a cotangent Laplacian), with the lip
border vertices held at their captured positions (Dirichlet). Its interior block is factored
once, here. Everything in :class:`.state.LipOperators` depends on the rest mesh and the regions
only, never on the training frames. Positions are scene units.
"""

from __future__ import annotations

import numpy as np

from ...errors import FaceLabError
from ...geometry.gradients import rest_inverse
from ...geometry.laplacian import poisson_operator
from ...geometry.linsolve import SPDFactor
from ..regions import region_border, validate_regions
from .patches import lip_patches
from .state import LipOperators

__all__ = ["lip_operators"]


def lip_operators(R, F, mouth_faces, lip_faces, *, center, patches, input_radius, backend) -> LipOperators:
    """Validate the regions and build the operators of a regressor on them.

    Parameters
    ----------
    R : (V,3) float64 ndarray
        Rest positions, scene units (checked, :func:`.guards.checked_mesh`).
    F : (F,3) int64 ndarray
        Triangles (checked).
    mouth_faces, lip_faces : (m,), (n,) int array_like
        Triangles of the trusted mouth and of the inner-lip region.
    center : {"rest", None}
        Feature centring (:class:`.state.Settings`).
    patches : int
        Number of local regressions (:func:`.patches.lip_patches`).
    input_radius : float or None
        Geodesic reach of each patch's mouth input, scene units.
    backend : {"auto", "cholespy", "splu"}
        Sparse factorisation of the Poisson system.

    Returns
    -------
    LipOperators

    Raises
    ------
    RegionError, MeshError
        Bad regions or degenerate triangles (:func:`..regions.validate_regions`, ``rest_inverse``).
    FaceLabError
        When every lip vertex is on the border (nothing to solve for).
    """
    mouth_faces, lip_faces = validate_regions(F, mouth_faces, lip_faces, len(R), R)
    mouth_tris, lip_tris = F[mouth_faces], F[lip_faces]
    mouth_rinv = rest_inverse(R, mouth_tris, name="mouth region")
    mouth_P = np.matmul(mouth_rinv, mouth_rinv.transpose(0, 2, 1))  # ||D R^-1||² = <DᵀD, P>
    lip_rinv = rest_inverse(R, lip_tris, name="inner-lip region")
    mouth_verts, inv = np.unique(mouth_tris, return_inverse=True)
    mouth_local = inv.reshape(-1, 3)
    lip_verts, inv = np.unique(lip_tris, return_inverse=True)
    lip_local = inv.reshape(-1, 3)
    used = np.union1d(mouth_verts, lip_verts)  # vertices read per frame
    # the largest plausible correction: the extent of the mouth and lip regions (scene units)
    mouth_size = float(np.ptp(R[used], axis=0).max())

    # Poisson system on the lip triangles, Dirichlet on the border: interior block factored once
    L, D = poisson_operator(R, F, lip_faces)
    border = region_border(F, lip_faces, len(R))
    interior = np.setdiff1d(lip_verts, border)
    if interior.size == 0:
        raise FaceLabError(
            "Every inner-lip vertex is on the border, so nothing would be predicted; widen 'FL_lips' "
            "(Auto Regions with a larger lip width)."
        )
    L = L.tocsr()
    L_II = L[interior][:, interior].tocsc()
    L_IB = L[interior][:, border].tocsr()
    D_I = D[interior].tocsr()  # (nI, 3n)
    try:
        factor = SPDFactor(L_II, backend, what="lip Poisson system")
    except Exception as e:  # pragma: no cover - validated regions make L_II SPD
        raise FaceLabError(
            f"The inner-lip Poisson system could not be factored ({e}); check for degenerate or "
            "disconnected triangles in 'FL_lips'."
        ) from e
    # divergence of the identity gradients: the constant part for center="rest"
    ident = np.broadcast_to(np.eye(3), (len(lip_faces), 3, 3))
    b_ident = D_I @ ident.transpose(0, 2, 1).reshape(-1, 3)  # (nI, 3)

    # local patches of the lip region and the divergence operator of each
    pts, spacing = lip_patches(R, F, mouth_faces, lip_faces, int(patches), input_radius)
    Dc = D_I.tocsc()
    D_patch = [Dc[:, (3 * ls[:, None] + np.arange(3)).ravel()].tocsr() for _, ls, _ in pts]
    return LipOperators(
        rest=R, faces=F, center=center, mouth_faces=mouth_faces, lip_faces=lip_faces, mouth_verts=mouth_verts,
        lip_verts=lip_verts, mouth_local=mouth_local, lip_local=lip_local, mouth_rinv=mouth_rinv, lip_rinv=lip_rinv,
        mouth_P=mouth_P, used=used, mouth_u=np.searchsorted(used, mouth_verts), mouth_size=mouth_size,
        border_vertices=border, interior_vertices=interior, iv_u=np.searchsorted(used, interior),
        bv_u=np.searchsorted(used, border), L_II=L_II, L_IB=L_IB, D_I=D_I, factor=factor, b_ident=b_ident,
        patches=pts, patch_spacing=spacing, D_patch=D_patch,
    )
