"""Online tree-landmark SLAM: sensor data in as it arrives, the current pose and map out (ours).

:class:`OnlineMapper` runs the iSAM2 back-end's method (:mod:`stemmap.slam.graph`: the same
numba front-end :func:`~stemmap.slam._isam2_track.track_keyframe`, the same factors and noise
models, :class:`~stemmap.slam.graph.Isam2Config`) one scan at a time:

* ``add_odometry(t, speed, steer)`` (or yaw rate for a unicycle model) and ``add_imu(t,
  yaw_rate)`` (unicycle model: the gyro's yaw rate replaces the odometry's) buffer controls;
* ``add_gnss(t, x, y, sigma)`` queues a fix, fused as in :mod:`stemmap.slam.gnss` once the
  keyframe after it has begun;
* ``add_scan(t, ranges, bearings, diameters)`` dead-reckons to ``t`` (pre-integration of the
  buffered controls), tracks and associates this scan's detections, and returns the current
  vehicle pose. Every ``keyframe_every`` scans a keyframe is closed (its detections merged per
  tree into bearing-range factors, the odometry factor added); every ``update_every``
  keyframes iSAM2 is updated.

**Bounded work and memory** (the batch back-end's graph grows for ever): every
``window_keyframes`` keyframes the smoother is *re-anchored*: a new iSAM2 starts from a prior
on the current keyframe pose (its marginal covariance) and the trees leave the optimiser with
their marginal covariance (:func:`stemmap.slam.graph._point_marginals` over the window's
graph). A tree seen again re-enters with that covariance as a prior (the mechanism of
:mod:`stemmap.slam.relocalise` for prior maps), so revisits still correct the current pose,
but old poses are no longer re-optimised. The marginals are treated as independent (the
pose-tree correlations of the closed window are dropped): a standard fixed-lag
approximation, slightly over-confident after a re-anchor. Work per scan is then bounded by
the window and by the trees within ``max_range`` + 10 m; memory holds the window's graph, the
trees (growing with the mapped area, not with time on a revisited area) and ~50 bytes per
scan of dead-reckoning bookkeeping (the front-end reads drift since a tree's last
observation from cumulative sums).

**Pose covariance** (issue 14; :attr:`OnlineMapper.pose_covs`, ``trajectory.csv`` of ``stemmap
map --realtime``): iSAM2's marginal of the latest keyframe at every update, carried scan by scan
and across re-anchors (:mod:`stemmap.slam._online_covariance`), times ``pose_cov_factor``.

Replaying a recorded log through the mapper: :func:`replay`
(:mod:`stemmap.slam._online_replay`).

Not done online (the batch back-end does them at the end of a run): the odometry
self-calibration, the duplicate merge and the final Levenberg-Marquardt pass. With GNSS, the
initial pose must already be in the GNSS frame (no look-ahead alignment); the tight prior on
the first pose is swapped for the weak ``gnss_prior_sigmas`` one when the first fix enters.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stemmap.errors import ConfigError, InputError
from stemmap.slam._graph_odometry import _sensor_between
from stemmap.slam._grow import _Grow
from stemmap.slam._isam2_track import (
    C_LOCAL,
    C_NEW,
    C_REACQ,
    C_SINGLE,
    merge_window,
    track_keyframe,
)
from stemmap.slam._online_covariance import PoseCovarianceCarry
from stemmap.slam._online_replay import replay
from stemmap.slam.base import Controls
from stemmap.slam.gnss import GnssPlan, gnss_factors, robust_kernel
from stemmap.slam.gnss_track import GnssOffsetFilter, GnssOffsetModel
from stemmap.slam.graph import Isam2Config, _point_marginals
from stemmap.slam.motion import between, compose, preintegrate
from stemmap.types import FloatArray, StemMap, Tree

__all__ = ["OnlineConfig", "OnlineMapper", "replay"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OnlineConfig:
    """Settings of :class:`OnlineMapper`.

    isam2 : the back-end's settings (``calibrate``, ``merge_dist``, ``batch_iterations`` and
        ``revisit_factors`` are batch-only and ignored here: the window bounds the work)
    window_keyframes : keyframes between re-anchors of the smoother (bounded work / memory)
    idle_keyframes : also re-anchor after this many keyframes without a tree measurement
        (a transit): the odometry chain alone would grow the window's pose uncertainty to
        where GTSAM finds the system indeterminate when trees appear again
    tree_sigma_floor : m, added (in quadrature) to a tree's marginal sigma when it leaves the
        optimiser (the dropped correlations)
    pose_cov_factor : variance factor on the reported pose covariances
        (:attr:`OnlineMapper.pose_covs`; the smoother's own are unscaled): 8.6 makes the median
        z² of Victoria Park's first half against the screened GPS (its own 1.14 m RMS counted)
        the calibrated 1.39 (docs/outputs.md, "Pose covariance columns"); the online mapper
        has no odometry self-calibration, so the odometry's bias is not in its covariance
    """

    isam2: Isam2Config = field(default_factory=Isam2Config)
    window_keyframes: int = 150
    idle_keyframes: int = 10
    tree_sigma_floor: float = 0.02
    pose_cov_factor: float = 8.6

    def __post_init__(self) -> None:
        if self.window_keyframes < 2 * self.isam2.update_every:
            raise ConfigError(
                f"OnlineConfig.window_keyframes must be >= 2 x update_every, got "
                f"{self.window_keyframes}."
            )
        if not self.pose_cov_factor > 0:
            raise ConfigError(
                f"OnlineConfig.pose_cov_factor must be > 0, got {self.pose_cov_factor}."
            )


class OnlineMapper:
    """Incremental iSAM2 tree-landmark SLAM fed one measurement at a time (module docs).

    Parameters
    ----------
    motion : AckermannModel or UnicycleModel
    sensor_offset : (a, b), m, laser in the vehicle frame
    initial_pose : vehicle pose at the first scan (in the GNSS frame when fixes are given)
    config : OnlineConfig
    gnss_lever_arm : (x, y), m, GNSS antenna in the vehicle frame
    gnss_offset_model : GnssOffsetModel, optional, the receiver's error model (e.g. a previous
        run's, metrics.json ``gnss_track.model``): enables :attr:`pose_gnss`, the pose as the
        receiver reads it (causal: from the fixes fused so far)
    """

    def __init__(
        self,
        motion: Any,
        sensor_offset: tuple[float, float] = (0.0, 0.0),
        initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        config: OnlineConfig | None = None,
        *,
        gnss_lever_arm: tuple[float, float] = (0.0, 0.0),
        gnss_offset_model: GnssOffsetModel | None = None,
    ) -> None:
        import gtsam

        self._g = gtsam
        self.cfg = config or OnlineConfig()
        c = self.cfg.isam2
        self.motion = motion
        self.kind = motion.kind
        self.offset = (float(sensor_offset[0]), float(sensor_offset[1]))
        self.lever = (float(gnss_lever_arm[0]), float(gnss_lever_arm[1]))
        self._gnss_track = (
            None if gnss_offset_model is None else GnssOffsetFilter(gnss_offset_model)
        )
        a, b = self.offset
        self.T_vs = gtsam.Pose2(a, b, 0.0)
        self.T_sv = self.T_vs.inverse()
        self.v0 = tuple(float(v) for v in initial_pose)
        # controls (kept from the previous keyframe's time on), gyro samples
        self._ct: list[float] = []
        self._cv: list[float] = []
        self._cs: list[float] = []
        self._imu_t: list[float] = []
        self._imu_w: list[float] = []
        # per-frame bookkeeping (the front-end's arrays, grown)
        self.times = _Grow(())
        self.veh = _Grow((3,))  # dead-reckoned vehicle poses
        self.sp_dr = _Grow((3,))  # dead-reckoned sensor poses, continuous heading
        self.cov_f = _Grow((3, 3))  # sensor-frame increment covariances (frame f -> f+1)
        self.cum_dist = _Grow(())
        self.cum_xy = _Grow(())
        self.cum_th = _Grow(())
        self.ptr = _Grow((), np.int64)
        self.ptr.append(0)
        self.rng = _Grow(())
        self.brg = _Grow(())
        self.dia = _Grow(())
        # trees
        self.lm_xy = _Grow((2,))
        self.lm_dsum = _Grow(())
        self.lm_dn = _Grow((), np.int64)
        self.lm_nobs = _Grow((), np.int64)
        self.lm_first = _Grow((), np.int64)
        self.lm_last = _Grow((), np.int64)
        self.lm_inc = _Grow((), np.int64, -1)
        self.lm_in_graph = _Grow((), np.bool_)
        self.lm_cov = _Grow((2, 2), np.float64, math.nan)
        self.n_lm = 0
        self.kparams = np.array(
            [
                c.sigma_range**2, c.sigma_bearing**2, (c.sigma_diameter or 1.0) ** 2,
                1.0 if c.sigma_diameter is not None else 0.0, c.gate_chi2, c.new_chi2,
                c.new_min_dist, c.max_range, c.max_drift_sigma**2, c.local_drift_sigma**2,
                c.consensus_chi2, c.drift_scale, c.min_window_obs,
            ]
        )  # fmt: skip
        self.counters = np.zeros(6, dtype=np.int64)
        self.P_floor = np.diag(np.array(c.track_floor_sigmas) ** 2)
        self.P = self.P_floor.copy()
        self.trk = np.zeros(3)
        self.fc = np.zeros(1, dtype=np.int64)
        self.f_upd = 0
        self.kernel = robust_kernel(gtsam, c.robust, c.robust_k)
        self.gnss_kernel = robust_kernel(gtsam, c.gnss_robust, c.gnss_robust_k)
        self._win: list[tuple[FloatArray, ...]] = []  # per-scan front-end output of the keyframe
        self.k = -1  # current keyframe
        self.kf_frame: list[int] = []  # first frame of each keyframe
        self.kf_est: dict[int, FloatArray] = {}  # latest estimate of each keyframe sensor pose
        self._gnss_q: list[tuple[float, float, float, float]] = []
        self._gnss_first = True
        self.n_gnss = 0
        self._new_isam()
        self.latency_s: list[float] = []
        self.cpu_s: list[float] = []
        self.k_meas = 0  # last keyframe with a tree measurement
        self._kd = np.zeros(3)  # vehicle increment since the keyframe's first scan
        self._kc = np.zeros((3, 3))
        self._cov = PoseCovarianceCarry(c.prior_sigmas)  # pose covariance (module docs)

    # ------------------------------------------------------------------ smoother life cycle
    def _new_isam(self) -> None:
        g = self._g
        p = g.ISAM2Params()
        p.setRelinearizeThreshold(self.cfg.isam2.relinearize_threshold)
        p.relinearizeSkip = self.cfg.isam2.relinearize_skip
        self.isam = g.ISAM2(p)
        self.graph = g.NonlinearFactorGraph()  # the current window's factors (for marginals)
        self.new_f = g.NonlinearFactorGraph()
        self.new_v = g.Values()
        self.remove_idx: list[int] = []
        self.k_anchor = max(self.k, 0)
        self.n_upd_window = 0

    def _add(self, fac: Any) -> None:
        self.new_f.add(fac)
        self.graph.add(fac)

    # ------------------------------------------------------------------ inputs
    def add_odometry(self, t: float, speed: float, steer: float) -> None:
        """One odometry sample: wheel speed (m/s) and steering angle (rad; yaw rate in rad/s for
        a unicycle model), held until the next sample."""
        if self._ct and t < self._ct[-1]:
            raise InputError(f"odometry sample at {t} s is older than the last ({self._ct[-1]}).")
        self._ct.append(float(t))
        self._cv.append(float(speed))
        self._cs.append(float(steer))

    def add_imu(self, t: float, yaw_rate: float) -> None:
        """A gyro sample (rad/s); with a unicycle model it replaces the odometry's yaw rate."""
        if self.kind != "unicycle":
            raise ConfigError("add_imu: the IMU yaw rate is used with a unicycle motion model.")
        self._imu_t.append(float(t))
        self._imu_w.append(float(yaw_rate))

    def add_gnss(self, t: float, x: float, y: float, sigma: float = 1.0) -> None:
        """A GNSS fix of the antenna (``gnss_lever_arm``), fused once its keyframe closes."""
        if not (math.isfinite(x) and math.isfinite(y) and sigma > 0):
            raise InputError(f"GNSS fix at {t} s: position must be finite and sigma > 0.")
        self._gnss_q.append((float(t), float(x), float(y), float(sigma)))

    def _controls(self) -> Controls:
        t = np.asarray(self._ct)
        s = np.asarray(self._cs)
        if self._imu_t and self.kind == "unicycle":
            it = np.asarray(self._imu_t)
            i = np.searchsorted(it, t, side="right") - 1
            s = np.where(i >= 0, np.asarray(self._imu_w)[np.clip(i, 0, None)], s)
        return Controls(t, np.asarray(self._cv), s, self.kind)

    def _dead_reckon(
        self, t0: float, t1: float, pose0: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Vehicle increment over [t0, t1] from the buffered controls (and its covariance)."""
        if len(self._ct) == 0 or t1 <= t0:
            return np.zeros(3), np.diag([1e-8, 1e-8, 1e-10])
        pre = preintegrate(self.motion, self._controls(), np.array([t0, t1]), pose0)
        return pre.deltas[0], pre.covs[0]

    # ------------------------------------------------------------------ per scan
    def add_scan(
        self, t: float, ranges: FloatArray, bearings: FloatArray, diameters: FloatArray
    ) -> tuple[float, float, float]:
        """Process one scan's tree detections (polar, sensor frame); returns the vehicle pose.

        Run the mapper inside :func:`stemmap.slam.base.single_threaded_blas` (as
        :func:`replay` does): multi-threaded BLAS on these small matrices costs CPU out of all
        proportion on a shared machine, and setting the limit per scan costs ~10 ms.
        """
        t_in, c_in = time.perf_counter(), time.process_time()
        pose = self._scan(float(t), ranges, bearings, diameters)
        self.latency_s.append(time.perf_counter() - t_in)
        self.cpu_s.append(time.process_time() - c_in)
        return pose

    def _accumulate(self, d: FloatArray, c: FloatArray) -> None:
        """Chain a frame increment (``d``, covariance ``c`` in its start frame) onto the
        keyframe's: ``D' = D ⊕ d``, ``Σ' = J_D Σ J_Dᵀ + J_d c J_dᵀ`` (additive errors in the
        keyframe's start frame, the convention of :func:`stemmap.slam.motion.preintegrate`)."""
        D, S = self._kd, self._kc
        cz, sz = math.cos(D[2]), math.sin(D[2])
        wx, wy = cz * d[0] - sz * d[1], sz * d[0] + cz * d[1]
        Jd_ = np.array([[1.0, 0.0, -wy], [0.0, 1.0, wx], [0.0, 0.0, 1.0]])
        Jn = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
        self._kc = Jd_ @ S @ Jd_.T + Jn @ c @ Jn.T
        self._kd = np.array([D[0] + wx, D[1] + wy, D[2] + d[2]])

    def _scan(self, t: float, r: Any, b: Any, d: Any) -> tuple[float, float, float]:
        c = self.cfg.isam2
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        b = np.asarray(b, dtype=np.float64).reshape(-1)
        d = np.asarray(d, dtype=np.float64).reshape(-1)
        if not (r.shape == b.shape == d.shape):
            raise InputError("add_scan: ranges, bearings and diameters must have one length.")
        f = self.times.n
        a_, b_ = self.offset
        if f == 0:
            v = np.array(self.v0)
            self.cum_dist.append(0.0)
            self.cum_xy.append(0.0)
            self.cum_th.append(0.0)
        else:
            if t < self.times.a[f - 1]:
                raise InputError(f"scan at {t} s is older than the previous one.")
            v_prev = self.veh.a[f - 1]
            dv, cv = self._dead_reckon(float(self.times.a[f - 1]), t, v_prev)
            v = compose(v_prev, dv)
            self._accumulate(dv, cv)
            _, cs = _sensor_between(dv[None], cv[None], self.offset)
            self.cov_f.append(cs[0])
            self.cum_dist.append(self.cum_dist.a[f - 1] + math.hypot(dv[0], dv[1]))
            self.cum_xy.append(self.cum_xy.a[f - 1] + 0.5 * (cs[0, 0, 0] + cs[0, 1, 1]))
            self.cum_th.append(self.cum_th.a[f - 1] + cs[0, 2, 2])
        self.times.append(t)
        sp_prev = self.sp_dr.a[f - 1].copy() if f else None
        self.veh.append(v)
        th_c = (
            v[2]
            if f == 0
            else self.sp_dr.a[f - 1, 2]
            + float(math.remainder(v[2] - self.veh.a[f - 1, 2], 2 * math.pi))
        )
        cv_, sv_ = math.cos(v[2]), math.sin(v[2])
        self.sp_dr.append((v[0] + cv_ * a_ - sv_ * b_, v[1] + sv_ * a_ + cv_ * b_, th_c))
        self.rng.extend(r)
        self.brg.extend(b)
        self.dia.extend(d)
        self.ptr.append(self.ptr.a[f] + r.shape[0])
        if sp_prev is not None:  # carry the covariance with this scan's sensor increment
            self._cov.carry(sp_prev, self.sp_dr.a[f], self.cov_f.a[f - 1])
        if f % c.keyframe_every == 0:
            self._new_keyframe(f)
        # front-end on this scan (room for every detection becoming a tree)
        for arr in (self.lm_xy, self.lm_dsum, self.lm_dn, self.lm_nobs, self.lm_first,
                    self.lm_last, self.lm_inc, self.lm_in_graph, self.lm_cov):  # fmt: skip
            arr.room(r.shape[0])
        cap = r.shape[0] + 1
        o_j = np.zeros(cap, dtype=np.int64)
        o_kx, o_ky, o_wxy, o_wth = (np.zeros(cap) for _ in range(4))
        n_lm, n_out, *_ = track_keyframe(
            f, f + 1, self.kf_frame[-1], self.f_upd, self.ptr.a, self.rng.a, self.brg.a,
            self.dia.a, self.sp_dr.a, self.cov_f.a, self.cum_xy.a, self.cum_th.a,
            self.cum_dist.a, self.trk, self.P, self.fc, self.lm_xy.a, self.lm_dsum.a,
            self.lm_dn.a, self.lm_nobs.a, self.lm_first.a, self.lm_last.a, self.lm_inc.a,
            self.n_lm, self.kparams, o_j, o_kx, o_ky, o_wxy, o_wth, self.counters,
        )  # fmt: skip
        out = (o_j, o_kx, o_ky, o_wxy, o_wth)
        for arr in (self.lm_xy, self.lm_dsum, self.lm_dn, self.lm_nobs, self.lm_first,
                    self.lm_last, self.lm_inc, self.lm_in_graph, self.lm_cov):  # fmt: skip
            arr.n = n_lm
        self.n_lm = n_lm
        self._win.append(tuple(o[:n_out].copy() for o in out))
        pose = self.pose
        self._cov.record(pose[2])
        return pose

    @property
    def pose_covs(self) -> FloatArray:
        """(N, 3, 3) covariance of the vehicle pose returned for every scan so far (x, y, θ,
        map frame): each scan's sensor-pose covariance (GTSAM tangent) carried through the
        mounting and rotated, as :func:`~stemmap.slam._graph_odometry.frame_covariances` does
        with every frame its own anchor (done here, not per scan), times
        ``pose_cov_factor``."""
        return self._cov.pose_covs(self.cfg.pose_cov_factor, self.offset)

    @property
    def pose(self) -> tuple[float, float, float]:
        """Current vehicle pose: the tracked sensor pose carried to the last scan, ∘ T_sv."""
        f = self.times.n - 1
        if f < 0:
            return self.v0  # type: ignore[return-value]
        g0 = int(self.fc[0])
        rel = between(self.sp_dr.a[g0], self.sp_dr.a[f])
        s = compose(self.trk, rel)
        v = compose(s, np.array([-self.offset[0], -self.offset[1], 0.0]))
        return (float(v[0]), float(v[1]), float(math.remainder(v[2], 2 * math.pi)))

    @property
    def pose_gnss(self) -> tuple[float, float, float, float]:
        """Current pose as the GNSS receiver reads it, ``(x, y, theta, std_m)``: :attr:`pose`
        + the causal offset of the fused fixes (:class:`~stemmap.slam.gnss_track.
        GnssOffsetFilter`; ``std_m`` its per-axis 1-sigma). Needs ``gnss_offset_model``."""
        if self._gnss_track is None:
            raise ConfigError("OnlineMapper.pose_gnss needs gnss_offset_model.")
        x, y, th = self.pose
        t = float(self.times.a[self.times.n - 1]) if self.times.n else 0.0
        off, std = self._gnss_track.at(t)
        return (x + float(off[0]), y + float(off[1]), th, std)

    # ------------------------------------------------------------------ keyframes
    def _new_keyframe(self, f: int) -> None:
        """Frame ``f`` starts keyframe k+1: close keyframe k (factors, odometry, update)."""
        g = self._g
        from gtsam.symbol_shorthand import L as LK
        from gtsam.symbol_shorthand import X as XK

        c = self.cfg.isam2
        self.k += 1
        k = self.k
        self.kf_frame.append(f)
        if k == 0:
            s0 = g.Pose2(*self.v0).compose(self.T_vs)
            self.pf = g.PriorFactorPose2(
                XK(0), s0, g.noiseModel.Diagonal.Sigmas(np.array(c.prior_sigmas))
            )
            self._add(self.pf)
            self.new_v.insert(XK(0), s0)
            self.trk[:] = (s0.x(), s0.y(), s0.theta())
            self.fc[0] = f
            self.kf_est[0] = self.trk.copy()
            return
        # merged window measurements of keyframe k-1
        if self._win:
            cj, ckx, cky, cwxy, cwth = (np.concatenate([w[i] for w in self._win]) for i in range(5))
            vr, vb, mo = float(self.kparams[0]), float(self.kparams[1]), int(self.kparams[12])
            trees, brg_w, rr, sig, _ = merge_window(
                cj, ckx, cky, cwxy, cwth, int(cj.shape[0]), vr, vb, mo
            )
            xk = XK(k - 1)
            if trees.size:
                self.k_meas = k - 1
            for t_, j in enumerate(trees.tolist()):
                if not self.lm_in_graph.a[j]:
                    self.new_v.insert(LK(j), self.lm_xy.a[j].copy())
                    self.lm_in_graph.a[j] = True
                    if np.isfinite(self.lm_cov.a[j]).all():  # back after a re-anchor
                        self._add(g.PriorFactorPoint2(
                            LK(j), self.lm_xy.a[j].copy(),
                            g.noiseModel.Gaussian.Covariance(self.lm_cov.a[j]),
                        ))  # fmt: skip
                base = g.noiseModel.Diagonal.Sigmas(sig[t_])
                noise = (
                    base if self.kernel is None else g.noiseModel.Robust.Create(self.kernel, base)
                )
                self._add(
                    g.BearingRangeFactor2D(
                        xk, LK(j), g.Rot2(float(brg_w[t_])), float(rr[t_]), noise
                    )
                )
        self._win = []
        # odometry factor (k-1 -> k) in the sensor frame
        f0 = self.kf_frame[k - 1]
        t0 = float(self.times.a[f0])
        dv, cv = self._kd, self._kc  # chained frame increments (= pre-integration, 2nd order)
        self._kd, self._kc = np.zeros(3), np.zeros((3, 3))
        ds, cs = _sensor_between(dv[None], cv[None], self.offset)
        cs = cs[0] + np.diag([1e-3**2, 1e-3**2, 1e-4**2])
        self._add(g.BetweenFactorPose2(
            XK(k - 1), XK(k), g.Pose2(*(float(x) for x in ds[0])),
            g.noiseModel.Gaussian.Covariance(cs),
        ))  # fmt: skip
        # initial value: the tracked pose carried to this keyframe
        rel = between(self.sp_dr.a[int(self.fc[0])], self.sp_dr.a[f])
        init = compose(self.trk, rel)
        self.new_v.insert(XK(k), g.Pose2(*(float(x) for x in init)))
        self.kf_est[k] = init
        self._fuse_gnss(k - 1)
        # trim the control buffer to what the next keyframe / late GNSS fixes need
        keep_from = int(np.searchsorted(np.asarray(self._ct), t0, side="right")) - 1
        if keep_from > 0:
            del self._ct[:keep_from], self._cv[:keep_from], self._cs[:keep_from]
        if self._imu_t:
            ki = int(np.searchsorted(np.asarray(self._imu_t), t0, side="right")) - 1
            if ki > 0:
                del self._imu_t[:ki], self._imu_w[:ki]
        if k % c.update_every == 0:
            self._update(f)

    def _fuse_gnss(self, k_done: int) -> None:
        """Fixes with a time inside keyframe ``k_done`` (or earlier, still in the buffer)."""
        if not self._gnss_q:
            return
        g = self._g
        from gtsam.symbol_shorthand import X as XK
        from gtsam.symbol_shorthand import Z as ZK

        f0 = self.kf_frame[k_done]
        t_kf, t_next = float(self.times.a[f0]), float(self.times.a[self.kf_frame[k_done + 1]])
        rest = []
        for fix in self._gnss_q:
            t, x, y, s = fix
            if t >= t_next:
                rest.append(fix)
                continue
            if t < t_kf:
                log.warning("online: GNSS fix at %.3f s arrived too late (dropped)", t)
                continue
            dv, cv = self._dead_reckon(t_kf, t, self.veh.a[f0])
            frac_cov = cv + np.diag([1e-3**2, 1e-3**2, 1e-4**2])
            rel = compose(compose(np.array([-self.offset[0], -self.offset[1], 0.0]), dv),
                          np.array([self.lever[0], self.lever[1], 0.0]))  # fmt: skip
            plan = GnssPlan(
                np.array([k_done]), rel[None], frac_cov[None], np.array([[x, y]]), np.array([s])
            )
            if self._gnss_first:  # the fixes give the frame from now on
                weak = g.PriorFactorPose2(
                    XK(0), self.pf.prior(),
                    g.noiseModel.Diagonal.Sigmas(np.array(self.cfg.isam2.gnss_prior_sigmas)),
                )  # fmt: skip
                if self.isam.size() == 0 and self.k_anchor == 0:
                    self.new_f.replace(0, weak)
                    self.graph.replace(0, weak)
                elif self.k_anchor == 0:
                    self.remove_idx.append(0)
                    self._add(weak)
                self._gnss_first = False
            key_x = XK(k_done)
            x_est = (
                self.new_v.atPose2(key_x)
                if self.new_v.exists(key_x)
                else self.isam.calculateEstimatePose2(key_x)
            )
            facs, key, val = gnss_factors(plan, 0, key_x, x_est, self.gnss_kernel, ZK(self.n_gnss))
            for fac in facs:
                self._add(fac)
            self.new_v.insert(key, val)
            gt = self._gnss_track  # the fix against the antenna as estimated now
            if gt is not None and t >= gt.last_time:
                gt.update(t, np.array([x - val.x(), y - val.y()]))
            self.n_gnss += 1
        self._gnss_q = rest

    def _update(self, f: int) -> None:
        from gtsam.symbol_shorthand import L as LK
        from gtsam.symbol_shorthand import X as XK

        k = self.k
        self.isam.update(self.new_f, self.new_v, self.remove_idx)
        self.remove_idx = []
        self.new_f = self._g.NonlinearFactorGraph()
        self.new_v = self._g.Values()
        self.n_upd_window += 1
        p = self.isam.calculateEstimatePose2(XK(k))
        rel = between(self.sp_dr.a[int(self.fc[0])], self.sp_dr.a[f])
        init = compose(self.trk, rel)
        dth = math.remainder(p.theta() - init[2], 2 * math.pi)
        self.trk[:] = (p.x(), p.y(), init[2] + dth)
        self._cov.update(self.isam, XK(k), p)
        self.P[:, :] = self.P_floor
        self.fc[0] = f
        self.f_upd = f
        n = self.n_lm
        self.lm_inc.a[:n] = self.lm_last.a[:n]
        ing = np.flatnonzero(self.lm_in_graph.a[:n])
        if ing.size:
            dxy = self.lm_xy.a[ing] - self.trk[:2]
            near = ing[dxy[:, 0] ** 2 + dxy[:, 1] ** 2 < (self.cfg.isam2.max_range + 30.0) ** 2]
            for j in near.tolist():
                self.lm_xy.a[j] = self.isam.calculateEstimatePoint2(LK(j))
        idle = k - self.k_meas >= self.cfg.idle_keyframes
        if k - self.k_anchor >= self.cfg.window_keyframes or (
            idle and k - self.k_anchor >= self.cfg.idle_keyframes
        ):
            self._reanchor(k)

    def _reanchor(self, k: int) -> None:
        """Start a new smoother at keyframe ``k`` (module docs: bounded work and memory)."""
        g = self._g
        from gtsam.symbol_shorthand import L as LK
        from gtsam.symbol_shorthand import X as XK

        est = self.isam.calculateEstimate()
        n = self.n_lm
        ing = np.flatnonzero(self.lm_in_graph.a[:n])
        if ing.size:
            try:
                covs = _point_marginals(self.graph, est, [LK(int(j)) for j in ing])
            except (np.linalg.LinAlgError, ValueError, RuntimeError) as exc:
                log.warning("online: tree marginals unavailable at re-anchor (%s)", exc)
                covs = np.tile(np.eye(2) * 0.1**2, (ing.size, 1, 1))
            covs = covs + np.eye(2)[None] * self.cfg.tree_sigma_floor**2
            self.lm_cov.a[ing] = covs
            self.lm_xy.a[ing] = np.array([est.atPoint2(LK(int(j))) for j in ing])
        pk = est.atPose2(XK(k))
        # the pose's marginal with its sigmas capped (1 m, 0.05 rad; _online_covariance)
        cov_k = self._cov.reanchor(self.isam, XK(k), pk, self.cfg.isam2.reloc_prior_sigmas)
        self.lm_in_graph.a[:n] = False
        self._new_isam()
        self.pf = g.PriorFactorPose2(XK(k), pk, g.noiseModel.Gaussian.Covariance(cov_k))
        self._add(self.pf)
        self.new_v.insert(XK(k), pk)
        self.isam.update(self.new_f, self.new_v)
        self.new_f = g.NonlinearFactorGraph()
        self.new_v = g.Values()

    # ------------------------------------------------------------------ outputs
    def stem_map(self, *, with_covariance: bool = False) -> StemMap:
        """The current map: trees seen >= ``min_obs`` times, estimates from the smoother (or the
        value they left it with); covariance of the trees that left the smoother, and with
        ``with_covariance`` also of those in it (iSAM2 marginals: ~0.1-1 ms per tree)."""
        from gtsam.symbol_shorthand import L as LK

        n = self.n_lm
        trees = []
        est = self.isam.calculateEstimate() if self.isam.size() else None
        for j in np.flatnonzero(self.lm_nobs.a[:n] >= self.cfg.isam2.min_obs).tolist():
            xy = self.lm_xy.a[j]
            if est is not None and self.lm_in_graph.a[j] and est.exists(LK(j)):
                xy = est.atPoint2(LK(j))
            cov = self.lm_cov.a[j].copy()
            if with_covariance and est is not None and self.lm_in_graph.a[j] and est.exists(LK(j)):
                cov = np.asarray(self.isam.marginalCovariance(LK(j)), dtype=np.float64)
            nd = int(self.lm_dn.a[j])
            trees.append(Tree(
                id=j, x=float(xy[0]), y=float(xy[1]),
                diameter=float(self.lm_dsum.a[j] / nd) if nd else math.nan,
                cov=cov, n_obs=int(self.lm_nobs.a[j]),
                first_time=float(self.times.a[self.lm_first.a[j]]),
                last_time=float(self.times.a[self.lm_last.a[j]]),
            ))  # fmt: skip
        return StemMap(tuple(trees))

    @property
    def stats(self) -> dict[str, int]:
        return {
            "scans": self.times.n,
            "keyframes": self.k + 1,
            "trees": self.n_lm,
            "matched": int(
                self.counters[C_LOCAL] + self.counters[C_REACQ] + self.counters[C_SINGLE]
            ),
            "new": int(self.counters[C_NEW]),
            "gnss_fused": self.n_gnss,
        }
