"""Blendshape solve and retargeting (Bhat et al. 2013): inner-lip and eyelid contour loops and
their matching, the bounded weight solve with its out-of-subspace corrective, deformation
transfer and the lip-sync retargeting heuristic."""
