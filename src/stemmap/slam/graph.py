"""Graph SLAM with GTSAM: iSAM2 incremental smoothing plus a final batch optimisation (ours).

The problem reads as a factor graph (GTSAM conventions; GTSAM batches are (2, N), ours (N, 2)):

* variables ``X(f)``: :class:`gtsam.Pose2` of the **sensor** at frame ``f`` (the laser pose, so
  bearing-range factors need no mounting offset; vehicle poses are recovered at the end by
  composing with the inverse mounting transform);
* ``L(j)``: :class:`gtsam.Point2` of tree ``j``;
* a prior on ``X(0)``;
* ``BetweenFactorPose2(X(f), X(f+1))`` from the Ackermann (or unicycle) odometry pre-integrated
  between the frames, covariance propagated from the control noise
  (:func:`stemmap.slam.motion.preintegrate`) and carried to the sensor frame with the adjoint of
  the mounting transform;
* ``BearingRangeFactor2D(X(f), L(j))`` for every associated detection, with a robust (Huber by
  default, or Cauchy) noise model on ``(sigma_bearing, sigma_range)``.

Front-end (``stemmap.slam._isam2_track.track_keyframe``, numba): between iSAM2 updates a pose
tracker carries the latest sensor-pose estimate forward with the odometry and its 3x3
covariance (``P' = F P Fᵀ + Q``), and every frame is associated in three steps:

1. **local trees** (whose estimate is tied to the current local map: odometry drift since their
   last observation that is already in iSAM2 below ``local_drift_sigma``): Mahalanobis gate
   with the pose covariance mapped through each detection (``J P Jᵀ``, so the heading error
   grows with range), the detection's world covariance, the tree's ``σ²/n`` and the diameter
   cue ``(d_obs - d_tree)² / (σ²_d + σ²_d / n)``; one-to-one greedy by negative log-likelihood
   ``d² + ln|S|``; then a MAP update of the tracked pose from the matched trees, and a second
   gating pass with the posterior. The trees are held fixed: the tracker only serves the
   association, the factors come from the raw detections.
2. **re-acquisition** of the other trees (revisits, loop closures): a wide gate with the
   odometry drift since they were last seen (capped at ``max_drift_sigma``), accepted only as a
   group of >= 2 detections that agree on one common offset (the drift of a revisit is common
   to the trees of that earlier pass), or singly when the tree is where the tracked pose puts it
   (gate without the drift). The old code gated every pair independently with the full drift,
   which let one detection pick a tree 2 m away while its neighbours said the pose was right.
3. an unmatched detection becomes a new tree only when it is clearly separate from every tree
   (d² > ``new_chi2`` with the drift, and farther than ``new_min_dist``); otherwise it is
   discarded as ambiguous.

iSAM2 is updated every ``update_every`` keyframes (the tracker bridges the gap); after the last
frame duplicate trees are merged, one Levenberg-Marquardt batch optimisation refines
everything (:mod:`stemmap.slam._graph_batch`), and each tree's 2x2 marginal covariance is the
Schur complement of the information over the pose chain (:func:`_point_marginals`, equal to
:class:`gtsam.Marginals`).

Localisation mode on revisits (ours; docs/algorithms/slam.md "Revisits"): a keyframe that only
re-observes well-mapped trees adds no pose (:mod:`stemmap.slam._graph_revisits`, bounded by area
and by the visits of each place: ``RevisitGate``);
the tracker is then localised on the map at each restart (:mod:`stemmap.slam._graph_localise`),
and a tracker the map contradicts puts the next keyframes back into the graph. A keyframe that
enters after a long left-out run is anchored by a prior at its tracked pose instead of an
odometry factor to the remote last graph keyframe (``revisit_anchor_after``,
:func:`~stemmap.slam._graph_revisits.anchor_prior`).

Sessions (docs/algorithms/slam.md "Maps reused across sessions"): with ``problem.prior_map``
its trees start as landmarks held by marginal priors (:mod:`stemmap.slam.relocalise`, seeded by
:mod:`stemmap.slam._graph_session`), or,
with ``problem.prior_graph``, the earlier session's whole graph is continued (its poses
``W(i)`` and trees stay variables, :mod:`stemmap.slam._graph_continue`); ``export_graph``
returns this session's graph for the next one.

Odometry self-calibration (ours; docs/algorithms/slam.md "Odometry self-calibration"): a
steering (yaw-rate) offset and a speed-scale correction enter every odometry factor to first
order, ``δ(c) = δ0 Exp(J c)``. They are estimated from the graph's own poses
(:func:`_calibration_lsq`, the conditional MAP given the poses; the keyframe odometry and its
calibration state: :class:`~stemmap.slam._graph_odometry.KeyframeOdometry`): online once per segment
from the last ``calib_window`` keyframes for the new factors, and at the end per segment with a
random walk between segments, alternated with the batch LM. A systematic odometry error is
otherwise treated as white noise and accumulates wherever the trees constrain the heading
weakly (the demo's loop drifted 1.25 m). Not a GTSAM variable: a ``CustomFactor`` on
``(X_k, X_k+1, C)`` was tried and made the full Victoria Park run 3-4x slower (pybind copies
the whole ``Values`` into every Python error call; cost grows with the graph).

Code: :class:`Isam2Slam` runs the incremental phase as an :class:`~stemmap.slam._graph_run.Isam2Run`
(the run state and one method per step of the keyframe loop: track, close the keyframe into the
graph or leave it out, predict the next, GNSS, iSAM2 update, tracker restart), then the batch
steps (:func:`_batch`), the read-out of the map (:func:`_read_out`) and of the trajectory
(:func:`_trajectory`), and the export of the session graph (:func:`_export`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from stemmap.errors import ConfigError, StemmapError
from stemmap.slam._graph_batch import BatchOutcome, Calibration, batch_rounds
from stemmap.slam._graph_config import Isam2Config
from stemmap.slam._graph_continue import SavedGraph, export_graph, graph_stats
from stemmap.slam._graph_marginals import (
    _fit_diagnostics,
    _merge_duplicates,  # noqa: F401  (re-exported: forestrix, loop_closure)
    _point_marginals,  # noqa: F401  (re-exported: stemmap.slam.online, tests)
    final_marginals,
)
from stemmap.slam._graph_odometry import (
    _calibration_jacobians,  # noqa: F401  (re-exported: tests)
    _calibration_lsq,  # noqa: F401  (re-exported: tests)
    _sensor_between,  # noqa: F401  (re-exported: tests)
    frame_covariances,
)
from stemmap.slam._graph_result import calibration_stats, gnss_stats, map_trees
from stemmap.slam._graph_revisits import held_into_map, localise_skipped
from stemmap.slam._graph_run import Isam2Run
from stemmap.slam._isam2_track import C_AMBIG, C_FAR, C_LOCAL, C_NEW, C_REACQ, C_SINGLE
from stemmap.slam.base import SlamProblem, SlamResult, frame_trajectory, single_threaded_blas
from stemmap.slam.motion import compose
from stemmap.slam.relocalise import _joint_sqrt_information
from stemmap.types import FloatArray, StemMap

__all__ = ["Isam2Config", "Isam2Slam"]

log = logging.getLogger(__name__)


class Isam2Slam:
    """GTSAM iSAM2 graph SLAM back-end (registered as ``"isam2"``), see module docs."""

    name = "isam2"

    def __init__(self, config: Isam2Config | None = None, **kwargs: object) -> None:
        if config is not None and kwargs:
            raise ConfigError("pass either an Isam2Config or keyword settings, not both.")
        try:
            self.config = config or Isam2Config(**kwargs)  # type: ignore[arg-type]
        except TypeError as exc:
            raise ConfigError(f"bad iSAM2 setting: {exc}.") from exc

    def run(
        self, problem: SlamProblem, *, progress: Callable[[int, int], None] | None = None
    ) -> SlamResult:
        # One BLAS thread: the matrices of the run are small, and on the shared 2-core machine
        # OpenBLAS's spinning worker threads cost CPU out of all proportion (dpotrf + dtrtri of
        # the ~800 x 800 tree information in _point_marginals: 0.9 s of CPU instead of 0.03 s).
        # The limit applies to the BLAS libraries loaded when it is set: scipy's (used by
        # scipy.linalg and by numba's kernels) is loaded first.
        import scipy.linalg  # noqa: F401

        with single_threaded_blas():
            return self._run(problem, progress)

    def _run(self, problem: SlamProblem, progress: Callable[[int, int], None] | None) -> SlamResult:
        import gtsam

        run = Isam2Run(gtsam, self.config, problem)
        run.keyframes(progress)  # the incremental phase (_graph_run)
        t_inc = time.perf_counter() - run.t_start
        batch = _batch(run)
        out = _read_out(run, batch)
        veh, pose_covs = _trajectory(run, out.kf_s, out.kf_cov)
        lm = run.lm
        trees = map_trees(
            out.keep, out.pts, out.covs, (lm.dsum, lm.dn, lm.nobs, lm.first, lm.last),
            run.frames.times,
        )  # fmt: skip
        saved = _export(run, batch, out.keep_g) if self.config.export_graph else None
        runtime = time.perf_counter() - run.t_start
        stats = self._stats(run, batch, out, len(trees), t_inc, runtime)
        log.info("iSAM2: %s", stats)
        stem_map = StemMap(tuple(trees), information=out.info_j)
        return SlamResult(
            frame_trajectory(run.frames.times, veh), stem_map, stats, pose_covs, graph=saved
        )

    def _stats(
        self,
        run: Isam2Run,
        batch: BatchOutcome,
        out: MapReadOut,
        n_trees: int,
        t_inc: float,
        runtime: float,
    ) -> dict[str, float | int | str]:
        """The run's statistics (``SlamResult.stats``): association counts, graph size,
        revisit and localisation counts, fit diagnostics, calibration, GNSS and timings."""
        counters, odo, gate = run.counters, run.odo, run.gate
        chi_odo, chi_meas, n_outlier = out.fit
        n_odo, n_meas = 3 * len(batch.odo_fac), 2 * len(run.meas_fac)
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "frames": run.nf,
            "detections": run.frames.n_detections,
            "matched": int(counters[C_LOCAL] + counters[C_REACQ] + counters[C_SINGLE]),
            "new_landmarks": int(counters[C_NEW]),
            "ambiguous_discarded": int(counters[C_AMBIG]),
            "beyond_max_range": int(counters[C_FAR]),
            "landmarks_in_graph": run.lm.n,
            "landmarks": n_trees,
            "factors": int(batch.graph.size()),
            "keyframes": int(run.nk),
            "keyframes_in_graph": int(run.gk.size),
            "keyframes_localised": len(run.skipped),
            "keyframes_anchored": len(run.anchor_fac),
            "localisation_runs": out.n_localised,
            "tracker_map_fixes": run.n_map_fix,
            "tracker_lost": run.n_map_lost,
            "trees_held": gate.n_held,
            "trees_held_mapped": len(out.keep) - len(out.keep_g),
            **{f"keyframes_entered_{k_e}": v_e for k_e, v_e in run.entered.items()},
            "isam2_updates": run.graph.n_updates,
            "measurement_factors": run.n_factors_meas,
            "unconfirmed_windows_skipped": run.n_single_skipped,
            "lm_iterations": batch.n_lm_iters,
            "merged_duplicates": batch.n_merged,
            "odometry_chi2_per_dof": chi_odo / n_odo if n_odo else math.nan,
            "measurement_chi2_per_dof": chi_meas / n_meas if n_meas else math.nan,
            "measurement_outlier_fraction": (
                n_outlier / len(run.meas_rec) if run.meas_rec else math.nan
            ),
            "calibration_segments": odo.n_seg,
            "calibration_rounds": batch.n_cal_rounds,
            **gnss_stats(batch.result, run.gnss_plan, run.gnss_keys),
            **graph_stats(run.cont),
            "incremental_s": t_inc,
            "runtime_s": runtime,
        }
        if odo.n_seg:
            stats.update(calibration_stats(odo.c_used))
        return stats


def _batch(run: Isam2Run) -> BatchOutcome:
    """After the incremental phase: iSAM2's estimate, duplicated trees merged and the odometry
    calibration re-estimated, alternated with batch LM on the rebuilt graph
    (:func:`~stemmap.slam._graph_batch.batch_rounds`)."""
    odo, lm, gk = run.odo, run.lm, run.gk
    one_step = gk[:-1][np.diff(gk) == 1]  # one-step odometry factors (calibration)
    result = run.graph.isam.calculateEstimate()
    # iSAM2's Bayes tree is not used after this (the batch steps work on the full graph):
    # freed before they build their own (on the 10x soak the two together were the run's peak)
    run.graph.isam = None
    return batch_rounds(
        run.gtsam, run.cfg, result, run.graph.all, keys=(run.XK, run.LK), n_lm=lm.n,
        lm=(lm.dsum, lm.dn, lm.nobs, lm.first, lm.last, lm.in_graph), pf=run.pf,
        odo_factor=run.odo_factor, edges=run.edges, odo_fac=run.odo_fac, map_fac=run.map_fac,
        joint_fac=run.joint_fac, gnss_fac=run.gnss_fac, anchor_fac=run.anchor_fac,
        gnss_keys=run.gnss_keys, meas_rec=run.meas_rec, meas_fac=run.meas_fac,
        meas_noise=run.meas_noise, gk=gk, prior_map=run.pmap, cont=run.cont,
        calib=Calibration(
            odo.residuals, run.kf_poses, one_step, odo.J_k, odo.info_k, odo.c_used, odo.seg_k,
            odo.n_seg, odo.dur_seg,
        ) if odo.calibrate else None,
    )  # fmt: skip


@dataclass
class MapReadOut:
    """The map read out of the optimum (:func:`_read_out`).

    ``kf_s`` (K, 3) / ``kf_cov`` (K, 3, 3): sensor poses of the graph keyframes and their
    marginals (NaN elsewhere); ``pts`` (n, 2) / ``covs`` (n, 2, 2): every tree's estimate and
    marginal; ``keep``: the mapped trees, ``keep_g`` those of the graph among them (the others
    were held out of it); ``info_j``: the map's joint information; ``fit``: (odometry chi²,
    measurement chi², outliers) at the optimum; ``n_localised``: left-out runs localised.
    """

    kf_s: FloatArray
    kf_cov: FloatArray
    pts: FloatArray
    covs: FloatArray
    keep: np.ndarray
    keep_g: np.ndarray
    info_j: Any
    fit: tuple[float, float, int]
    n_localised: int


def _read_out(run: Isam2Run, batch: BatchOutcome) -> MapReadOut:
    """Poses, trees and their marginals at the optimum (:func:`~stemmap.slam._graph_marginals.
    final_marginals`; consistency and association quality, GPS-free:
    :func:`~stemmap.slam._graph_marginals._fit_diagnostics`); then the keyframes left out of the
    graph localised on the final map, run by run, and the held trees mapped from their poses
    when confirmed (:func:`~stemmap.slam._graph_revisits.localise_skipped`,
    :func:`~stemmap.slam._graph_revisits.held_into_map`)."""
    gtsam, cfg, lm, skipped, gk = run.gtsam, run.cfg, run.lm, run.skipped, run.gk
    n_lm, result, alias = lm.n, batch.result, batch.alias
    kf_s = run.kf_poses(result)  # sensor poses of the graph keyframes
    pts = np.zeros((n_lm, 2))
    ing = np.flatnonzero(lm.in_graph[:n_lm])
    if ing.size:
        pts[ing] = gtsam.utilities.extractPoint2(result)
    fit = _fit_diagnostics(
        gtsam, result, batch.odo_fac, run.meas_fac, run.meas_rec, kf_s, pts[alias]
    )
    keep = np.flatnonzero((lm.nobs[:n_lm] >= cfg.min_obs) & lm.in_graph[:n_lm])
    covs = np.full((n_lm, 2, 2), np.nan)
    kf_cov = np.full((run.nk, 3, 3), np.nan)  # graph keyframes' sensor-pose marginals
    covs[keep], kf_cov[gk], info_j = final_marginals(
        batch.graph, result, [run.LK(int(q_)) for q_ in keep], [run.XK(int(k_)) for k_ in gk],
        cfg,
    )  # fmt: skip
    skipped.remap_trees(alias)
    held = run.gate.held(n_lm) & ~lm.in_graph[:n_lm]
    n_localised = localise_skipped(
        gtsam, skipped, kf_s, run.kf_init, run.odo.measured(slice(0, run.nk - 1)),
        run.odo.cov_k, pts, covs, run.meas_noise, (run.XK, run.LK), held=held,
    )  # fmt: skip
    keep_g = keep  # (the graph's trees)
    if held.any():  # held trees: mapped from the left-out poses when confirmed
        keep, info_j = held_into_map(
            skipped, kf_s, held, run.gate.tree_visits(n_lm), (lm.dsum, lm.dn, lm.nobs), cfg,
            keep, pts, covs, info_j,
        )  # fmt: skip
    skipped.close()  # (its spill file, _graph_leftout)
    return MapReadOut(kf_s, kf_cov, pts, covs, keep, keep_g, info_j, fit, n_localised)


def _trajectory(
    run: Isam2Run, kf_s: FloatArray, kf_cov: FloatArray
) -> tuple[FloatArray, FloatArray | None]:
    """Every frame's vehicle pose: keyframe sensor pose ∘ (dead-reckoned sensor motion since
    the keyframe) ∘ T_sv, and with ``pose_marginals`` its covariance
    (:func:`~stemmap.slam._graph_odometry.frame_covariances`)."""
    a, b = run.problem.sensor_offset
    T_sv = run.T_vs.inverse()
    veh = compose(
        compose(kf_s[run.kf_of], run.fo.rel_s), np.array([T_sv.x(), T_sv.y(), T_sv.theta()])
    )
    if not run.cfg.pose_marginals:
        return veh, None
    fo = run.fo
    return veh, frame_covariances(
        kf_cov, run.kf_of, run.kf_frames, fo.d_f, fo.cov_f, (a, b), veh[:, 2]
    )


def _export(run: Isam2Run, batch: BatchOutcome, keep_g: np.ndarray) -> SavedGraph | None:
    """This session's graph for the next one (:func:`~stemmap.slam._graph_continue.
    export_graph`), with what held its frame (GNSS fixes) and the earlier map (its priors);
    None (logged) on a bookkeeping error: the map is still written."""
    cfg, pmap = run.cfg, run.pmap
    u_j = None if run.joint_fac is None or pmap is None else _joint_sqrt_information(pmap)
    try:
        return export_graph(
            run.gtsam, batch.result, keys=(run.XK, run.LK, run.WK), gk=run.gk, keep=keep_g,
            alias=batch.alias, odo_fac=batch.odo_fac, pose_priors=[run.pf, *run.anchor_fac],
            meas_rec=run.meas_rec, cont=run.cont, map_fac=run.map_fac,
            prior_robust=(
                cfg.prior_map_robust if run.prior_kernel is not None else "none", cfg.robust_k
            ),
            joint=None if u_j is None or pmap is None else (u_j, pmap.xy),
            gnss_fac=run.gnss_fac, gnss_robust=(cfg.gnss_robust, cfg.gnss_robust_k),
        )  # fmt: skip
    except StemmapError as exc:  # (a bookkeeping bug: the map is still written)
        log.warning("iSAM2: session graph not exported: %s", exc)
        return None
