"""End-of-run batch step of the iSAM2 back-end: duplicate merging, calibration rounds, LM (ours).

Split out of :meth:`stemmap.slam.graph.Isam2Slam._run` (graph.py had grown past the ~800-line
limit), unchanged: after the incremental phase, duplicated trees (two landmarks of one trunk,
e.g. first seen far away and initialised apart) are merged (:func:`_merge_duplicates`), the
per-segment odometry calibration is re-estimated from the current poses
(:func:`_calibration_lsq`, docs/algorithms/slam.md "Odometry self-calibration"), and the
rebuilt graph is optimised by Levenberg-Marquardt; see :func:`batch_rounds`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from stemmap.slam._graph_continue import ContinuedGraph
from stemmap.slam._graph_marginals import _merge_duplicates
from stemmap.slam._graph_odometry import _calibration_lsq
from stemmap.slam.relocalise import joint_prior_factor
from stemmap.types import FloatArray, StemMap

__all__ = ["BatchOutcome", "Calibration", "batch_rounds"]


@dataclass
class Calibration:
    """The odometry self-calibration state the batch rounds re-estimate.

    ``c_used`` (per one-step odometry factor, (nk - 1, 2)) is updated **in place**: the
    back-end's ``odo_measured`` (behind ``odo_residuals`` and ``odo_factor``) reads it.
    """

    odo_residuals: Callable[[FloatArray, np.ndarray], FloatArray]
    kf_poses: Callable[[Any], FloatArray]  # (nk, 3) sensor poses of the graph keyframes
    one_step: np.ndarray  # keyframes k whose factor (k, k + 1) is one step
    J: FloatArray  # (nk - 1, 3, 2) calibration Jacobians
    info: FloatArray  # (nk - 1, 3, 3) odometry information
    c_used: FloatArray  # (nk - 1, 2), updated in place
    seg: np.ndarray  # segment of each step
    n_seg: int
    dur_seg: FloatArray  # duration of each segment but the last


@dataclass
class BatchOutcome:
    """What the batch step hands back to the back-end."""

    result: Any  # gtsam.Values at the optimum
    graph: Any  # the (rebuilt) gtsam.NonlinearFactorGraph
    odo_fac: list[Any]  # the odometry factors of that graph
    alias: np.ndarray  # landmark slot each slot's factors now point to
    n_merged: int
    n_cal_rounds: int
    n_lm_iters: int


def batch_rounds(
    gtsam: Any,
    cfg: Any,
    result: Any,
    graph_all: Any,
    *,
    keys: tuple[Any, Any],
    n_lm: int,
    lm: tuple[np.ndarray, ...],
    pf: Any,
    odo_factor: Callable[[int, int], Any],
    edges: list[tuple[int, int]],
    odo_fac: list[Any],
    map_fac: list[Any],
    joint_fac: Any,
    gnss_fac: list[Any],
    anchor_fac: list[Any],
    gnss_keys: list[int],
    meas_rec: list[tuple[int, int, float, float, float, float]],
    meas_fac: list[Any],
    meas_noise: Callable[[FloatArray], Any],
    gk: np.ndarray,
    prior_map: StemMap | None,
    calib: Calibration | None,
    cont: ContinuedGraph | None = None,
) -> BatchOutcome:
    """Merge duplicates and re-estimate the calibration, alternated with batch LM.

    Closer than ``merge_dist`` with compatible diameters -> one key; the rebuilt graph is
    optimised again (this also closes the loops they imply). The first round looks at the
    iSAM2 estimate ``result``, so when it merges, the batch step runs once, on the merged graph
    (a separate batch before merging cost ~15 % of the run). With calibration, each round also
    re-estimates the per-segment calibration from the current poses (:func:`_calibration_lsq`)
    and, if it moved the increments by more than 0.1 sigma, rebuilds the odometry factors with
    it: block-coordinate descent on (poses, calibration), alternated with the LM steps the
    merging needs anyway. Without a round that changed anything, ``batch_iterations`` of LM run
    on ``graph_all`` as it is.

    ``anchor_fac``: the priors of keyframes that entered after a long left-out run
    (:func:`~stemmap.slam._graph_revisits.anchor_prior`), kept as they are when rebuilding.

    ``cont``: a continued earlier session graph (:mod:`stemmap.slam._graph_continue`), its
    factors and poses kept when rebuilding (its measurements of merged trees re-keyed).

    ``lm`` = (lm_dsum, lm_dn, lm_nobs, lm_first, lm_last, lm_in_graph), the landmark
    bookkeeping, updated in place for merged trees (and so are ``map_fac`` and ``meas_fac``).
    """
    XK, LK = keys
    lm_dsum, lm_dn, lm_nobs, lm_first, lm_last, lm_in_graph = lm
    calibrate = calib is not None
    n_lm_iters = 0
    batch_done = False
    n_merged = 0
    n_cal_rounds = 0
    alias = np.arange(n_lm)  # landmark slot each slot's factors now point to
    merging = cfg.merge_dist > 0 and n_lm > 1
    for _round in range(cfg.calib_rounds if calibrate else 3 if merging else 0):
        ing = np.flatnonzero(lm_in_graph[:n_lm])
        est_xy = gtsam.utilities.extractPoint2(result)
        remap = np.arange(n_lm)
        n_new_merges = 0
        if merging and _round < 3:
            # merging moves trees; repeat until no close compatible pair is left
            rep = _merge_duplicates(
                est_xy,
                lm_dsum[ing] / np.maximum(lm_dn[ing], 1),
                lm_nobs[ing],
                cfg.merge_dist,
                3.0 * (cfg.sigma_diameter or math.inf) * math.sqrt(2.0),
            )
            n_new_merges = int((rep != np.arange(ing.size)).sum())
            remap[ing] = ing[rep]  # landmark slot each slot maps to
        cal_moved = False
        if calib is not None:
            one_step, J_k, info_k, seg_k = calib.one_step, calib.J, calib.info, calib.seg
            c_used = calib.c_used
            c_seg = _calibration_lsq(
                calib.odo_residuals(calib.kf_poses(result), one_step), J_k[one_step],
                info_k[one_step], c_used[one_step], seg_k[one_step], calib.n_seg,
                calib.dur_seg, cfg.calib_prior_sigmas, cfg.calib_walk_sigmas,
            )  # fmt: skip
            dc = (J_k @ (c_seg[seg_k] - c_used)[:, :, None])[:, :, 0]
            moved = np.sqrt(np.einsum("ki,kij,kj->k", dc, info_k, dc))
            cal_moved = bool(moved.max() > 0.1)
            if cal_moved:
                c_used[:] = c_seg[seg_k]  # in place: odo_measured reads it
                n_cal_rounds += 1
        if n_new_merges == 0 and not cal_moved:
            break
        n_merged += n_new_merges
        # compose with earlier rounds: a factor of a tree merged before follows it
        alias = remap[alias]
        g2 = gtsam.NonlinearFactorGraph()
        g2.add(pf)
        odo_fac = [odo_factor(ka_, kb_) for ka_, kb_ in edges]
        for j_p, fac_p in enumerate(map_fac):  # a merged prior tree: on its representative
            if alias[j_p] != j_p and fac_p is not None:
                map_fac[j_p] = gtsam.PriorFactorPoint2(
                    LK(int(alias[j_p])), fac_p.prior(), fac_p.noiseModel()
                )
        if joint_fac is not None and prior_map is not None:
            # the joint prior over the map's trees: on the representatives
            joint_fac = joint_prior_factor(prior_map, LK, alias)
            g2.add(joint_fac)
        for fac_o in odo_fac + gnss_fac + anchor_fac + [f_ for f_ in map_fac if f_ is not None]:
            g2.add(fac_o)
        for i_m, (k_, j_, b_, r_, sb_, sr_) in enumerate(meas_rec):
            if alias[j_] != j_:  # the tree was merged: a factor on its representative
                noise_m = meas_noise(np.array([sb_, sr_]))
                meas_fac[i_m] = gtsam.BearingRangeFactor2D(
                    XK(k_), LK(int(alias[j_])), gtsam.Rot2(b_), r_, noise_m
                )
            g2.add(meas_fac[i_m])
        v2 = gtsam.Values()
        if cont is not None:
            for fac_c in cont.factors(gtsam, LK, meas_noise, alias):
                g2.add(fac_c)
            for key_c, val_c in cont.values(gtsam, result):
                v2.insert(key_c, val_c)
        for k_ in gk.tolist():
            v2.insert(XK(k_), result.atPose2(XK(k_)))
        for key_g in gnss_keys:
            v2.insert(key_g, result.atPose2(key_g))
        gone = np.zeros(n_lm, dtype=bool)
        for t_, j_ in enumerate(ing.tolist()):
            if remap[j_] == j_:
                v2.insert(LK(j_), est_xy[t_])
            else:
                gone[j_] = True
                tgt = int(remap[j_])
                lm_nobs[tgt] += lm_nobs[j_]
                lm_dsum[tgt] += lm_dsum[j_]
                lm_dn[tgt] += lm_dn[j_]
                lm_first[tgt] = min(lm_first[tgt], lm_first[j_])
                lm_last[tgt] = max(lm_last[tgt], lm_last[j_])
        lm_in_graph[:n_lm] &= ~gone
        graph_all = g2
        lm_params = gtsam.LevenbergMarquardtParams()
        lm_params.setMaxIterations(max(cfg.batch_iterations, 5))
        lm_params.setRelativeErrorTol(cfg.batch_rel_tol)
        opt = gtsam.LevenbergMarquardtOptimizer(graph_all, v2, lm_params)
        result = opt.optimize()
        n_lm_iters += int(opt.iterations())
        batch_done = True
    if cfg.batch_iterations > 0 and not batch_done:
        lm_params = gtsam.LevenbergMarquardtParams()
        lm_params.setMaxIterations(cfg.batch_iterations)
        lm_params.setRelativeErrorTol(cfg.batch_rel_tol)
        opt = gtsam.LevenbergMarquardtOptimizer(graph_all, result, lm_params)
        result = opt.optimize()
        n_lm_iters += int(opt.iterations())
    return BatchOutcome(result, graph_all, odo_fac, alias, n_merged, n_cal_rounds, n_lm_iters)
