"""Mesh geometry shared by every method: validation and adjacency, Laplacians and the Poisson
operator, deformation gradients, sparse factorisations, the one constrained Laplacian solver
(:mod:`.deform`), silhouettes, spheres and the compression of corrective displacements."""
