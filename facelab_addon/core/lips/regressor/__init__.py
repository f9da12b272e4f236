"""The lip regressor of Dinev et al. 2018 §4, split by concept.

:class:`.lip_regressor.LipRegressor` is the public object; it composes plain functions over plain
data (:mod:`.state`): :mod:`.operators` (regions, Poisson system, patches), :mod:`.features` (frame
checks and mouth deformation-gradient features), :mod:`.reduced` (thin SVDs and the reduced ridge
regression), :mod:`.model_choice` (whole-motion, correction or blend; damping), :mod:`.training`
(features of corrected frames to a :class:`.state.TrainedModel`), :mod:`.prediction` and
:mod:`.predict32` (positions of captured frames, float64 and float32), :mod:`.patches` and
:mod:`.guards`.
"""

from .lip_regressor import LipRegressor

__all__ = ["LipRegressor"]
