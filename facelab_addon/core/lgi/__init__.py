"""Local geometric indexing (Cong, Lan, Fedkiw 2019): rebuild a face from sparse 3D bundles
with a shape dataset, stitched by natural-neighbour weights, with jaw skinning, baselines and
rig correctives.

Modules, lowest first: ``tets`` (tetrahedron geometry), ``jaw`` (:class:`JawRig`, §6),
``binding`` (bundles on the neutral surface), ``natural_neighbor`` (stitching weights, §5),
``indexing`` (the subpackage of :class:`GeometricIndexer` and :class:`IndexerParams`, §4-§5, §7),
``baselines`` (:class:`BlendshapeFit`, §7) and
``correctives`` (:class:`RigCorrectives`, §7, Fig. 7)."""
