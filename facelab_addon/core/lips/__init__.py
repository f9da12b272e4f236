"""Inner-lip correction (Dinev et al. 2018): finding the mouth, the trusted-mouth and inner-lip
regions, the sketch-based refinement (§5) and the regression that propagates corrections (§4)."""
