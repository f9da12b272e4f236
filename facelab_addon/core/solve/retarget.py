"""Retargeting a solved performance to a creature (Bhat et al. 2013, §5.1 and Fig. 8/10).

"High fidelity facial animation capture and retargeting with contours":

1. the actor's blendshapes are carried to the creature by deformation
   transfer (:mod:`.deformation_transfer`), giving parallel rigs; the solved
   weights are copied and the per-frame correctives are transferred too;
2. on a creature whose mouth is much wider than the actor's, the lip-sync
   heuristic (:mod:`.lip_sync`) reshapes the creature's lips so the
   upper-to-lower lip distances along a talking portion of its inner-lip
   contours (:mod:`.lip_contours`) match the actor's.

:class:`Retargeter` builds the parallel rig and the lip-sync deformer once
(options: :class:`RetargetParams`) and retargets single frames;
:func:`retarget_performance` runs it over a whole performance (:class:`RetargetResult`), keeping the creature's
correctives or streaming them frame by frame to a sink.

Units: positions in scene units; end points are fractions of arc length;
times in seconds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import FaceLabError
from ..geometry.axes import Y_UP, Z_FORWARD
from .deformation_transfer import DeformationTransfer
from .lip_contours import lip_contours
from .lip_sync import LipSync, LipSyncParams

__all__ = ["RetargetParams", "RetargetResult", "Retargeter", "retarget_performance"]


@dataclass(frozen=True)
class RetargetParams:
    """Options of the retargeting (:class:`Retargeter`).

    Attributes
    ----------
    lip_sync : bool
        Build the lip-sync deformer and apply the heuristic on every frame.
    threshold : float
        Lip-sync distance threshold, scene units: extra talking length allowed
        before the creature's corners are sealed.
    lip : LipSyncParams
        The lip-sync deformer's reach, weights and smoothing.
    """

    lip_sync: bool = True
    threshold: float = 0.0
    lip: LipSyncParams = field(default_factory=LipSyncParams)


@dataclass
class RetargetResult:
    """A performance carried to the creature.

    Attributes
    ----------
    deltas : (S,W,3) float64
        Creature blendshape deltas (the transferred actor shapes), scene units.
    weights : (T,S) float64
        Weights copied from the actor's solve.
    correctives : (T,W,3) float32 or None
        Per-frame creature correctives on top of ``rest + weights @ deltas``:
        the transferred actor corrective plus the lip-sync offset, scene units;
        None when they were handed to a ``corrective_sink`` instead.
    end_points : list of EndPoints or None
        Talking portion used on each frame (``None`` without lip sync).
    info : dict
        Timings (seconds) and counts.
    """

    deltas: np.ndarray
    weights: np.ndarray
    correctives: np.ndarray
    end_points: list
    info: dict


class Retargeter:
    """Parallel creature rig plus per-frame retargeting (Bhat §5.1).

    Parameters
    ----------
    actor_rest : (V,3) array_like
        Actor neutral, scene units.
    actor_faces : (F,3) int array_like
    actor_deltas : (S,V,3) array_like
        Actor blendshape deltas, scene units.
    creature_rest : (W,3) array_like
        Creature neutral, scene units.
    creature_faces : (F_t,3) int array_like
    correspondence : (F_t,) int array_like, optional
        Source triangle per creature triangle; default: shared topology.
    params : RetargetParams
        Lip sync on or off, its threshold and deformer options.
    actor_loop, creature_loop : (L,) int array_like, optional
        Inner-lip edge loops; default: detected (``lip_loop.inner_lip_loop``)
        on the actor, and the same vertex ids on a creature of the same
        topology (detected on the creature otherwise).
    actor_contours, creature_contours : LipContours, optional
        Give the split contours directly instead of loops.
    up, forward : (3,) float
        Face axes (actor space) for the corner and upper/lower detection.
    """

    def __init__(self, actor_rest, actor_faces, actor_deltas, creature_rest, creature_faces, *,
                 params: RetargetParams = RetargetParams(), correspondence=None, actor_loop=None, creature_loop=None,
                 actor_contours=None, creature_contours=None, up=Y_UP, forward=Z_FORWARD):
        t0 = time.perf_counter()
        self.transfer = DeformationTransfer(actor_rest, actor_faces, creature_rest, creature_faces, correspondence)
        t1 = time.perf_counter()
        D = np.asarray(actor_deltas, dtype=np.float64)
        if D.ndim == 2:
            D = D[None]
        if D.ndim != 3 or D.shape[1:] != self.transfer.source_rest.shape:
            raise FaceLabError(
                f"The actor's shape deltas have shape {np.shape(actor_deltas)}, expected (S, {len(actor_rest)}, 3); "
                "the rig must have shape keys on the actor mesh."
            )
        if len(D) == 0:
            raise FaceLabError("The actor rig has no shape keys; add blendshapes (shape keys) to the actor first.")
        self.actor_deltas = D
        self.creature_deltas = self.transfer.transfer_deltas(D)
        t2 = time.perf_counter()
        self.params = params
        self.threshold = float(params.threshold)
        self.lip_sync = None
        if params.lip_sync:
            Va, Fa = self.transfer.source_rest, self.transfer.source_faces
            Vc, Fc = self.transfer.target_rest, self.transfer.target_faces
            ac = actor_contours or lip_contours(Va, Fa, actor_loop, up=up, forward=forward)
            if creature_contours is not None:
                cc = creature_contours
            elif creature_loop is None and self.transfer.same_topology:
                cc = lip_contours(Vc, Fc, np.r_[ac.upper, ac.lower[1:-1][::-1]], corners=ac.corners, up=up,
                                  forward=forward)
            else:
                cc = lip_contours(Vc, Fc, creature_loop, up=up, forward=forward)
            self.lip_sync = LipSync(Vc, Fc, cc, ac, params=params.lip)
        t3 = time.perf_counter()
        self.info = {"factor_s": t1 - t0, "transfer_shapes_s": t2 - t1, "lip_sync_setup_s": t3 - t2}

    @property
    def creature_rest(self):
        return self.transfer.target_rest

    def frame(self, weights, corrective=None, *, end_points=None, lip_sync: bool | None = None,
              threshold: float | None = None):
        """Retarget one frame.

        Parameters
        ----------
        weights : (S,) array_like
            Actor weights of this frame (copied to the creature).
        corrective : (V,3) array_like, optional
            Actor's out-of-subspace corrective of this frame, scene units.
        end_points : EndPoints or fractions, optional
            Artist override of the talking portion on this frame.
        lip_sync : bool, optional
            Apply the lip-sync heuristic (default: when it was built).
        threshold : float, optional
            Distance threshold, scene units (default: ``params.threshold``).

        Returns
        -------
        corrective : (W,3) float64 ndarray
            Creature corrective on top of ``creature_rest + weights @ creature_deltas``,
            scene units.
        info : dict
            ``end_points`` (or None) and ``constraints``.
        """
        w = np.asarray(weights, dtype=np.float64).ravel()
        if w.shape != (len(self.actor_deltas),) or not np.isfinite(w).all():
            raise FaceLabError(
                f"Expected {len(self.actor_deltas)} finite weights for this frame, got {w.shape}; solve the frame first."
            )
        blend_a = np.tensordot(w, self.actor_deltas, axes=1)
        blend_c = np.tensordot(w, self.creature_deltas, axes=1)
        if corrective is not None:
            dv = np.asarray(corrective, dtype=np.float64)
            corr_c = self.transfer.transfer_correctives(dv, base=blend_a)
        else:
            dv = 0.0
            corr_c = np.zeros_like(blend_c)
        info = {"end_points": None, "constraints": 0}
        use = self.lip_sync is not None if lip_sync is None else bool(lip_sync)
        if use:
            if self.lip_sync is None:
                raise FaceLabError("Lip sync was not set up for this creature; build the Retargeter with RetargetParams(lip_sync=True).")
            actor = self.transfer.source_rest + blend_a + dv
            creature = self.creature_rest + blend_c + corr_c
            th = self.threshold if threshold is None else float(threshold)
            X, info = self.lip_sync.solve(actor, creature, end_points=end_points, threshold=th)
            corr_c = X - self.creature_rest - blend_c
        return corr_c, info


def _actor_correctives(correctives, corrective_keys, T: int, shape: tuple):
    """One frame's actor corrective at a time (see :func:`retarget_performance`).

    Returns a function ``t -> (V,3) ndarray or None``; ``corrective_keys`` is mixed frame by frame
    (``einsum("r,rvd->vd")``, the same values as mixing the whole shot with ``einsum("tr,rvd->tvd")``).
    """
    if correctives is not None and corrective_keys is not None:
        raise FaceLabError("Give the actor's correctives either per frame (correctives) or as keys and values "
                           "(corrective_keys), not both.")
    if corrective_keys is not None:
        correctives = tuple(corrective_keys)
        if len(correctives) != 2:
            raise FaceLabError(
                f"corrective_keys must be the pair (keys' deltas (R, {shape[0]}, 3), values ({T}, R)), "
                f"got {len(correctives)} items."
            )
        basis, values = (np.asarray(x, dtype=np.float64) for x in correctives)
        R = len(basis) if basis.ndim == 3 else -1
        if basis.shape[1:] != shape or values.shape != (T, R):
            raise FaceLabError(
                f"Corrective keys have shape {basis.shape} and values {values.shape}, expected (R, {shape[0]}, 3) "
                f"and ({T}, R): one row of key values per frame."
            )
        return lambda t: np.einsum("r,rvd->vd", values[t], basis)
    if correctives is None:
        return lambda t: None
    C = np.asarray(correctives)
    if C.shape != (T,) + shape:
        raise FaceLabError(f"Correctives have shape {C.shape}, expected ({T}, {shape[0]}, 3): one per frame.")
    return lambda t: C[t]


def retarget_performance(retargeter: Retargeter, weights, *, correctives=None, corrective_keys=None,
                         end_points: dict | None = None, progress=None, corrective_sink=None) -> RetargetResult:
    """Retarget a solved performance to a creature (Bhat §5.1).

    Parameters
    ----------
    retargeter : Retargeter
        The actor's and creature's parallel rigs and the lip-sync deformer.
    weights : (T,S) array_like
        Solved weights per frame.
    correctives : (T,V,3) array_like, optional
        Actor correctives per frame, scene units.
    corrective_keys : tuple of ((R,V,3) array_like, (T,R) array_like), optional
        Instead of ``correctives``: the actor's corrective keys' deltas (scene units) and their value on
        each frame, mixed one frame at a time so that no (T,V,3) array is built (bit for bit the frames
        of ``einsum("tr,rvd->tvd", values, basis)``).
    end_points : dict frame index -> EndPoints or fractions, optional
        Artist overrides on some frames.
    progress : callable(done, total), optional
        Called after each frame with the number of frames done.
    corrective_sink : callable(frame_index, corrective), optional
        Each frame's creature corrective, a (W,3) float32 array in scene units (the row the
        whole-shot ``correctives`` would hold), is handed to it in frame order, every frame once,
        instead of being kept: ``correctives`` of the result is then None and memory does not
        grow with frames times vertices.

    Returns
    -------
    RetargetResult
        ``info`` has the :class:`Retargeter` set-up timings, ``frames_s`` (seconds for the
        frames) and ``nonzero`` (some frame's corrective is not zero).
    """
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2:
        raise FaceLabError(f"Weights must be (frames, shapes), got shape {W.shape}.")
    rt = retargeter
    T = len(W)
    actor_corrective = _actor_correctives(correctives, corrective_keys, T, rt.transfer.source_rest.shape)
    out = np.zeros((T,) + rt.creature_rest.shape, dtype=np.float32) if corrective_sink is None else None
    eps, nonzero = [], False
    overrides = end_points or {}
    t0 = time.perf_counter()
    for t in range(T):
        corr, info = rt.frame(W[t], actor_corrective(t), end_points=overrides.get(t))
        row = np.asarray(corr, dtype=np.float32)  # what the whole-shot (T,W,3) float32 result holds
        nonzero = nonzero or bool(row.any())
        if out is not None:
            out[t] = row
        else:
            corrective_sink(t, row)
        eps.append(info["end_points"])
        if progress is not None:
            progress(t + 1, T)
    info = dict(rt.info, frames_s=time.perf_counter() - t0, nonzero=nonzero)
    return RetargetResult(deltas=rt.creature_deltas, weights=W.copy(), correctives=out, end_points=eps, info=info)
