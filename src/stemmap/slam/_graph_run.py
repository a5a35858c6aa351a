"""The incremental phase of :class:`stemmap.slam.graph.Isam2Slam`: its run state and keyframe steps.

Split out of ``Isam2Slam._run`` (517 lines of closures over some 60 local variables); the
method is described in :mod:`stemmap.slam.graph` and docs/algorithms/slam.md ("Front-end",
"Revisits", "Odometry self-calibration", "Maps reused across sessions"). :class:`Isam2Run`
holds what the keyframe loop carries from one keyframe to the next, and each step is one of
its methods, in the order of :meth:`Isam2Run.keyframes`:

1. :meth:`~Isam2Run.track`: the front-end on the keyframe's frames (numba,
   :func:`~stemmap.slam._isam2_track.track_keyframe`: tracked pose, association, new trees);
2. :meth:`~Isam2Run.close_keyframe`: the completed keyframe into the graph (pose, odometry
   factor or anchor prior, :meth:`~Isam2Run.add_measurements`), or left out
   (:class:`~stemmap.slam._graph_revisits.RevisitGate`);
3. :meth:`~Isam2Run.predict_keyframe`: the next keyframe's initial value (the tracked pose
   carried by dead reckoning), then :meth:`~Isam2Run.add_gnss`;
4. every ``update_every`` keyframes: :meth:`~Isam2Run.update` (iSAM2 and the online odometry
   calibration), :meth:`~Isam2Run.restart_tracker` (from the estimate, or localised on the map
   after left-out keyframes: :meth:`~Isam2Run.localise_tracker`) and
   :meth:`~Isam2Run.refresh_trees`.

The factor graph itself (iSAM2, the full graph for the batch steps, the batch not yet given to
iSAM2) is an :class:`Isam2Graph`, the landmark bookkeeping a :class:`Landmarks`. The batch
optimisation and the read-out after the loop are in :mod:`stemmap.slam.graph`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stemmap._memory import TRIM_INTERVAL_S, HeapTrimmer
from stemmap.slam._graph_localise import localise_windows, restart_covariance
from stemmap.slam._graph_odometry import frame_odometry, keyframe_odometry
from stemmap.slam._graph_result import LANDMARK_FILL, new_landmarks, tracker_params
from stemmap.slam._graph_revisits import LeftOutMeasurements, RevisitGate, anchor_prior
from stemmap.slam._graph_session import seed_earlier_session
from stemmap.slam._isam2_track import grow_landmarks, track_keyframe
from stemmap.slam.base import SlamProblem
from stemmap.slam.gnss import gnss_factors, plan_gnss, robust_kernel, with_gnss_frame
from stemmap.slam.motion import between, compose
from stemmap.types import FloatArray, wrap_angle

__all__ = ["Isam2Graph", "Isam2Run", "Landmarks"]

log = logging.getLogger("stemmap.slam.graph")


@dataclass
class Landmarks:
    """The landmark bookkeeping of a run (numpy, grown geometrically; filled by the numba
    tracker, :func:`~stemmap.slam._graph_result.new_landmarks`).

    Per tree: ``xy`` the estimate the tracker associates with, ``dsum`` / ``dn`` the sum and
    count of its diameter measurements, ``nobs`` observations, ``first`` / ``last`` frame seen,
    ``inc`` last frame whose observation is in iSAM2, ``in_graph``, ``ref`` iSAM2 updates at
    the last refresh of ``xy``, ``nfac`` measurement factors; ``n`` trees so far.
    """

    xy: FloatArray
    dsum: FloatArray
    dn: np.ndarray
    nobs: np.ndarray
    first: np.ndarray
    last: np.ndarray
    inc: np.ndarray
    in_graph: np.ndarray
    ref: np.ndarray
    nfac: np.ndarray
    n: int = field(default=0, init=False)

    @classmethod
    def empty(cls, cap: int) -> Landmarks:
        """Room for ``cap`` trees, none yet."""
        return cls(*new_landmarks(cap))

    def arrays(self) -> tuple[np.ndarray, ...]:
        """The arrays in the order of :data:`~stemmap.slam._graph_result.LANDMARK_FILL`."""
        return (
            self.xy, self.dsum, self.dn, self.nobs, self.first, self.last, self.inc,
            self.in_graph, self.ref, self.nfac,
        )  # fmt: skip

    def reserve(self, need: int) -> None:
        """Room for at least ``need`` trees (:func:`~stemmap.slam._isam2_track.grow_landmarks`)."""
        if need > self.xy.shape[0]:
            (self.xy, self.dsum, self.dn, self.nobs, self.first, self.last, self.inc,
             self.in_graph, self.ref, self.nfac) = grow_landmarks(
                need, self.arrays(), LANDMARK_FILL
            )  # fmt: skip


class Isam2Graph:
    """The factor graph of a run: the iSAM2 instance, every factor (``all``: the batch steps at
    the end rebuild from it) and the batch not yet given to iSAM2 (factors ``new_f``, initial
    values ``new_v``, indices of iSAM2 factors to remove ``remove_idx``)."""

    def __init__(self, gtsam: Any, cfg: Any) -> None:
        self._gtsam = gtsam
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(cfg.relinearize_threshold)
        params.relinearizeSkip = cfg.relinearize_skip
        self.isam: Any = gtsam.ISAM2(params)  # (freed after the incremental phase)
        self.all = gtsam.NonlinearFactorGraph()
        self.new_f = gtsam.NonlinearFactorGraph()
        self.new_v = gtsam.Values()
        self.remove_idx: list[int] = []
        self.n_updates = 0  # iSAM2 updates so far

    def add(self, fac: Any) -> None:
        """A factor into the graph (and into the next iSAM2 update)."""
        self.new_f.add(fac)
        self.all.add(fac)

    def insert(self, key: int, value: Any) -> None:
        """The initial value of a new variable."""
        self.new_v.insert(key, value)

    def pose(self, key: int) -> Any:
        """The current estimate of pose ``key`` (its initial value while not in iSAM2)."""
        if self.new_v.exists(key):
            return self.new_v.atPose2(key)
        return self.isam.calculateEstimatePose2(key)

    def pending(self) -> bool:
        """Whether anything waits for the next iSAM2 update."""
        return bool(self.new_f.size() or self.new_v.size() or self.remove_idx)

    def update(self) -> None:
        """One iSAM2 update with the pending batch."""
        self.isam.update(self.new_f, self.new_v, self.remove_idx)
        self.remove_idx.clear()
        self.n_updates += 1
        self.new_f = self._gtsam.NonlinearFactorGraph()
        self.new_v = self._gtsam.Values()


class Isam2Run:
    """One run of :class:`~stemmap.slam.graph.Isam2Slam` on ``problem`` (settings ``cfg``, an
    :class:`~stemmap.slam._graph_config.Isam2Config`): the set-up in the constructor, the
    incremental phase in :meth:`keyframes` (see the module docs for its steps).

    Frames and keyframes: ``kf_of`` (F,) the keyframe of each frame, ``kf_frames`` (K,) the
    frame of each keyframe; ``fo`` the dead reckoning of every frame
    (:class:`~stemmap.slam._graph_odometry.FrameOdometry`), ``odo`` the keyframe odometry with
    its calibration (:class:`~stemmap.slam._graph_odometry.KeyframeOdometry`; ``c_cur`` the
    online estimate used by every new odometry factor). The graph: ``graph``
    (:class:`Isam2Graph`), ``in_graph_k`` (K,) keyframes with a pose in it, ``kf_init`` (K, 3)
    the front-end's sensor pose of every keyframe, the factors by kind (kept when the batch
    steps rebuild the graph), ``lm`` the trees (:class:`Landmarks`), ``skipped`` the
    measurements of the keyframes left out (``gate`` decides,
    :class:`~stemmap.slam._graph_revisits.RevisitGate`). The tracker: ``trk`` / ``P_trk`` its
    sensor pose and covariance at frame ``fc[0]``, ``window`` the last keyframe's merged
    measurements.
    """

    def __init__(self, gtsam: Any, cfg: Any, problem: SlamProblem) -> None:
        from gtsam.symbol_shorthand import L, V, W, X

        self.gtsam, self.cfg = gtsam, cfg
        self.XK, self.LK, self.WK, self.VK = X, L, W, V
        self.t_start = time.perf_counter()
        self.problem = with_gnss_frame(problem)  # the graph lives in the frame of the GNSS fixes
        self.frames = self.problem.frames
        self.nf = len(self.frames)
        self._set_up_odometry()
        self._set_up_graph()
        self._set_up_tracker()

    def _set_up_odometry(self) -> None:
        """Keyframes, the frame and keyframe odometry (_graph_odometry), the GNSS plan."""
        cfg, problem = self.cfg, self.problem
        a, b = problem.sensor_offset
        self.T_vs = self.gtsam.Pose2(a, b, 0.0)
        self.kf_of = np.arange(self.nf) // cfg.keyframe_every  # keyframe index of each frame
        self.kf_frames = np.arange(0, self.nf, cfg.keyframe_every)  # frame of each keyframe
        self.nk = int(self.kf_frames.size)
        # odometry between consecutive frames (for association and drift)
        self.fo = frame_odometry(problem, self.kf_of, self.kf_frames)
        # keyframe odometry with its self-calibration (steering / yaw-rate offset, speed
        # scale): odo.c_used[i] is the calibration inside the factor of keyframes (i, i+1)
        kf_times = self.frames.times[self.kf_frames]
        self.odo, kf_dr = keyframe_odometry(problem, cfg, kf_times)
        self.gnss_plan = (
            None
            if problem.gnss is None
            else plan_gnss(problem, problem.gnss, kf_times, kf_dr, self.odo.cov_k)
        )
        self.c_cur = np.zeros(2)  # online estimate, used by every new odometry factor
        self.cal_seg = 0  # segment of the last online estimate
        # keyframes with a GNSS fix always enter the graph (the fix hangs from their pose)
        self.must_keep = np.zeros(self.nk, dtype=bool)
        if self.gnss_plan is not None:
            self.must_keep[np.asarray(self.gnss_plan.kf, dtype=np.int64)] = True

    def _set_up_graph(self) -> None:
        """The graph's first pose and its prior, the robust kernels, the earlier session."""
        gtsam, cfg, problem, XK = self.gtsam, self.cfg, self.problem, self.XK
        # one (stateless) robust kernel shared by every measurement factor
        self.kernel = robust_kernel(gtsam, cfg.robust, cfg.robust_k)
        self.gnss_kernel = robust_kernel(gtsam, cfg.gnss_robust, cfg.gnss_robust_k)
        self.prior_kernel = robust_kernel(gtsam, cfg.prior_map_robust, cfg.robust_k)
        self.graph = Isam2Graph(gtsam, cfg)
        self.s0 = gtsam.Pose2(*problem.initial_pose).compose(self.T_vs)
        prior = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(cfg.prior_sigmas if problem.prior_map is None else cfg.reloc_prior_sigmas)
        )
        self.pf = gtsam.PriorFactorPose2(XK(0), self.s0, prior)  # (swapped by add_gnss)
        self.gnss_fac: list[Any] = []  # the GNSS factors in the graph (kept when rebuilding)
        self.gnss_keys: list[int] = []
        self.g_next = 0  # next fix of gnss_plan to add
        self.graph.add(self.pf)
        self.meas_rec: list[tuple[int, int, float, float, float, float]] = []
        self.meas_fac: list[Any] = []  # the factor of each meas_rec entry (reused to rebuild)
        self.odo_fac: list[Any] = []  # the odometry factors of the graph, in keyframe order
        self.edges: list[tuple[int, int]] = []  # the graph keyframes each odometry factor links
        self.anchor_fac: list[Any] = []  # priors of keyframes after long left-out runs (kept)
        self.graph.insert(XK(0), self.s0)
        self.in_graph_k = np.zeros(self.nk, dtype=bool)  # keyframes with a pose in the graph
        self.in_graph_k[0] = True
        self.gk = np.zeros(0, dtype=np.int64)  # the graph keyframes (set after the loop)
        self.kf_init = np.zeros((self.nk, 3))  # the front-end's sensor pose of every keyframe
        self.kf_init[0] = (self.s0.x(), self.s0.y(), self.s0.theta())
        # measurements of the keyframes left out of the graph (_graph_revisits)
        self.skipped = LeftOutMeasurements()
        n_prior = 0 if problem.prior_map is None else len(problem.prior_map)
        self.lm = lm = Landmarks.empty(n_prior + 1024 if n_prior else 1024)
        # an earlier session (_graph_session): its map's trees as landmarks 0..n-1 held by
        # marginal priors, or its whole graph continued (_graph_continue)
        earlier = seed_earlier_session(
            gtsam, problem, cfg, (self.LK, self.WK, self.VK),
            (lm.xy, lm.dsum, lm.dn, lm.nobs, lm.in_graph), meas_noise=self.meas_noise,
            prior_kernel=self.prior_kernel, add_factor=self.graph.add,
            add_value=self.graph.insert,
        )  # fmt: skip
        lm.n, self.pmap, self.cont = earlier.n_lm, earlier.pmap, earlier.cont
        self.map_fac, self.joint_fac = earlier.map_fac, earlier.joint_fac

    def _set_up_tracker(self) -> None:
        """The front-end tracker's state, parameters and output buffers (track_keyframe)."""
        cfg, frames = self.cfg, self.frames
        self.kparams = tracker_params(cfg)
        self.ptr = np.ascontiguousarray(frames.ptr, dtype=np.int64)
        self.f_rng = np.ascontiguousarray(frames.ranges, dtype=np.float64)
        self.f_brg = np.ascontiguousarray(frames.bearings, dtype=np.float64)
        self.f_dia = np.ascontiguousarray(frames.diameters, dtype=np.float64)
        self.cov_fc = np.ascontiguousarray(self.fo.cov_f)
        self.trk = np.array([self.s0.x(), self.s0.y(), self.s0.theta()])
        self.P_floor = np.diag(np.array(cfg.track_floor_sigmas) ** 2)
        self.P_trk = self.P_floor.copy()
        self.fc = np.zeros(1, dtype=np.int64)  # the frame the tracker's pose is at
        self.f_upd = 0  # frames before it: every observation in (or redundant with) the graph
        self.counters = np.zeros(6, dtype=np.int64)  # (C_LOCAL ... C_FAR of _isam2_track)
        kfe = cfg.keyframe_every
        out_cap = int(np.diff(self.ptr).reshape(-1)[: self.nf].max(initial=0)) * kfe + 1
        self.out = (
            np.zeros(out_cap, dtype=np.int64),
            np.zeros(out_cap),
            np.zeros(out_cap),
            np.zeros(out_cap),
            np.zeros(out_cap),
        )  # (j, kx, ky, wxy, wth)
        self.window: list[Any] = []  # the last keyframe's measurements (track_keyframe)
        self.n_factors_meas = self.n_single_skipped = 0
        # freed heap back to the OS every TRIM_INTERVAL_S of CPU time (glibc; changes no
        # value): RSS then follows the heap in use on long drives, used as a library too
        # (docs/reliability.md "Soak"; shared with stemmap map's own trimmer)
        self.trim = HeapTrimmer(TRIM_INTERVAL_S)
        self.g_last = 0  # the last keyframe in the graph
        # why keyframes entered the graph (a revisit that enters is one of these)
        self.entered = {"forced": 0, "new_tree": 0, "young_tree": 0}
        self.gate = RevisitGate(cfg, self.kf_init[0, :2])  # which keyframes stay out
        self.d_last = np.zeros(3)  # the calibrated increment of the last step (k-1 -> k)
        self.force_until = 0  # keyframes before this enter the graph (the tracker was lost)
        self.n_map_fix = self.n_map_lost = 0

    def meas_noise(self, sigmas: FloatArray) -> Any:
        """Noise of one bearing-range factor, ``sigmas`` = (sigma_bearing, sigma_range)."""
        base = self.gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        if self.kernel is None:
            return base
        return self.gtsam.noiseModel.Robust.Create(self.kernel, base)

    def odo_factor(self, ka: int, kb: int, d: FloatArray | None = None) -> Any:
        """BetweenFactorPose2 of graph keyframes ``ka < kb`` (KeyframeOdometry.factor)."""
        return self.odo.factor(self.gtsam, self.XK, ka, kb, d)

    def keyframes(self, progress: Callable[[int, int], None] | None) -> None:
        """The incremental phase: every keyframe tracked and closed (into the graph or left
        out), iSAM2 updated every ``update_every`` keyframes and once more at the end."""
        for k in range(self.nk):
            if k > 0:
                self.next_keyframe(k)
            f1 = self.track(k)
            if progress is not None:
                progress(f1, self.nf)
            self.trim()
        self.close_keyframe(self.nk - 1)
        self.add_gnss(self.nk - 1)
        if self.graph.pending():
            self.graph.update()
        self.gk = np.flatnonzero(self.in_graph_k)  # the graph keyframes (key order)

    def next_keyframe(self, k: int) -> None:
        """Keyframe ``k - 1`` is complete: closed; keyframe ``k`` predicted; on an update
        keyframe iSAM2 updated and the tracker restarted."""
        self.odo.c_used[k - 1] = self.c_cur
        d_step = self.odo.step(k - 1, self.c_cur)  # step k-1 -> k with the current calibration
        # close the previous keyframe (the step into it is d_last), then this one's initial
        # value: the tracked pose carried to it by dead reckoning
        self.close_keyframe(k - 1)
        self.d_last = d_step
        init, rel = self.predict_keyframe(k)
        self.add_gnss(k - 1)
        if k % self.cfg.update_every == 0:
            p = self.update(k, d_step)  # (None: the front-end tracks on the map alone)
            self.restart_tracker(k, d_step, init, rel, p)
            self.refresh_trees()

    def predict_keyframe(self, k: int) -> tuple[Any, FloatArray]:
        """Keyframe ``k``'s initial value: the tracked pose carried by the dead-reckoned sensor
        motion ``rel`` from the tracker's frame (both returned; ``kf_init[k]`` set)."""
        trk, sp_dr = self.trk, self.fo.sp_dr
        rel = between(sp_dr[int(self.fc[0])], sp_dr[int(self.kf_frames[k])])
        ct_, st_ = math.cos(trk[2]), math.sin(trk[2])
        init = self.gtsam.Pose2(
            trk[0] + ct_ * rel[0] - st_ * rel[1],
            trk[1] + st_ * rel[0] + ct_ * rel[1],
            trk[2] + rel[2],
        )
        self.kf_init[k] = (init.x(), init.y(), init.theta())
        return init, rel

    def update(self, k: int, d_step: FloatArray) -> Any:
        """iSAM2 update with the pending batch. Returns keyframe ``k``'s estimate (keyframe
        ``k - 1``'s carried by the odometry step ``d_step``) when ``k - 1`` is in the graph, else
        None; then, once per calibration segment, the online calibration from the last
        ``calib_window`` keyframes (:meth:`KeyframeOdometry.online
        <stemmap.slam._graph_odometry.KeyframeOdometry.online>`): new odometry factors use it."""
        if not self.graph.pending():
            return None
        self.graph.update()
        if self.g_last != k - 1:
            return None
        isam, XK, cfg = self.graph.isam, self.XK, self.cfg
        p = isam.calculateEstimatePose2(XK(k - 1)).compose(
            self.gtsam.Pose2(float(d_step[0]), float(d_step[1]), float(d_step[2]))
        )
        if self.odo.calibrate and k // cfg.calib_every != self.cal_seg:
            self.cal_seg = k // cfg.calib_every
            self.c_cur = self.odo.online(
                k, p, self.in_graph_k, lambda i_: isam.calculateEstimatePose2(XK(i_)), cfg,
                self.c_cur,
            )  # fmt: skip
        return p

    def restart_tracker(
        self, k: int, d_step: FloatArray, init: Any, rel: FloatArray, p: Any
    ) -> None:
        """The tracker restarts at keyframe ``k`` from the estimate ``p`` (:meth:`update`), or,
        after keyframes left out of the graph, from its own pose localised on the map
        (:meth:`localise_tracker`; lost: the next keyframes are forced into the graph), else
        carries on from ``init``. Its covariance is relative to the trees just seen (the drift
        since the others were seen covers them), widened by a disagreement with the tracker
        (:func:`~stemmap.slam._graph_localise.restart_covariance`, a sharp turn)."""
        restart = p is not None
        P_restart = self.P_floor
        if not restart and (k - 1) in self.skipped:
            p_fix, P_restart = self.localise_tracker(k, d_step)
            if p_fix is None:
                self.force_until = k + self.cfg.update_every  # lost: map the next ones
                self.n_map_lost += 1
            else:
                p, restart = p_fix, True
                self.n_map_fix += 1
        dth = float(wrap_angle(p.theta() - init.theta())) if restart else 0.0
        if restart:
            P_restart = restart_covariance(P_restart, p.x() - init.x(), p.y() - init.y(), dth)
            self.trk[:2] = (p.x(), p.y())
        else:
            self.trk[:2] = (init.x(), init.y())
        self.trk[2] = self.trk[2] + rel[2] + dth
        self.P_trk[:, :] = P_restart
        f0 = int(self.kf_frames[k])
        self.fc[0] = f0
        # every observation so far is in (or redundant with) the graph
        self.f_upd = f0
        lm = self.lm
        lm.inc[: lm.n] = lm.last[: lm.n]

    def refresh_trees(self) -> None:
        """The tracker's estimate of the trees that can be associated soon (within the search
        radius plus one keyframe of driving) from iSAM2; far trees are refreshed when
        approached, and only trees not refreshed since the last update (in localisation mode
        no update runs for long)."""
        lm, n_upd = self.lm, self.graph.n_updates
        if not lm.n:
            return
        ing = np.flatnonzero(lm.in_graph[: lm.n] & (lm.ref[: lm.n] < n_upd))
        dxy = lm.xy[ing] - self.trk[:2]
        near_k = ing[dxy[:, 0] ** 2 + dxy[:, 1] ** 2 < (self.cfg.max_range + 30.0) ** 2]
        if near_k.size:
            lm.ref[near_k] = n_upd
            isam, LK = self.graph.isam, self.LK
            lm.xy[near_k] = [isam.calculateEstimatePoint2(LK(jn)) for jn in near_k.tolist()]

    def track(self, k: int) -> int:
        """The front-end on keyframe ``k``'s frames (:func:`~stemmap.slam._isam2_track.
        track_keyframe`): ``window`` its merged measurements, new trees in ``lm``. Returns the
        frame after the keyframe's last."""
        f0 = int(self.kf_frames[k])
        f1 = min(f0 + self.cfg.keyframe_every, self.nf)
        lm, fo = self.lm, self.fo
        # room for every detection of this keyframe becoming a new tree
        lm.reserve(lm.n + int(self.ptr[f1] - self.ptr[f0]))
        n_lm, _, *window = track_keyframe(
            f0, f1, f0, self.f_upd, self.ptr, self.f_rng, self.f_brg, self.f_dia, fo.sp_dr,
            self.cov_fc, fo.cum_xy, fo.cum_th, fo.cum_dist, self.trk, self.P_trk, self.fc,
            lm.xy, lm.dsum, lm.dn, lm.nobs, lm.first, lm.last, lm.inc, lm.n, self.kparams,
            *self.out, self.counters,
        )  # fmt: skip
        lm.n, self.window = n_lm, window
        return f1

    def close_keyframe(self, kc: int) -> None:
        """Keyframe ``kc``'s window is complete: into the graph (pose, odometry from the last
        graph keyframe, its factors), or left out when it only re-observes well-mapped trees
        (:meth:`RevisitGate.leave_out <stemmap.slam._graph_revisits.RevisitGate.leave_out>`;
        its pose is localised at the end). A keyframe after a long left-out run is anchored
        at its tracked pose instead (:func:`~stemmap.slam._graph_revisits.anchor_prior`)."""
        cfg, window, lm = self.cfg, self.window, self.lm
        n_skip_w = int(window[4]) if window else 0
        revisits = cfg.revisit_factors > 0 and kc > 0 and bool(window) and not self.must_keep[kc]
        # at a place visited before (RevisitGate) young trees pull no keyframe in; a lost
        # tracker forces keyframes in
        s_kc = float(self.fo.cum_dist[self.kf_frames[kc]])  # path distance (m): visits
        trees_w = window[0] if window else np.zeros(0, dtype=np.int64)
        anchored = 0 < cfg.revisit_anchor_after < kc - self.g_last
        if self.gate.leave_out(
            self.kf_init[kc, :2], s_kc, trees_w, lm.in_graph, lm.nfac,
            allowed=revisits and kc >= self.force_until, linked=not anchored,
        ):  # fmt: skip
            self.skipped.add(kc, window[0], window[1], window[2], window[3])
            self.n_single_skipped += n_skip_w
            return
        if revisits:  # why it entered
            new_t = window[0].size and not np.all(lm.in_graph[window[0]])
            forced = kc < self.force_until
            self.entered["forced" if forced else "new_tree" if new_t else "young_tree"] += 1
        if kc > 0:
            self.add_keyframe(kc, anchored)
            self.gate.entered(self.kf_init[kc, :2], s_kc, anchored)
        self.add_measurements(kc)

    def add_keyframe(self, kc: int, anchored: bool) -> None:
        """Keyframe ``kc``'s pose into the graph at its tracked value, linked to the last graph
        keyframe by odometry or, ``anchored``, held by a prior at its tracked pose."""
        g_last, XK = self.g_last, self.XK
        if anchored:
            # after a long left-out run: anchored at its tracked pose, not linked to the
            # remote graph keyframe (anchor_prior)
            bf = anchor_prior(
                self.gtsam, XK(kc), self.kf_init[kc], self.odo.measured(slice(g_last, kc)),
                self.odo.cov_k[g_last:kc],
            )  # fmt: skip
            self.anchor_fac.append(bf)
        else:
            bf = self.odo_factor(g_last, kc, self.d_last if g_last == kc - 1 else None)
            self.odo_fac.append(bf)
            self.edges.append((g_last, kc))
        self.graph.add(bf)
        self.graph.insert(XK(kc), self.gtsam.Pose2(*(float(q) for q in self.kf_init[kc])))
        self.in_graph_k[kc] = True
        self.g_last = kc

    def add_measurements(self, k: int) -> None:
        """The window's detections, merged per tree, as one bearing-range factor each from
        keyframe ``k`` (new trees get their initial value)."""
        if not self.window:
            return
        trees_w, brg_w, rr, sig, n_skip = self.window
        self.n_single_skipped += n_skip  # not confirmed by a second scan of the window
        js = trees_w.tolist()
        if not js:
            return
        gtsam, LK, lm = self.gtsam, self.LK, self.lm
        bl, rl = brg_w.tolist(), rr.tolist()
        xk = self.XK(k)
        for t_, j in enumerate(js):
            if not lm.in_graph[j]:
                self.graph.insert(LK(j), lm.xy[j].copy())
                lm.in_graph[j] = True
            fac = gtsam.BearingRangeFactor2D(
                xk, LK(j), gtsam.Rot2(bl[t_]), rl[t_], self.meas_noise(sig[t_])
            )
            self.graph.add(fac)
            self.meas_fac.append(fac)
        lm.nfac[trees_w] += 1
        self.gate.factored(trees_w, float(self.fo.cum_dist[self.kf_frames[k]]))
        sbl, srl = sig[:, 0].tolist(), sig[:, 1].tolist()
        self.meas_rec.extend(zip([k] * len(js), js, bl, rl, sbl, srl, strict=True))
        self.n_factors_meas += len(js)

    def localise_tracker(self, k: int, d_step: FloatArray) -> tuple[Any, FloatArray]:
        """Keyframe ``k``'s sensor pose from the left-out keyframes before it localised on the
        map (:func:`~stemmap.slam._graph_localise.localise_windows`; None when the map
        contradicts the tracker), and the tracker's covariance to restart with (its own when
        too few trees tell)."""
        cfg, fo, lm, skipped = self.cfg, self.fo, self.lm, self.skipped
        ks = [i for i in range(max(k - cfg.update_every, 0), k) if i in skipped]
        fl = int(self.kf_frames[k - 1])
        prior_p = compose(
            self.trk[None], between(fo.sp_dr[int(self.fc[0])][None], fo.sp_dr[fl][None])
        )[0]
        fk = self.kf_frames[ks]  # (the dead reckoning's drift from each to fl, below)
        vr, vb = cfg.sigma_range**2, cfg.sigma_bearing**2
        fix = localise_windows(
            prior_p, self.P_trk + self.P_floor, [skipped[i] for i in ks],
            between(fo.sp_dr[fl][None], fo.sp_dr[fk]), lm.xy,
            (vr + 400.0 * vb) / np.maximum(lm.nobs, 1),
            np.abs(np.column_stack((fo.cum_xy[fl] - fo.cum_xy[fk], fo.cum_th[fl] - fo.cum_th[fk]))),
        )  # fmt: skip
        if fix.lost:
            log.debug("iSAM2: tracker not localised at keyframe %d: %s", k - 1, fix.reason)
            return None, self.P_floor
        if fix.ok:
            self.kf_init[k - 1] = fix.pose
        pose = self.gtsam.Pose2(*(float(q) for q in fix.pose))  # (too few trees: the prior)
        d_s = self.gtsam.Pose2(float(d_step[0]), float(d_step[1]), float(d_step[2]))
        return pose.compose(d_s), fix.cov if fix.ok else self.P_trk.copy()

    def add_gnss(self, k_done: int) -> None:
        """Add the fixes hanging from keyframes <= ``k_done`` (their time has passed).

        With the first fix the tight prior on ``X(0)`` (which fixed the gauge until then) is
        swapped for the weak ``gnss_prior_sigmas`` one: from now on the fixes give the frame.
        (A weak prior from the start leaves the first updates without a fix nearly
        indeterminate: GTSAM refuses them.)
        """
        plan, graph, gtsam = self.gnss_plan, self.graph, self.gtsam
        if plan is None:
            return
        g1 = int(np.searchsorted(plan.kf, k_done, side="right"))
        if self.g_next == 0 and g1 > 0:
            weak = gtsam.PriorFactorPose2(
                self.XK(0), self.s0,
                gtsam.noiseModel.Diagonal.Sigmas(np.array(self.cfg.gnss_prior_sigmas)),
            )  # fmt: skip
            graph.all.replace(0, weak)
            if graph.n_updates == 0:  # still in the pending batch (its first factor)
                graph.new_f.replace(0, weak)
            else:
                graph.remove_idx.append(0)  # iSAM2 numbers factors in the order they came in
                graph.new_f.add(weak)
            self.pf = weak
        for i_g in range(self.g_next, g1):
            xk_ = self.XK(int(plan.kf[i_g]))
            facs, key, val = gnss_factors(plan, i_g, xk_, graph.pose(xk_), self.gnss_kernel)
            for fac_g in facs:
                graph.add(fac_g)
                self.gnss_fac.append(fac_g)
            graph.insert(key, val)
            self.gnss_keys.append(key)
        self.g_next = max(self.g_next, g1)

    def kf_poses(self, values: Any) -> FloatArray:
        """(K, 3) sensor poses of the graph keyframes in ``values`` (NaN elsewhere)."""
        out = np.full((self.nk, 3), np.nan)
        # (the continued graph's antenna poses V and poses W sort before X)
        n_w = 0 if self.cont is None else self.cont.n_poses + self.cont.saved.n_fixes
        out[self.gk] = self.gtsam.utilities.extractPose2(values)[n_w : n_w + self.gk.size]
        return out
