"""Local geometric indexing (Cong, Lan, Fedkiw 2019): rebuild a face from sparse 3D bundles
with a shape dataset, stitched by natural-neighbour weights, with jaw skinning, baselines and
rig correctives."""
