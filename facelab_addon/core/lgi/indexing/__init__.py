"""Local geometric indexing (Cong, Lan and Fedkiw 2019, §4-§7) as state objects, lowest first.

``params`` (:class:`IndexerParams`, the tuning), ``dataset`` (:class:`IndexedDataset`: checked inputs,
jaw-unskinned float32 deltas, natural-neighbour weights), ``clouds`` (:class:`BundleClouds` and
:class:`TetGrid`: point clouds, tetrahedra, hulls, search grids, §4), ``locate`` (:class:`Locator`: the
per-frame choice of tetrahedra, §4, §5.1), ``stitch`` (:class:`Stitcher`: the blend and exact
interpolation, §5, §7) and ``indexer`` (:class:`GeometricIndexer`, composing them, with sequences and
temporal smoothing)."""
