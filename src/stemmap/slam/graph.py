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
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from stemmap._memory import TRIM_INTERVAL_S, HeapTrimmer
from stemmap.errors import ConfigError, StemmapError
from stemmap.slam._graph_batch import Calibration, batch_rounds
from stemmap.slam._graph_config import Isam2Config
from stemmap.slam._graph_continue import export_graph, graph_stats
from stemmap.slam._graph_localise import localise_windows, restart_covariance
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
    frame_odometry,
    keyframe_odometry,
)
from stemmap.slam._graph_result import (
    LANDMARK_FILL,
    calibration_stats,
    gnss_stats,
    map_trees,
    new_landmarks,
    tracker_params,
)
from stemmap.slam._graph_revisits import (
    LeftOutMeasurements,
    RevisitGate,
    anchor_prior,
    held_into_map,
    localise_skipped,
)
from stemmap.slam._graph_session import seed_earlier_session
from stemmap.slam._isam2_track import (
    C_AMBIG,
    C_FAR,
    C_LOCAL,
    C_NEW,
    C_REACQ,
    C_SINGLE,
    grow_landmarks,
    track_keyframe,
)
from stemmap.slam.base import SlamProblem, SlamResult, frame_trajectory, single_threaded_blas
from stemmap.slam.gnss import (
    gnss_factors,
    plan_gnss,
    robust_kernel,
    with_gnss_frame,
)
from stemmap.slam.motion import between, compose
from stemmap.slam.relocalise import _joint_sqrt_information
from stemmap.types import FloatArray, StemMap, wrap_angle

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
        from gtsam.symbol_shorthand import L as LK
        from gtsam.symbol_shorthand import V as VK
        from gtsam.symbol_shorthand import W as WK
        from gtsam.symbol_shorthand import X as XK

        cfg = self.config
        t_start = time.perf_counter()
        problem = with_gnss_frame(problem)  # the graph lives in the frame of the GNSS fixes
        frames = problem.frames
        nf = len(frames)
        a, b = problem.sensor_offset
        T_vs = gtsam.Pose2(a, b, 0.0)
        T_sv = T_vs.inverse()
        kf_of = np.arange(nf) // cfg.keyframe_every  # keyframe index of each frame
        kf_frames = np.arange(0, nf, cfg.keyframe_every)  # frame index of each keyframe
        nk = kf_frames.size
        # odometry between consecutive frames (for association and drift; _graph_odometry)
        fo = frame_odometry(problem, kf_of, kf_frames)
        d_f, cov_f, sp_dr = fo.d_f, fo.cov_f, fo.sp_dr
        cum_dist, cum_xy, cum_th = fo.cum_dist, fo.cum_xy, fo.cum_th
        # keyframe odometry with its self-calibration (steering / yaw-rate offset, speed
        # scale; _graph_odometry): odo.c_used[i] is the calibration inside the factor of
        # keyframes (i, i+1)
        odo, kf_dr = keyframe_odometry(problem, cfg, frames.times[kf_frames])
        cov_k, calibrate = odo.cov_k, odo.calibrate
        gnss_plan = (
            None
            if problem.gnss is None
            else plan_gnss(problem, problem.gnss, frames.times[kf_frames], kf_dr, cov_k)
        )
        del kf_dr
        c_cur = np.zeros(2)  # online estimate, used by every new odometry factor
        cal_seg = 0  # segment of the last online estimate
        # keyframes with a GNSS fix always enter the graph (the fix hangs from their pose)
        must_keep = np.zeros(nk, dtype=bool)
        if gnss_plan is not None:
            must_keep[np.asarray(gnss_plan.kf, dtype=np.int64)] = True

        def odo_factor(ka: int, kb: int, d: FloatArray | None = None) -> Any:
            """BetweenFactorPose2 of graph keyframes ``ka < kb`` (KeyframeOdometry.factor)."""
            return odo.factor(gtsam, XK, ka, kb, d)

        # one (stateless) robust kernel shared by every measurement factor
        kernel = robust_kernel(gtsam, cfg.robust, cfg.robust_k)

        gnss_kernel = robust_kernel(gtsam, cfg.gnss_robust, cfg.gnss_robust_k)
        prior_kernel = robust_kernel(gtsam, cfg.prior_map_robust, cfg.robust_k)

        def meas_noise(sigmas: FloatArray) -> Any:
            """Noise of one bearing-range factor, ``sigmas`` = (sigma_bearing, sigma_range)."""
            base = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            return base if kernel is None else gtsam.noiseModel.Robust.Create(kernel, base)

        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(cfg.relinearize_threshold)
        params.relinearizeSkip = cfg.relinearize_skip
        isam: Any = gtsam.ISAM2(params)  # (freed after the incremental phase)
        graph_all = gtsam.NonlinearFactorGraph()
        new_f = gtsam.NonlinearFactorGraph()
        new_v = gtsam.Values()

        s0 = gtsam.Pose2(*problem.initial_pose).compose(T_vs)
        prior = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(cfg.prior_sigmas if problem.prior_map is None else cfg.reloc_prior_sigmas)
        )
        pf = gtsam.PriorFactorPose2(XK(0), s0, prior)
        gnss_fac: list[Any] = []  # the GNSS factors in the graph (kept when rebuilding)
        gnss_keys: list[int] = []
        g_next = 0  # next fix of gnss_plan to add
        remove_idx: list[int] = []  # iSAM2 factor indices to remove at the next update

        def add_gnss(k_done: int) -> None:
            """Add the fixes hanging from keyframes <= k_done (their time has passed).

            With the first fix the tight prior on ``X(0)`` (which fixed the gauge until then)
            is swapped for the weak ``gnss_prior_sigmas`` one: from now on the fixes give the
            frame. (A weak prior from the start leaves the first updates without a fix nearly
            indeterminate: GTSAM refuses them.)
            """
            nonlocal g_next, pf
            if gnss_plan is None:
                return
            g1 = int(np.searchsorted(gnss_plan.kf, k_done, side="right"))
            if g_next == 0 and g1 > 0:
                weak = gtsam.PriorFactorPose2(
                    XK(0), s0, gtsam.noiseModel.Diagonal.Sigmas(np.array(cfg.gnss_prior_sigmas))
                )
                graph_all.replace(0, weak)
                if n_updates == 0:  # still in the pending batch (its first factor)
                    new_f.replace(0, weak)
                else:
                    remove_idx.append(0)  # iSAM2 numbers factors in the order they came in
                    new_f.add(weak)
                pf = weak
            for i_g in range(g_next, g1):
                xk_ = XK(int(gnss_plan.kf[i_g]))
                x_est = (
                    new_v.atPose2(xk_) if new_v.exists(xk_) else isam.calculateEstimatePose2(xk_)
                )
                facs, key, val = gnss_factors(gnss_plan, i_g, xk_, x_est, gnss_kernel)
                for fac_g in facs:
                    new_f.add(fac_g)
                    graph_all.add(fac_g)
                    gnss_fac.append(fac_g)
                new_v.insert(key, val)
                gnss_keys.append(key)
            g_next = max(g_next, g1)

        new_f.add(pf)
        graph_all.add(pf)
        meas_rec: list[tuple[int, int, float, float, float, float]] = []
        meas_fac: list[Any] = []  # the factor of each meas_rec entry (reused when rebuilding)
        odo_fac: list[Any] = []  # the odometry factors of the graph, in keyframe order
        edges: list[tuple[int, int]] = []  # the graph keyframes each odometry factor links
        anchor_fac: list[Any] = []  # priors of keyframes after long left-out runs (kept)
        new_v.insert(XK(0), s0)
        in_graph_k = np.zeros(nk, dtype=bool)  # keyframes with a pose in the graph
        in_graph_k[0] = True
        kf_init = np.zeros((nk, 3))  # the front-end's sensor pose of every keyframe
        kf_init[0] = (s0.x(), s0.y(), s0.theta())
        # measurements of the keyframes left out of the graph (_graph_revisits)
        skipped = LeftOutMeasurements()

        # landmark bookkeeping (numpy, grown geometrically; filled by the numba tracker)
        n_prior = 0 if problem.prior_map is None else len(problem.prior_map)
        (lm_xy, lm_dsum, lm_dn, lm_nobs, lm_first, lm_last, lm_inc, lm_in_graph, lm_ref,
         lm_nfac) = new_landmarks(n_prior + 1024 if n_prior else 1024)  # fmt: skip

        def add_factor(fac: Any) -> None:
            new_f.add(fac)
            graph_all.add(fac)

        # an earlier session (_graph_session): its map's trees as landmarks 0..n-1 held by
        # marginal priors, or its whole graph continued (_graph_continue)
        earlier = seed_earlier_session(
            gtsam, problem, cfg, (LK, WK, VK), (lm_xy, lm_dsum, lm_dn, lm_nobs, lm_in_graph),
            meas_noise=meas_noise, prior_kernel=prior_kernel, add_factor=add_factor,
            add_value=new_v.insert,
        )  # fmt: skip
        n_lm, pmap, cont = earlier.n_lm, earlier.pmap, earlier.cont
        map_fac, joint_fac = earlier.map_fac, earlier.joint_fac
        vr, vb = cfg.sigma_range**2, cfg.sigma_bearing**2
        kparams = tracker_params(cfg)
        ptr = np.ascontiguousarray(frames.ptr, dtype=np.int64)
        f_rng = np.ascontiguousarray(frames.ranges, dtype=np.float64)
        f_brg = np.ascontiguousarray(frames.bearings, dtype=np.float64)
        f_dia = np.ascontiguousarray(frames.diameters, dtype=np.float64)
        cov_fc = np.ascontiguousarray(cov_f)
        trk = np.array([s0.x(), s0.y(), s0.theta()])
        P_floor = np.diag(np.array(cfg.track_floor_sigmas) ** 2)
        P_trk = P_floor.copy()
        fc = np.zeros(1, dtype=np.int64)
        f_upd = 0
        counters = np.zeros(6, dtype=np.int64)
        kfe = cfg.keyframe_every
        out_cap = int(np.diff(ptr).reshape(-1)[:nf].max(initial=0)) * kfe + 1
        out_j = np.zeros(out_cap, dtype=np.int64)
        out_kx = np.zeros(out_cap)
        out_ky = np.zeros(out_cap)
        out_wxy = np.zeros(out_cap)
        out_wth = np.zeros(out_cap)
        n_factors_meas = n_updates = n_single_skipped = 0
        # freed heap back to the OS every TRIM_INTERVAL_S of CPU time (glibc; changes no
        # value): RSS then follows the heap in use on long drives, used as a library too
        # (docs/reliability.md "Soak"; shared with stemmap map's own trimmer)
        trim = HeapTrimmer(TRIM_INTERVAL_S)
        window: list[Any] = []  # the last keyframe's measurements (track_keyframe)

        def flush(k: int) -> None:
            """Merge the window's detections per tree into one bearing-range factor each."""
            nonlocal n_factors_meas, n_single_skipped
            if not window:
                return
            trees_w, brg_w, rr, sig, n_skip = window
            n_single_skipped += n_skip  # not confirmed by a second scan of the window
            js = trees_w.tolist()
            if not js:
                return
            bl, rl = brg_w.tolist(), rr.tolist()
            xk = XK(k)
            for t_, j in enumerate(js):
                if not lm_in_graph[j]:
                    new_v.insert(LK(j), lm_xy[j].copy())
                    lm_in_graph[j] = True
                fac = gtsam.BearingRangeFactor2D(
                    xk, LK(j), gtsam.Rot2(bl[t_]), rl[t_], meas_noise(sig[t_])
                )
                new_f.add(fac)
                graph_all.add(fac)
                meas_fac.append(fac)
            lm_nfac[trees_w] += 1
            gate.factored(trees_w, float(cum_dist[kf_frames[k]]))
            sbl, srl = sig[:, 0].tolist(), sig[:, 1].tolist()
            meas_rec.extend(zip([k] * len(js), js, bl, rl, sbl, srl, strict=True))
            n_factors_meas += len(js)

        g_last = 0  # the last keyframe in the graph
        # why keyframes entered the graph (a revisit that enters is one of these)
        entered = {"forced": 0, "new_tree": 0, "young_tree": 0}
        gate = RevisitGate(cfg, kf_init[0, :2])  # which keyframes stay out (_graph_revisits)

        def fix_tracker(k: int, d_step: FloatArray) -> tuple[Any, FloatArray]:
            """Keyframe ``k``'s sensor pose from the left-out keyframes before it localised on
            the map (:func:`localise_windows`; None when the map contradicts the tracker), and
            the tracker's covariance to restart with (its own when too few trees tell)."""
            ks = [i for i in range(max(k - cfg.update_every, 0), k) if i in skipped]
            fl = int(kf_frames[k - 1])
            prior_p = compose(trk[None], between(sp_dr[int(fc[0])][None], sp_dr[fl][None]))[0]
            fk = kf_frames[ks]  # (the dead reckoning's drift from each to fl, below)
            fix = localise_windows(
                prior_p, P_trk + P_floor, [skipped[i] for i in ks],
                between(sp_dr[fl][None], sp_dr[fk]), lm_xy,
                (vr + 400.0 * vb) / np.maximum(lm_nobs, 1),
                np.abs(np.column_stack((cum_xy[fl] - cum_xy[fk], cum_th[fl] - cum_th[fk]))),
            )  # fmt: skip
            if fix.lost:
                log.debug("iSAM2: tracker not localised at keyframe %d: %s", k - 1, fix.reason)
                return None, P_floor
            if fix.ok:
                kf_init[k - 1] = fix.pose
            pose = gtsam.Pose2(*(float(q) for q in fix.pose))  # (too few trees: the prior)
            d_s = gtsam.Pose2(float(d_step[0]), float(d_step[1]), float(d_step[2]))
            return pose.compose(d_s), fix.cov if fix.ok else P_trk.copy()

        def close_keyframe(kc: int) -> None:
            """Keyframe ``kc``'s window is complete: into the graph (pose, odometry from the
            last graph keyframe, its factors), or left out when it only re-observes well-mapped
            trees (:func:`redundant`; its pose is localised at the end)."""
            nonlocal g_last, n_single_skipped
            n_skip_w = int(window[4]) if window else 0
            revisits = cfg.revisit_factors > 0 and kc > 0 and bool(window) and not must_keep[kc]
            # at a place visited before (RevisitGate) young trees pull no keyframe in; a lost
            # tracker forces keyframes in
            s_kc = float(cum_dist[kf_frames[kc]])  # path distance (m): visits by distance
            trees_w = window[0] if window else np.zeros(0, dtype=np.int64)
            anchored = 0 < cfg.revisit_anchor_after < kc - g_last
            if gate.leave_out(
                kf_init[kc, :2], s_kc, trees_w, lm_in_graph, lm_nfac,
                allowed=revisits and kc >= force_until, linked=not anchored,
            ):  # fmt: skip
                skipped.add(kc, window[0], window[1], window[2], window[3])
                n_single_skipped += n_skip_w
                return
            if revisits:  # why it entered
                new_t = window[0].size and not np.all(lm_in_graph[window[0]])
                entered[
                    "forced" if kc < force_until else "new_tree" if new_t else "young_tree"
                ] += 1
            if kc > 0:
                if anchored:
                    # after a long left-out run: anchored at its tracked pose, not linked to
                    # the remote graph keyframe (anchor_prior)
                    bf = anchor_prior(
                        gtsam, XK(kc), kf_init[kc], odo.measured(slice(g_last, kc)),
                        cov_k[g_last:kc],
                    )  # fmt: skip
                    anchor_fac.append(bf)
                else:
                    bf = odo_factor(g_last, kc, d_last if g_last == kc - 1 else None)
                    odo_fac.append(bf)
                    edges.append((g_last, kc))
                new_f.add(bf)
                graph_all.add(bf)
                new_v.insert(XK(kc), gtsam.Pose2(*(float(q) for q in kf_init[kc])))
                in_graph_k[kc] = True
                g_last = kc
                gate.entered(kf_init[kc, :2], s_kc, anchored)
            flush(kc)

        d_last = np.zeros(3)  # the calibrated increment of the last step (keyframe k-1 -> k)
        force_until = 0  # keyframes before this enter the graph (the tracker was lost)
        n_map_fix = n_map_lost = 0
        for k in range(nk):
            f0 = int(kf_frames[k])
            if k > 0:
                odo.c_used[k - 1] = c_cur
                d0_ = odo.step(k - 1, c_cur)  # the step k-1 -> k with the current calibration
                # close the previous keyframe (the step into it is d_last), then this one's
                # initial value: the tracked pose carried to it by dead reckoning
                close_keyframe(k - 1)
                d_last = d0_
                g_ = int(fc[0])
                rel = between(sp_dr[g_], sp_dr[f0])
                ct_, st_ = math.cos(trk[2]), math.sin(trk[2])
                init = gtsam.Pose2(
                    trk[0] + ct_ * rel[0] - st_ * rel[1],
                    trk[1] + st_ * rel[0] + ct_ * rel[1],
                    trk[2] + rel[2],
                )
                kf_init[k] = (init.x(), init.y(), init.theta())
                add_gnss(k - 1)
                if k % cfg.update_every == 0:
                    restart = False  # else the front-end tracks on the map alone
                    if new_f.size() or new_v.size() or remove_idx:
                        isam.update(new_f, new_v, remove_idx)
                        remove_idx.clear()
                        n_updates += 1
                        new_f = gtsam.NonlinearFactorGraph()
                        new_v = gtsam.Values()
                        restart = g_last == k - 1
                        if restart:
                            # keyframe k's estimate: keyframe k-1's, carried by the odometry step
                            p = isam.calculateEstimatePose2(XK(k - 1)).compose(
                                gtsam.Pose2(float(d0_[0]), float(d0_[1]), float(d0_[2]))
                            )
                        if calibrate and restart and k // cfg.calib_every != cal_seg:
                            # online calibration from the last calib_window keyframes, once
                            # per segment (KeyframeOdometry.online): new odometry factors use it
                            cal_seg = k // cfg.calib_every
                            c_cur = odo.online(
                                k, p, in_graph_k, lambda i_: isam.calculateEstimatePose2(XK(i_)),
                                cfg, c_cur,
                            )  # fmt: skip
                    P_restart = P_floor
                    if not restart and (k - 1) in skipped:
                        # left out of the graph: localise the tracker on the map instead
                        p_fix, P_restart = fix_tracker(k, d0_)
                        if p_fix is None:
                            force_until = k + cfg.update_every  # lost: map the next ones
                            n_map_lost += 1
                        else:
                            p, restart = p_fix, True
                            n_map_fix += 1
                    # the tracker restarts from the estimate (on a revisit left out of the
                    # graph: from its own pose, carried here); its covariance is relative to
                    # the trees just seen, the drift since the others were seen covers them
                    dth = float(wrap_angle(p.theta() - init.theta())) if restart else 0.0
                    if restart:  # covering a disagreement with the tracker (a sharp turn)
                        P_restart = restart_covariance(
                            P_restart, p.x() - init.x(), p.y() - init.y(), dth
                        )
                        trk[:2] = (p.x(), p.y())
                    else:
                        trk[:2] = (init.x(), init.y())
                    trk[2] = trk[2] + rel[2] + dth
                    P_trk[:, :] = P_restart
                    fc[0] = f0
                    # every observation so far is in (or redundant with) the graph
                    f_upd = f0
                    lm_inc[:n_lm] = lm_last[:n_lm]
                    # refresh the trees that can be associated soon (within the search radius
                    # plus one keyframe of driving); far trees are refreshed when approached
                    if n_lm:
                        # (only trees whose estimate may have changed: not refreshed since the
                        # last iSAM2 update; in localisation mode no update runs for long)
                        ing = np.flatnonzero(lm_in_graph[:n_lm] & (lm_ref[:n_lm] < n_updates))
                        dxy = lm_xy[ing] - trk[:2]
                        near_k = ing[dxy[:, 0] ** 2 + dxy[:, 1] ** 2 < (cfg.max_range + 30.0) ** 2]
                        if near_k.size:
                            lm_ref[near_k] = n_updates
                            lm_xy[near_k] = [
                                isam.calculateEstimatePoint2(LK(jn)) for jn in near_k.tolist()
                            ]
            f1 = min(f0 + kfe, nf)
            # room for every detection of this keyframe becoming a new tree
            need = n_lm + int(ptr[f1] - ptr[f0])
            if need > lm_xy.shape[0]:
                (lm_xy, lm_dsum, lm_dn, lm_nobs, lm_first, lm_last, lm_inc, lm_in_graph, lm_ref,
                 lm_nfac) = grow_landmarks(
                    need, (lm_xy, lm_dsum, lm_dn, lm_nobs, lm_first, lm_last, lm_inc,
                           lm_in_graph, lm_ref, lm_nfac), LANDMARK_FILL,
                )  # fmt: skip
            n_lm, _, *window = track_keyframe(
                f0, f1, f0, f_upd, ptr, f_rng, f_brg, f_dia, sp_dr, cov_fc, cum_xy, cum_th,
                cum_dist, trk, P_trk, fc, lm_xy, lm_dsum, lm_dn, lm_nobs, lm_first, lm_last,
                lm_inc, n_lm, kparams, out_j, out_kx, out_ky, out_wxy, out_wth, counters,
            )  # fmt: skip
            if progress is not None:
                progress(f1, nf)
            trim()
        close_keyframe(nk - 1)
        add_gnss(nk - 1)
        if new_f.size() or new_v.size() or remove_idx:
            isam.update(new_f, new_v, remove_idx)
            n_updates += 1
        gk = np.flatnonzero(in_graph_k)  # the graph keyframes (key order)
        one_step = gk[:-1][np.diff(gk) == 1]  # one-step odometry factors (calibration)

        def kf_poses(values: Any) -> FloatArray:
            """(nk, 3) sensor poses of the graph keyframes in ``values`` (NaN elsewhere)."""
            out = np.full((nk, 3), np.nan)
            # (the continued graph's antenna poses V and poses W sort before X)
            n_w = 0 if cont is None else cont.n_poses + cont.saved.n_fixes
            out[gk] = gtsam.utilities.extractPose2(values)[n_w : n_w + gk.size]
            return out

        n_matched = int(counters[C_LOCAL] + counters[C_REACQ] + counters[C_SINGLE])
        n_new = int(counters[C_NEW])
        n_ambiguous = int(counters[C_AMBIG])
        n_far = int(counters[C_FAR])

        t_inc = time.perf_counter() - t_start
        result = isam.calculateEstimate()
        # iSAM2's Bayes tree is not used after this (the batch steps work on graph_all): freed
        # before they build their own (on the 10x soak the two together were the run's peak)
        isam = None
        # merge duplicated trees and re-estimate the odometry calibration, alternated with
        # batch LM on the rebuilt graph (stemmap.slam._graph_batch)
        batch = batch_rounds(
            gtsam, cfg, result, graph_all, keys=(XK, LK), n_lm=n_lm,
            lm=(lm_dsum, lm_dn, lm_nobs, lm_first, lm_last, lm_in_graph), pf=pf,
            odo_factor=odo_factor, edges=edges, odo_fac=odo_fac, map_fac=map_fac,
            joint_fac=joint_fac, gnss_fac=gnss_fac, anchor_fac=anchor_fac, gnss_keys=gnss_keys,
            meas_rec=meas_rec, meas_fac=meas_fac, meas_noise=meas_noise, gk=gk,
            prior_map=pmap, cont=cont,
            calib=Calibration(
                odo.residuals, kf_poses, one_step, odo.J_k, odo.info_k, odo.c_used, odo.seg_k,
                odo.n_seg, odo.dur_seg,
            ) if calibrate else None,
        )  # fmt: skip
        result, graph_all, odo_fac, alias = batch.result, batch.graph, batch.odo_fac, batch.alias
        n_merged, n_cal_rounds, n_lm_iters = batch.n_merged, batch.n_cal_rounds, batch.n_lm_iters
        kf_s = kf_poses(result)  # sensor poses of the graph keyframes
        pts = np.zeros((n_lm, 2))
        ing = np.flatnonzero(lm_in_graph[:n_lm])
        if ing.size:
            pts[ing] = gtsam.utilities.extractPoint2(result)
        # consistency and association quality at the optimum (GPS-free, _fit_diagnostics)
        chi_odo, chi_meas, n_outlier = _fit_diagnostics(
            gtsam, result, odo_fac, meas_fac, meas_rec, kf_s, pts[alias]
        )
        n_odo, n_meas = 3 * len(odo_fac), 2 * len(meas_fac)
        keep = np.flatnonzero((lm_nobs[:n_lm] >= cfg.min_obs) & lm_in_graph[:n_lm])
        covs = np.full((n_lm, 2, 2), np.nan)
        kf_cov = np.full((nk, 3, 3), np.nan)  # graph keyframes' sensor-pose marginals
        covs[keep], kf_cov[gk], info_j = final_marginals(
            graph_all, result, [LK(int(q_)) for q_ in keep], [XK(int(k_)) for k_ in gk], cfg
        )
        # the keyframes left out of the graph: localised on the final map, run by run
        skipped.remap_trees(alias)
        held = gate.held(n_lm) & ~lm_in_graph[:n_lm]
        n_localised = localise_skipped(
            gtsam,
            skipped,
            kf_s, kf_init, odo.measured(slice(0, nk - 1)), cov_k, pts, covs, meas_noise,
            (XK, LK), held=held,
        )  # fmt: skip
        keep_g = keep  # (the graph's trees)
        if held.any():  # held trees: mapped from the left-out poses when confirmed
            keep, info_j = held_into_map(
                skipped, kf_s, held, gate.tree_visits(n_lm), (lm_dsum, lm_dn, lm_nobs), cfg,
                keep, pts, covs, info_j,
            )  # fmt: skip
        skipped.close()  # (its spill file, _graph_leftout)
        # every frame: keyframe sensor pose ∘ (dead-reckoned sensor motion since the keyframe),
        # then the vehicle pose = sensor pose ∘ T_sv
        veh = compose(compose(kf_s[kf_of], fo.rel_s), np.array([T_sv.x(), T_sv.y(), T_sv.theta()]))
        pose_covs = (
            frame_covariances(kf_cov, kf_of, kf_frames, d_f, cov_f, (a, b), veh[:, 2])
            if cfg.pose_marginals
            else None
        )
        trees = map_trees(
            keep, pts, covs, (lm_dsum, lm_dn, lm_nobs, lm_first, lm_last), frames.times
        )
        saved = None
        if cfg.export_graph:
            # with what held the frame (GNSS fixes) and the earlier map (its priors)
            u_j = None if joint_fac is None or pmap is None else _joint_sqrt_information(pmap)
            try:
                saved = export_graph(
                    gtsam, result, keys=(XK, LK, WK), gk=gk, keep=keep_g, alias=alias,
                    odo_fac=odo_fac, pose_priors=[pf, *anchor_fac], meas_rec=meas_rec, cont=cont,
                    map_fac=map_fac,
                    prior_robust=(
                        cfg.prior_map_robust if prior_kernel is not None else "none", cfg.robust_k
                    ),
                    joint=None if u_j is None or pmap is None else (u_j, pmap.xy),
                    gnss_fac=gnss_fac, gnss_robust=(cfg.gnss_robust, cfg.gnss_robust_k),
                )  # fmt: skip
            except StemmapError as exc:  # (a bookkeeping bug: the map is still written)
                log.warning("iSAM2: session graph not exported: %s", exc)
        runtime = time.perf_counter() - t_start
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "frames": nf,
            "detections": frames.n_detections,
            "matched": n_matched,
            "new_landmarks": n_new,
            "ambiguous_discarded": n_ambiguous,
            "beyond_max_range": n_far,
            "landmarks_in_graph": n_lm,
            "landmarks": len(trees),
            "factors": int(graph_all.size()),
            "keyframes": int(nk),
            "keyframes_in_graph": int(gk.size),
            "keyframes_localised": len(skipped),
            "keyframes_anchored": len(anchor_fac),
            "localisation_runs": n_localised,
            "tracker_map_fixes": n_map_fix,
            "tracker_lost": n_map_lost,
            "trees_held": gate.n_held,
            "trees_held_mapped": len(keep) - len(keep_g),
            **{f"keyframes_entered_{k_e}": v_e for k_e, v_e in entered.items()},
            "isam2_updates": n_updates,
            "measurement_factors": n_factors_meas,
            "unconfirmed_windows_skipped": n_single_skipped,
            "lm_iterations": n_lm_iters,
            "merged_duplicates": n_merged,
            "odometry_chi2_per_dof": chi_odo / n_odo if n_odo else math.nan,
            "measurement_chi2_per_dof": chi_meas / n_meas if n_meas else math.nan,
            "measurement_outlier_fraction": n_outlier / len(meas_rec) if meas_rec else math.nan,
            "calibration_segments": odo.n_seg,
            "calibration_rounds": n_cal_rounds,
            **gnss_stats(result, gnss_plan, gnss_keys),
            **graph_stats(cont),
            "incremental_s": t_inc,
            "runtime_s": runtime,
        }
        if odo.n_seg:
            stats.update(calibration_stats(odo.c_used))
        log.info("iSAM2: %s", stats)
        stem_map = StemMap(tuple(trees), information=info_j)
        return SlamResult(
            frame_trajectory(frames.times, veh), stem_map, stats, pose_covs, graph=saved
        )
