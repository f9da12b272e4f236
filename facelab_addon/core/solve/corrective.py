"""Per-frame out-of-subspace corrective on top of the blendshape fit (Bhat et al. 2013, §4.3).

"High fidelity facial animation capture and retargeting with contours": the
rig cannot reach every expression, so each frame gets a corrective ``ΔV``
minimising the cotangent-Laplacian energy of ``ΔV`` (weight 1) plus the 2D
marker (1), 3D bundle (1), 2D contour (0.5) and 3D eyelid curve (0.5)
residuals on ``V_blend + ΔV``, with the mesh boundary held fixed: a linear
least-squares problem solved with the shared
``core.geometry.deform.LaplacianDeformer`` (factored once, per-frame solves
reuse the factor).

Implementation notes (deviations, all documented in docs/solve.md):

* The 2D terms use the linear form of a pixel residual: the distance (scene
  units) of the surface point to the camera ray through the pixel
  (``PointConstraints.rays``); ``pixel_units=True`` measures it in pixels.
  Contour points default to the distance to the plane through the ray and
  the curve's image tangent (``contour_metric='plane'``).
* A small ``damping |ΔV|^2`` keeps the corrective local.

Conventions: vertices (V,3) float64 scene units; pixels top-left origin,
y down; cameras ``core.capture.camera.Camera`` (OpenCV).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..capture.markers import SurfacePoints
from ..errors import FaceLabError
from ..geometry.deform import LaplacianDeformer, PointConstraints
from ..geometry.laplacian import cotangent_laplacian
from ..geometry.linsolve import small_dense_threads
from ..geometry.mesh import edge_faces, grow_region, validate_mesh, vertex_adjacency
from .blendshape_solve import check_cameras

__all__ = ["CorrectiveParams", "OutOfSubspaceCorrective", "lip_band", "LIP_BAND_RINGS"]

#: Edge rings around the mouth loops (lip weld to lip fronts) that :func:`lip_band` adds.
LIP_BAND_RINGS = 2


def lip_band(faces, loops, n_vertices: int, rings: int = LIP_BAND_RINGS) -> np.ndarray:
    """(V,) bool: the lips, where the lip passes of the corrective may act.

    The mouth's candidate contour loops (``loops.mouth``: from the lip weld
    to the lip fronts) grown by ``rings`` edge rings. Topological, so it does
    not depend on the scene's units or the face's size.

    Parameters
    ----------
    faces : (F,3) int
    loops : ContourLoops
    n_vertices : int
    rings : int
    """
    m = np.zeros(int(n_vertices), bool)
    for v in getattr(loops, "mouth", None) or []:
        m[np.asarray(v, np.int64).ravel()] = True
    if not m.any():
        raise FaceLabError("The contour loops have no mouth loops; a lip band needs them (build the loops with "
                           "contour_loops on a mesh with an open mouth, or give no lip band).")
    return grow_region(m, vertex_adjacency(np.asarray(faces, np.int64), int(n_vertices)), int(rings))


@dataclass(frozen=True)
class CorrectiveParams:
    """Options of the out-of-subspace corrective (:class:`OutOfSubspaceCorrective`).

    All weights are dimensionless factors on squared scene-unit lengths (the
    cotangent Laplacian ``|L ΔV|``, the ray / plane distances and ``|ΔV|``;
    squared pixels with ``pixel_units``), so their balance does not depend on
    the scene scale.

    Energy weights
    --------------
    marker_weight, bundle_weight, contour_weight, eyelid_weight, laplacian_weight : float
        Weights of the 2D marker rays, 3D bundles, 2D contour points, 3D
        eyelid targets and ``|L ΔV|^2`` (paper: 1, 1, 0.5, 0.5, 1).

    Damping
    -------
    damping : float
        Weight of ``|ΔV|^2`` (not in the paper, whose energy has only the
        Laplacian): keeps the corrective local. With the Laplacian alone a
        constraint that the rig cannot meet (an eyelid target, a lip
        silhouette) bends the whole free surface, since the marker rays pin
        it only sideways, and the error grows away from the eyes and mouth.
        The default keeps the correction near its constraints; 0 is the
        paper's energy. Inside the corrective's ``region``: ``region_damping``.
    region_damping : float
        Damping inside the ``region`` (not in the paper; the default is
        chosen on the tuning captures): stronger than ``damping`` so the lip
        and lid corrections stay near the contours instead of spilling onto
        the outer lips. Outside, ``damping`` stays low so that what the
        markers see beyond the rig (a cheek puff the rig lacks) is still
        corrected.

    2D terms
    --------
    contour_metric : {'plane', 'ray'}
        How a 2D contour point is tied to its tracked pixel. ``'ray'``: the
        distance to the pixel's camera ray (the paper's Eq. 1 in 3D).
        ``'plane'``: the distance to the plane through the ray and the
        curve's image tangent, i.e. the silhouette residual along the curve
        normal only. That plane is the surface's tangent plane at the true
        occluding contour, so it stays right when the rig's silhouette sits
        on a neighbouring edge ring or at another depth, where pulling the
        rig's ring point onto the ray (from two cameras: onto the rays'
        intersection, off the surface) bends the lip.
    pixel_units : bool
        False (the paper's form): 2D marker / contour terms are scene-unit
        distances to the camera rays. True: the distances are converted to
        pixels (times ``f / depth``), which weights the 2D terms
        ~(f/depth)^2 more: tighter contours, but the corrective then also
        fits the marker noise.

    Lip passes
    ----------
    lip_contour_weight, lip_damping : float
        The 2D contour weight and the damping of
        :meth:`OutOfSubspaceCorrective.lip_band_solve` (not in the paper; the
        first pass keeps ``contour_weight`` and ``region_damping``). A
        heavier contour term with a stiffer damping takes the lip rim onto
        the tracked line while keeping the correction on the rim's few rings
        (chosen on the tuning captures, see docs/solve.md).

    Raises
    ------
    FaceLabError
        An unknown ``contour_metric``; ``region_damping``, ``lip_contour_weight``
        or ``lip_damping`` negative or not finite.
    """

    marker_weight: float = 1.0
    bundle_weight: float = 1.0
    contour_weight: float = 0.5
    eyelid_weight: float = 0.5
    laplacian_weight: float = 1.0
    damping: float = 0.01
    region_damping: float = 0.03
    contour_metric: str = "plane"
    pixel_units: bool = False
    lip_contour_weight: float = 8.0
    lip_damping: float = 0.3

    def __post_init__(self):
        if self.contour_metric not in ("plane", "ray"):
            raise FaceLabError(f"contour_metric must be 'plane' or 'ray', got {self.contour_metric!r}.")
        for nm in ("region_damping", "lip_contour_weight", "lip_damping"):
            val = float(getattr(self, nm))
            if not (np.isfinite(val) and val >= 0):
                raise FaceLabError(f"{nm} must be a non-negative number, got {val!r}.")


class OutOfSubspaceCorrective:
    """Per-frame out-of-subspace corrective ``ΔV`` (Bhat et al. 2013, §4.3).

    Minimises ``laplacian_weight |L ΔV|^2`` (cotangent Laplacian of the
    neutral) plus ``damping |ΔV|^2`` plus the marker-ray, bundle, contour and
    eyelid 3D terms on ``V_blend + ΔV``, with ``ΔV = 0`` on ``boundary``.
    Factored once here; per-frame solves reuse the factor and the cached
    Woodbury columns.

    Units: ``L`` has dimensionless cotangent weights, so ``|L ΔV|``, the
    ray / plane distances and ``|ΔV|`` are all scene-unit lengths and the
    weights' balance does not depend on the scene scale (centimetres on
    ICT-FaceKit, metres elsewhere). It does depend on the mesh resolution:
    ``|L ΔV|`` of a smooth displacement shrinks with the edge length squared,
    so ``damping`` (and the data weights) gain relative to the Laplacian on
    denser meshes.

    Parameters
    ----------
    neutral : (V,3) float
        Rest mesh, scene units.
    faces : (F,3) int
    cameras : list of Camera
    markers, bundles : SurfacePoints or None
        As for :class:`BlendshapeSolver`.
    params : CorrectiveParams
        Energy weights, damping and the contour metric.
    boundary : (V,) bool, optional
        Vertices held fixed (``ΔV = 0``). Default: the mesh border plus every
        connected component no marker or bundle lies on.
    region : (V,) bool, optional
        Where the curves inform the face (the mouth and the eyes:
        ``blendshape_solve.contour_region``), damped by
        ``params.region_damping``; None: ``params.damping`` everywhere.
    lip_band : (V,) bool, optional
        Where :meth:`lip_band_solve` and :meth:`lip_line_pass` may act
        (:func:`lip_band`): a second, small factor (the band's vertices
        only, the rest held), so these passes cannot move the face outside
        the lips and cost a fraction of a full solve. None: they act on the
        whole free surface (the full factor).
    warm_vertices : (k,) int, optional
        Vertices whose Woodbury columns are computed up front (e.g. all
        candidate contour-loop vertices), so the first frames are not slower.
    """

    def __init__(self, neutral, faces, cameras, markers: SurfacePoints | None, bundles: SurfacePoints | None, *,
                 params: CorrectiveParams = CorrectiveParams(), boundary=None, region=None, lip_band=None,
                 warm_vertices=None):
        V0, F = validate_mesh(neutral, faces, name="neutral mesh")
        self.params = params
        self.neutral, self.faces = V0, F
        self.cameras = check_cameras(cameras)
        self.markers, self.bundles = markers, bundles
        self.marker_weight = float(params.marker_weight)
        self.bundle_weight = float(params.bundle_weight)
        self.contour_weight = float(params.contour_weight)
        self.eyelid_weight = float(params.eyelid_weight)
        self.pixel_units = bool(params.pixel_units)
        self.contour_metric = params.contour_metric
        n = len(V0)
        if boundary is None:
            boundary = self.default_boundary(V0, F, markers, bundles)
        boundary = np.asarray(boundary, bool)
        if boundary.shape != (n,):
            raise FaceLabError(f"The boundary mask must have one entry per vertex ({n}), got {boundary.shape}.")
        self.boundary = boundary
        L = cotangent_laplacian(V0, F)
        t0 = time.perf_counter()
        self.damping = float(params.damping)
        self.region_damping = float(params.region_damping)
        pos = self.damping
        if region is not None:
            region = np.asarray(region, bool)
            if region.shape != (n,):
                raise FaceLabError(f"The region mask must have one entry per vertex ({n}), got {region.shape}.")
            pos = np.where(region, self.region_damping, self.damping)
        self.region = region
        laplacian_weight = float(params.laplacian_weight)
        self.deformer = LaplacianDeformer(L, lambda_reg=laplacian_weight, pos_weights=pos, pinned=boundary)
        self.lip_band, self.band_deformer = None, None
        self.lip_contour_weight, self.lip_damping = float(params.lip_contour_weight), float(params.lip_damping)
        if lip_band is not None:
            lip_band = np.asarray(lip_band, bool)
            if lip_band.shape != (n,):
                raise FaceLabError(f"The lip band mask must have one entry per vertex ({n}), got {lip_band.shape}.")
            self.lip_band = lip_band & ~boundary
            if self.lip_band.any():
                self.band_deformer = LaplacianDeformer(L, lambda_reg=laplacian_weight,
                                                       pos_weights=self.lip_damping, pinned=~self.lip_band)
        self.factor_time_s = time.perf_counter() - t0
        if warm_vertices is not None:
            wv = np.unique(np.asarray(warm_vertices, np.int64))
            wv = wv[~boundary[wv]]
            if len(wv):
                self.deformer.solve(V0, constraints=PointConstraints.points(wv, V0[wv], 1e-3))

    @staticmethod
    def default_boundary(vertices, faces, markers=None, bundles=None) -> np.ndarray:
        """(V,) bool: mesh-border vertices plus components no marker/bundle touches."""
        from scipy.sparse.csgraph import connected_components

        n = len(vertices)
        edges, ef = edge_faces(faces)
        b = np.zeros(n, bool)
        b[edges[(ef < 0).any(axis=1)].ravel()] = True
        _, lab = connected_components(vertex_adjacency(faces, n), directed=False)
        used = np.zeros(n, bool)
        for p in (markers, bundles):
            if p is not None and len(p):
                used[p.vertices[p.bound].ravel()] = True
        keep = np.isin(lab, np.unique(lab[used])) if used.any() else np.ones(n, bool)
        return b | ~keep

    def _px_scale(self, cam, X):
        """(n,) squared pixels per squared scene unit at points X, or 1 without ``pixel_units``."""
        if not self.pixel_units:
            return 1.0
        z = np.maximum(cam.depth(X), 1e-12)
        f = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        return (f / z) ** 2

    def constraints(self, vertices_blend, markers_px, bundles, correspondences,
                    contour_weight: float | None = None) -> PointConstraints | None:
        """The frame's point constraints (marker rays, bundles, contour rays, eyelid points).

        ``contour_weight`` overrides the 2D contour weight (default: ``params.contour_weight``).
        """
        Vb = np.asarray(vertices_blend, float)
        cw = self.contour_weight if contour_weight is None else float(contour_weight)
        items = []
        if self.markers is not None and markers_px is not None:
            mp = np.asarray(markers_px, float)
            if mp.ndim == 2:
                mp = mp[None]
            ok = self.markers.bound
            for c, cam in enumerate(self.cameras):
                sel = np.flatnonzero(np.isfinite(mp[c]).all(axis=1) & cam.in_frame(mp[c]) & ok)
                if len(sel):
                    o, d = cam.rays(mp[c, sel])
                    s = self.marker_weight * self._px_scale(cam, self.markers.subset(sel).evaluate(Vb))
                    items.append(PointConstraints.rays(self.markers.vertices[sel], o, d, s,
                                                       bary=self.markers.bary[sel]))
        if self.bundles is not None and bundles is not None:
            b = np.asarray(bundles, float).reshape(-1, 3)
            sel = np.flatnonzero(np.isfinite(b).all(axis=1) & self.bundles.bound)
            if len(sel):
                items.append(PointConstraints.points(self.bundles.vertices[sel], b[sel], self.bundle_weight,
                                                     bary=self.bundles.bary[sel]))
        for cc in correspondences or []:
            v = np.asarray(cc.vertices, np.int64)
            bb = np.asarray(cc.bary, float)
            if getattr(cc, "pixels", None) is not None and cc.camera >= 0:
                cam = self.cameras[cc.camera]
                o, d = cam.rays(np.asarray(cc.pixels, float))
                s = cw * self._px_scale(cam, np.einsum("ck,ckd->cd", bb, Vb[v]))
                if self.contour_metric == "plane" and len(v) >= 2:
                    items.append(PointConstraints(v, bb, o, _contour_planes(d), s))
                else:
                    items.append(PointConstraints.rays(v, o, d, s, bary=bb))
            elif getattr(cc, "targets", None) is not None:
                items.append(PointConstraints.points(v, np.asarray(cc.targets, float), self.eyelid_weight, bary=bb))
        return PointConstraints.concat(items)

    def solve(self, vertices_blend, markers_px, bundles=None, correspondences=None) -> np.ndarray:
        """The corrective ``ΔV`` (V,3), scene units (zero on the boundary)."""
        Vb = np.asarray(vertices_blend, dtype=np.float64)
        if Vb.shape != self.neutral.shape:
            raise FaceLabError(f"Expected {len(self.neutral)} vertices, got {Vb.shape}; the topology changed.")
        C = self.constraints(Vb, markers_px, bundles, correspondences)
        if C is None:
            return np.zeros_like(Vb)
        with small_dense_threads(1):
            X = self.deformer.solve(Vb, Vb, C)
        return X - Vb

    def lip_band_solve(self, vertices_blend, delta, markers_px, bundles=None, correspondences=None) -> np.ndarray:
        """Solve the corrective again inside the lip band, the rest held at ``delta``; returns the new ``ΔV``.

        The energy of :meth:`solve` (Laplacian and damping of ``ΔV``, all
        data terms) with the 2D contour weight ``lip_contour_weight`` and the
        damping ``lip_damping``, minimised over the :attr:`lip_band` vertices
        only, with every other vertex held at ``V_blend + delta``. Used after
        matching the contours again on ``V_blend + delta`` (the first
        correspondence was built on the rig mesh, where a steep view's
        occluding contour can sit several edge rings from the truth's): §4.2's
        alternation of correspondence and solve, applied to the lips alone.
        Without a lip band this is :meth:`solve` (the whole surface).

        Parameters
        ----------
        vertices_blend : (V,3) float
            The rig's fitted mesh, scene units.
        delta : (V,3) float
            The current ``ΔV``, scene units.
        markers_px, bundles, correspondences
            As for :meth:`solve` (correspondences matched on ``V_blend + delta``).

        Returns
        -------
        (V,3) float64
            ``ΔV``, equal to ``delta`` outside the band.
        """
        if self.band_deformer is None:
            return self.solve(vertices_blend, markers_px, bundles, correspondences)
        Vb = np.asarray(vertices_blend, dtype=np.float64)
        dV = np.asarray(delta, dtype=np.float64)
        C = self.constraints(Vb, markers_px, bundles, correspondences, contour_weight=self.lip_contour_weight)
        if C is None:
            return dV.copy()
        anchor = Vb + np.where(self.lip_band[:, None], 0.0, dV)  # damping towards V_blend; the rest held
        with small_dense_threads(1):
            X = self.band_deformer.solve(anchor, Vb, C)
        return X - Vb

    def off_the_line(self, vertices, correspondences, curves, curve_px: float) -> bool:
        """Whether any 2D contour's RMS pixel distance to its tracked curve on ``vertices`` is above ``curve_px``.

        Parameters
        ----------
        vertices : (V,3) float
            Mesh, scene units.
        correspondences : list of CurveCorrespondence
        curves : list of TrackedCurve
        curve_px : float
            Pixels.
        """
        from .matching import contour_curve_distance

        for cc in correspondences or []:
            if getattr(cc, "pixels", None) is None or cc.camera < 0:
                continue
            r = contour_curve_distance(vertices, self.cameras, [cc], curves)
            if len(r) and np.sqrt(np.mean(r ** 2)) > float(curve_px):
                return True
        return False

    def lip_line_pass(self, vertices_blend, delta, markers_px, bundles, correspondences, curves, *,
                      threshold_px: float, curve_threshold_px: float) -> np.ndarray:
        """A second corrective pass on the 2D contour points still off their curve; returns the new ``ΔV``.

        The first pass (:meth:`solve`) stops short of a curve the rig misses by
        a lot: its damping and Laplacian pull every correction back towards
        ``V_blend``. This pass starts from ``X1 = V_blend + ΔV``, penalises
        only the increment (Laplacian and damping of ``X - X1``), holds the
        markers and bundles, and adds the contour terms of the points whose
        pixel distance to their tracked curve on ``X1`` is above
        ``threshold_px`` (points already on the line are left out, so they are
        not pulled twice). With a :attr:`lip_band` only the band's vertices
        move (the face outside the lips cannot change). Not in the paper.

        Parameters
        ----------
        vertices_blend : (V,3) float
            The rig's fitted mesh, scene units.
        delta : (V,3) float
            The first pass's ``ΔV``, scene units.
        markers_px, bundles
            As for :meth:`solve`.
        correspondences : list of CurveCorrespondence
            Matched on ``V_blend + ΔV`` (re-match before calling).
        curves : list of TrackedCurve
            The frame's tracked curves (to measure the distance to the line).
        threshold_px : float
            Points within this many pixels of their curve get no term
            (``PerformanceParams.lip_line_threshold_px``).
        curve_threshold_px : float
            Curves whose RMS pixel distance on ``V_blend + ΔV`` is at most
            this get no term (``PerformanceParams.lip_line_curve_px``).

        Returns
        -------
        (V,3) float64
            ``ΔV`` after the pass (zero on the boundary).
        """
        from .matching import contour_curve_distance

        Vb = np.asarray(vertices_blend, dtype=np.float64)
        X1 = Vb + np.asarray(delta, dtype=np.float64)
        items = [self.constraints(X1, markers_px, bundles, [])]
        for cc in correspondences or []:
            if getattr(cc, "pixels", None) is None or cc.camera < 0:
                continue
            r = contour_curve_distance(X1, self.cameras, [cc], curves)
            if len(r) != len(cc.vertices):
                continue
            keep = r > float(threshold_px)
            if not keep.any() or np.sqrt(np.mean(r ** 2)) <= float(curve_threshold_px):
                continue
            C = self.constraints(X1, None, None, [cc])  # planes from the whole curve, then the points kept
            items.append(PointConstraints(C.vertices[keep], C.bary[keep], C.targets[keep], C.metrics[keep],
                                          C.strength[keep]))
        C = PointConstraints.concat(items)
        if C is None:
            return X1 - Vb
        deformer = self.deformer if self.band_deformer is None else self.band_deformer
        with small_dense_threads(1):
            X = deformer.solve(X1, X1, C)
        return X - Vb


def _contour_planes(d):
    """(c,3,3) metrics ``n n^T`` of the planes through a curve's camera rays and the curve tangent.

    ``d`` (c,3): the rays' directions, in curve order. The plane through the
    camera centre that contains the ray of a curve pixel and the curve's
    image tangent there is the surface's tangent plane at the true occluding
    contour point (the ray grazes the surface along the contour), so a
    nearby surface point belongs on it to second order, whichever edge ring
    the silhouette is on and whatever the depth along the ray: the distance
    to this plane is the silhouette residual along the curve normal.
    """
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    tan = np.empty_like(d)
    tan[1:-1] = d[2:] - d[:-2]
    tan[0] = d[1] - d[0]
    tan[-1] = d[-1] - d[-2]
    n = np.cross(d, tan)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    bad = nn[:, 0] < 1e-12
    n = n / np.maximum(nn, 1e-300)
    P = n[:, :, None] * n[:, None, :]
    if bad.any():  # repeated pixels: fall back to the ray distance there
        P[bad] = np.eye(3)[None] - d[bad, :, None] * d[bad, None, :]
    return P
