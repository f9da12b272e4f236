"""Settings of a geometric indexer (Cong, Lan and Fedkiw 2019, §4-§5): one documented dataclass.

:class:`IndexerParams` groups every tuning knob of
:class:`~facelab_addon.core.lgi.indexing.indexer.GeometricIndexer`; the data
(mesh, dataset shapes, bundle binding, UVs, jaw rig) are the indexer's own
arguments. Tolerances left at ``None`` scale with the face size (the bounding
box diagonal of the vertices that have natural-neighbour weights, scene
units): :meth:`IndexerParams.merge_tolerance_at` and its siblings resolve them.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["IndexerParams"]


@dataclass(frozen=True)
class IndexerParams:
    """Tuning of local geometric indexing; the defaults are the add-on's.

    Attributes
    ----------
    nn_method : {"uv", "geodesic"} or None
        Natural-neighbour weights in UV space (§5, the paper's choice) or
        with geodesics on the mesh; ``None``: UV space when the indexer gets
        UVs, else geodesics.
    prune_tolerance : float or None
        Scene units. A shape is dropped from a bundle's point cloud when it
        moves no vertex of the bundle's natural-neighbour region by more than
        this, weighted by the bundle's weight (§4.1); a shape that moves the
        skin between bundles without moving the bundle itself stays reachable
        (it is merged into the neutral's point and costs no tetrahedra).
        ``None``: ``1e-7`` times the face size.
    merge_tolerance : float or None
        Scene units. Shapes that put a bundle within this distance of each
        other share one cloud point; the neighbouring bundles pick which of
        them to use (§5.1). ``None``: ``2e-4`` times the face size.
    neighbors : int
        Each cloud point forms tetrahedra with 3 of its ``neighbors`` nearest
        cloud points (all 4-point combinations when the cloud has at most
        ``neighbors + 1`` points); the cloud's Delaunay tetrahedra are added
        so that the tetrahedra cover its convex hull (§4).
    min_quality : float
        Unitless, 0..1. Tetrahedra whose mean-ratio quality is lower are "too
        thin" and deleted (§4.1).
    max_edge : float or None
        Scene units. Tetrahedra with a longer edge are "too large" and
        deleted (§4.1); ``None``: no limit.
    forbidden : tuple of tuples of int or str
        Flagged combinations: a tetrahedron holding all shapes of one set
        (indices into the dataset shapes, or their names) is deleted (§4.1).
    min_tets_per_point : int
        Every cloud point keeps at least this many of its best tetrahedra.
    temporal_bias : float
        Unitless. For animated bundles (§5.1) a candidate's neighbour cost is
        multiplied by ``1 + temporal_bias * (4 - shared) / 4``, where
        ``shared`` counts the shapes it shares with the previous frame's
        choice; a candidate that fits the neighbours exactly still wins.
    tie_tolerance : float or None
        Scene units. When a bundle's best candidate reproduces its neighbours
        to within this (they cannot tell candidates apart), the candidates
        are re-ranked by the shapes the moving bundles chose. ``None``:
        ``1e-5`` times the face size; 0 disables the re-ranking.
    neighbor_rings : int
        Bundles whose surface points judge a candidate (§5.1): the natural
        neighbours (1), or also their neighbours (2), ...
    grid_density : float
        Grid cells per tetrahedron of a bundle: the bundle's search grid has
        about ``(n_tets * grid_density)^(1/3)`` cells along its longest side
        (more cells: fewer candidates per query, more memory).
    exact : bool
        Add the ``B x B`` residual correction so that the surface passes
        exactly through every bundle.
    threads : int
        Threads for the blend (2 on a 2-core machine).
    """

    nn_method: str | None = None
    prune_tolerance: float | None = None
    merge_tolerance: float | None = None
    neighbors: int = 6
    min_quality: float = 0.05
    max_edge: float | None = None
    forbidden: tuple = ()
    min_tets_per_point: int = 4
    temporal_bias: float = 0.25
    tie_tolerance: float | None = None
    neighbor_rings: int = 1
    grid_density: float = 1.0
    exact: bool = True
    threads: int = 2

    def prune_tolerance_at(self, face_size: float) -> float:
        """``prune_tolerance`` in scene units for a face of ``face_size`` scene units."""
        return 1e-7 * face_size if self.prune_tolerance is None else float(self.prune_tolerance)

    def merge_tolerance_at(self, face_size: float) -> float:
        """``merge_tolerance`` in scene units for a face of ``face_size`` scene units."""
        return 2e-4 * face_size if self.merge_tolerance is None else float(self.merge_tolerance)

    def tie_tolerance_at(self, face_size: float) -> float:
        """``tie_tolerance`` in scene units for a face of ``face_size`` scene units."""
        return 1e-5 * face_size if self.tie_tolerance is None else float(self.tie_tolerance)
