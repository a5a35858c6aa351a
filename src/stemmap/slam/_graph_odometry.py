"""Odometry factors of the iSAM2 back-end: sensor-frame increments and self-calibration (ours).

Split out of :mod:`stemmap.slam.graph` (which re-exports the names): the vehicle-frame
pre-integrated increments carried to the sensor frame in GTSAM's tangent convention, and the
steering-offset / speed-scale calibration estimated from the graph's own poses (see
docs/algorithms/slam.md "Odometry self-calibration").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stemmap.slam.base import SlamProblem
from stemmap.slam.motion import between, compose, preintegrate_spans
from stemmap.types import FloatArray

__all__ = [
    "KeyframeOdometry",
    "_calibration_jacobians",
    "_calibration_lsq",
    "_sensor_between",
    "frame_covariances",
    "keyframe_odometry",
    "preintegrate_spans",
    "sensor_increments",
]


def _sensor_between(
    deltas: FloatArray, covs: FloatArray, offset: tuple[float, float]
) -> tuple[FloatArray, FloatArray]:
    """Vehicle-frame odometry increments -> sensor-frame increments and GTSAM tangent covariances.

    ``δ_s = T_vs⁻¹ δ T_vs``. Our covariance is additive on ``(x, y, θ)`` in the START frame; GTSAM
    perturbs on the right, in the END frame (``δ Exp(ξ)``): ``ξ_xy ≈ R(θ_δ)ᵀ e_xy``,
    ``ξ_θ = e_θ``; then ``ξ_s = Ad(T_vs⁻¹) ξ``.
    """
    a, b = offset
    n = deltas.shape[0]
    c, s = np.cos(deltas[:, 2]), np.sin(deltas[:, 2])
    ds = sensor_increments(deltas, offset)
    M = np.zeros((n, 3, 3))
    M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1] = c, s, -s, c
    M[:, 2, 2] = 1.0
    # Ad(T^-1) for T = (a, b, 0): T^-1 = (-a, -b, 0); Pose2 adjoint [[R, [y, -x]^T], [0, 1]]
    Ad = np.array([[1.0, 0.0, -b], [0.0, 1.0, a], [0.0, 0.0, 1.0]])
    G = Ad[None] @ M
    cov = G @ covs @ np.swapaxes(G, 1, 2)
    return ds, cov


def sensor_increments(deltas: FloatArray, offset: tuple[float, float]) -> FloatArray:
    """Vehicle-frame increments -> sensor-frame increments ``δ_s = T_vs⁻¹ δ T_vs`` (the
    increments of :func:`_sensor_between`, without covariances)."""
    a, b = offset
    c, s = np.cos(deltas[:, 2]), np.sin(deltas[:, 2])
    # δ_s translation: T_vs^-1 δ T_vs with T_vs = (a, b, 0)
    tx = deltas[:, 0] + c * a - s * b - a
    ty = deltas[:, 1] + s * a + c * b - b
    return np.column_stack((tx, ty, deltas[:, 2]))


def frame_covariances(
    kf_cov: FloatArray,
    kf_of: np.ndarray,
    kf_frames: np.ndarray,
    d_f: FloatArray,
    cov_f: FloatArray,
    offset: tuple[float, float],
    veh_theta: FloatArray,
    *,
    block: int = 8192,
) -> FloatArray:
    """(N, 3, 3) covariance of every frame's vehicle pose (x, y, θ in the map frame) from the
    keyframes' sensor-pose marginals ``kf_cov`` (nk, 3, 3; GTSAM tangent; NaN where none).

    A frame's sensor pose is its keyframe's composed with the dead-reckoned sensor increments
    ``d_f`` (frame f-1 -> f, covariances ``cov_f``, :func:`_sensor_between`) since it, as
    :class:`~stemmap.slam.graph.Isam2Slam` builds the trajectory: covariance
    ``C ← Ad(d⁻¹) C Ad(d⁻¹)ᵀ + cov`` per step (:func:`compose_increments`, first order; the
    increments are independent of the keyframe's estimate). The vehicle pose is the sensor
    pose composed with the fixed mounting ``T_sv``: ``Ad(T_vs)`` carries the tangent; last,
    the right-perturbation tangent goes to map-frame (x, y, θ) with the heading's rotation.

    Keyframes without a marginal (left out of the graph in localisation mode, issue 14): their
    frames get ``(1 - w) C_fwd + w C_bwd`` -- ``C_fwd`` propagated forward from the last graph
    keyframe before them, ``C_bwd`` backward from the next one (``C ← Ad(d) (C + cov) Ad(d)ᵀ``,
    the same increments inverted), ``w`` the share of the gap's odometry variance (trace of the
    position block) already driven. The two neighbours' errors are nearly the same (the map
    holds both), so this weighs them as fully correlated: at the middle of a gap the
    odometry part is twice a Brownian bridge's ``w (1 - w) Q``, conservative (the localisation
    on the map, which the bridge ignores, also holds these poses; docs/algorithms/slam.md).
    Frames after the last graph keyframe get ``C_fwd`` alone.

    Computed in blocks of about ``block`` frames cut at graph keyframes (a frame's value
    depends on its two neighbouring graph keyframes only; the odometry variance driven is
    summed over the whole drive first, so every value is the same bytes as in one block):
    the working memory is ~0.4 kB per frame of a block (a block is longer only where the
    run between two graph keyframes is), besides the (N, 3, 3) result.
    """
    nf = kf_of.size
    kf_frames = np.asarray(kf_frames, dtype=np.int64)
    has = np.all(np.isfinite(kf_cov), axis=(1, 2))
    anchors = kf_frames[has]  # frames of the graph keyframes
    # odometry variance driven up to each frame (the gaps' weights), over the whole drive
    q = np.concatenate(([0.0], np.cumsum(cov_f[:, 0, 0] + cov_f[:, 1, 1])))
    out = np.empty((nf, 3, 3))
    lo = 0
    while lo < nf:
        i = int(np.searchsorted(anchors, lo + max(int(block), 1), side="left"))
        hi = int(anchors[i]) if i < anchors.size else nf  # a graph keyframe (or the end)
        e = min(hi + 1, nf)  # (with the next graph keyframe: the gaps' backward pass)
        k0, k1 = int(kf_of[lo]), int(kf_of[e - 1]) + 1
        out[lo:hi] = _frame_covariances_block(
            kf_cov[k0:k1], kf_of[lo:e] - k0, kf_frames[k0:k1] - lo, d_f[lo:e], cov_f[lo:e],
            q[lo:e], offset, veh_theta[lo:e],
        )[: hi - lo]  # fmt: skip
        lo = hi
    return out


def _frame_covariances_block(
    kf_cov: FloatArray,
    kf_of: np.ndarray,
    kf_frames: np.ndarray,
    d_f: FloatArray,
    cov_f: FloatArray,
    q: FloatArray,
    offset: tuple[float, float],
    veh_theta: FloatArray,
) -> FloatArray:
    """:func:`frame_covariances` of frames that start at a graph keyframe (or at frame 0);
    ``q`` (n,): the odometry variance driven up to each frame, summed from the drive's start."""
    from stemmap.slam._graph_revisits import _adjoint_inv

    nf = kf_of.size
    fr = np.arange(nf)
    has = np.all(np.isfinite(kf_cov), axis=(1, 2))
    anchors = np.asarray(kf_frames, dtype=np.int64)[has]  # frames of the graph keyframes
    C = np.full((nf, 3, 3), np.nan)
    if anchors.size:
        C[anchors] = kf_cov[has]
        i_prev = np.searchsorted(anchors, fr, side="right") - 1
        prev = np.where(i_prev >= 0, anchors[np.clip(i_prev, 0, None)], -1)
        step = np.where(prev >= 0, fr - prev, -1)  # frames since the last graph keyframe
        for j in range(1, int(step.max(initial=0)) + 1):
            f = np.flatnonzero(step == j)
            A = _adjoint_inv(d_f[f - 1])
            C[f] = A @ C[f - 1] @ np.swapaxes(A, 1, 2) + cov_f[f - 1]
        i_next = np.searchsorted(anchors, fr, side="left")
        gap = ~has[kf_of] & (prev >= 0) & (i_next < anchors.size)
        if gap.any():
            nxt = np.where(i_next < anchors.size, anchors[np.clip(i_next, 0, anchors.size - 1)], -1)
            back = np.where(gap, nxt - fr, -1)  # frames to the next graph keyframe
            Cb = np.full((nf, 3, 3), np.nan)
            Cb[anchors] = kf_cov[has]
            d_inv = between(d_f, np.zeros(3))  # Ad(d) = Ad((d⁻¹)⁻¹)
            for j in range(1, int(back.max(initial=0)) + 1):
                f = np.flatnonzero(back == j)
                A = _adjoint_inv(d_inv[f])
                Cb[f] = A @ (Cb[f + 1] + cov_f[f]) @ np.swapaxes(A, 1, 2)
            g = np.flatnonzero(gap)
            span = q[nxt[g]] - q[prev[g]]
            w = np.where(
                span > 0,
                (q[g] - q[prev[g]]) / np.where(span > 0, span, 1.0),
                (g - prev[g]) / (nxt[g] - prev[g]),
            )[:, None, None]
            C[g] = (1.0 - w) * C[g] + w * Cb[g]
    a, b = offset
    ad_vs = np.array([[1.0, 0.0, b], [0.0, 1.0, -a], [0.0, 0.0, 1.0]])  # Ad(T_vs), T_vs=(a,b,0)
    c, s = np.cos(veh_theta), np.sin(veh_theta)
    B = np.zeros((nf, 3, 3))
    B[:, 0, 0], B[:, 0, 1], B[:, 1, 0], B[:, 1, 1], B[:, 2, 2] = c, -s, s, c, 1.0
    B = B @ ad_vs
    out = B @ C @ np.swapaxes(B, 1, 2)
    return np.asarray(0.5 * (out + np.swapaxes(out, 1, 2)), dtype=np.float64)


def _calibration_jacobians(
    problem: SlamProblem, times: FloatArray, d0: FloatArray, eps: float = 1e-4
) -> FloatArray:
    """(K, 3, 2): derivative of each sensor-frame increment w.r.t. the calibration ``c``.

    ``c = (o, s)``: every steering sample (yaw-rate sample for unicycle controls) becomes
    ``steer + o`` and every speed sample ``speed (1 + s)``. Forward differences of the same
    pre-integration the odometry factors use, so the Jacobian is generic in the motion model
    (the increments are smooth in both parameters over one keyframe); GTSAM's right-tangent
    convention, ``δ(c) ≈ δ0 Exp(J c)``.
    """
    from stemmap.slam.base import Controls

    ctl = problem.controls
    out = np.empty((d0.shape[0], 3, 2))
    for i, (d_steer, d_scale) in enumerate(((eps, 0.0), (0.0, eps))):
        c2 = Controls(
            ctl.times, np.asarray(ctl.speed) * (1.0 + d_scale), np.asarray(ctl.steer) + d_steer,
            ctl.kind,
        )  # fmt: skip
        # in spans: one call over a long drive holds the whole drive's working arrays (the 10x
        # Victoria Park soak: +66 MB); the increments are the same
        pre = preintegrate_spans(
            problem.motion, c2, times, problem.initial_pose, with_covariance=False
        )
        d1 = sensor_increments(pre.deltas, problem.sensor_offset)
        out[:, :, i] = between(d0, d1) / eps
    return out


def _calibration_lsq(
    res: FloatArray,
    J: FloatArray,
    info: FloatArray,
    c_lin: FloatArray,
    seg: np.ndarray,
    n_seg: int,
    dur: FloatArray,
    prior_sigmas: tuple[float, float],
    walk_sigmas: tuple[float, float],
) -> FloatArray:
    """Calibration of each segment given the poses: one block-coordinate step (ours).

    The odometry factor of keyframe ``k`` used the increment ``δ(c_lin_k) = δ0 Exp(J_k c_lin_k)``
    and has the residual ``res_k = Log(δ(c_lin_k)⁻¹ X_k⁻¹ X_k+1)`` at the current poses; to first
    order ``res_k ≈ J_k (c_seg(k) - c_lin_k)``. Minimises
    ``Σ_k |res_k - J_k (c_seg(k) - c_lin_k)|²_info_k + |c_0 / prior|² +
    Σ_s |(c_s+1 - c_s) / (walk sqrt(dur_s))|²`` (prior mean 0: the motion model's own
    calibration; random walk between segments) -- the conditional MAP of the calibration given
    the poses, a small dense (2 n_seg)² system.

    res (K, 3), J (K, 3, 2), info (K, 3, 3), c_lin (K, 2), seg (K,) segment of each factor,
    dur (n_seg - 1,) s between segment starts. Returns (n_seg, 2).
    """
    n = 2 * n_seg
    JtW = np.swapaxes(J, 1, 2) @ info  # (K, 2, 3)
    A_k = JtW @ J  # (K, 2, 2)
    b_k = (JtW @ (res + (J @ c_lin[:, :, None])[:, :, 0])[:, :, None])[:, :, 0]
    A = np.zeros((n, n))
    bb = np.zeros(n)
    for i in range(2):
        bb[i::2] = np.bincount(seg, weights=b_k[:, i], minlength=n_seg)
        for j in range(2):
            A[i::2, j::2] += np.diag(np.bincount(seg, weights=A_k[:, i, j], minlength=n_seg))
    A[0:2, 0:2] += np.diag(1.0 / np.asarray(prior_sigmas) ** 2)
    w2 = np.asarray(walk_sigmas) ** 2
    for s_ in range(n_seg - 1):
        W = np.diag(1.0 / (w2 * max(float(dur[s_]), 1e-3)))
        i0, i1 = 2 * s_, 2 * s_ + 2
        A[i0 : i0 + 2, i0 : i0 + 2] += W
        A[i1 : i1 + 2, i1 : i1 + 2] += W
        A[i0 : i0 + 2, i1 : i1 + 2] -= W
        A[i1 : i1 + 2, i0 : i0 + 2] -= W
    return np.asarray(np.linalg.solve(A, bb), dtype=np.float64).reshape(n_seg, 2)


@dataclass
class KeyframeOdometry:
    """The odometry of :class:`~stemmap.slam.graph.Isam2Slam` between consecutive keyframes,
    with its self-calibration (docs/algorithms/slam.md "Odometry self-calibration").

    ``d_k`` (K, 3) / ``cov_k`` (K, 3, 3): the sensor-frame increment of each step (keyframe
    ``k`` -> ``k + 1``) and its GTSAM tangent covariance. With ``calibrate``: ``J_k`` (K, 3, 2),
    :func:`_calibration_jacobians`; ``info_k`` the inverse covariances; ``c_used[k]`` the
    calibration inside the factor of step ``k`` (set as the run goes); ``seg_k`` the segment of
    each step, ``n_seg`` segments, ``dur_seg`` s between segment starts (:func:`_calibration_lsq`).
    """

    d_k: FloatArray
    cov_k: FloatArray
    calibrate: bool
    c_used: FloatArray
    J_k: Any = None
    info_k: Any = None
    seg_k: Any = None
    n_seg: int = 0
    dur_seg: Any = None
    noise: dict[tuple[int, int], Any] = field(default_factory=dict)  # (GTSAM noise models)

    def measured(self, idx: Any) -> FloatArray:
        """Increments of the steps ``idx`` (keyframe k -> k + 1) with their calibration."""
        if not self.calibrate:
            return self.d_k[idx]
        corr = (self.J_k[idx] @ self.c_used[idx][:, :, None])[:, :, 0]
        return compose(self.d_k[idx], corr)  # δ0 Exp(J c) to first order (J c is small)

    def step(self, k: int, c: FloatArray) -> FloatArray:
        """The increment of step ``k`` with calibration ``c``: :meth:`measured` of one step in
        scalars (called once per keyframe: 1,450 calls on Victoria Park)."""
        d0 = self.d_k[k]
        if not self.calibrate:
            return d0
        xi = self.J_k[k] @ c
        cz, sz = math.cos(d0[2]), math.sin(d0[2])
        return np.array(
            (d0[0] + cz * xi[0] - sz * xi[1], d0[1] + sz * xi[0] + cz * xi[1], d0[2] + xi[2])
        )

    def residuals(self, kf_xyt: FloatArray, idx: np.ndarray, k0: int = 0) -> FloatArray:
        """Residuals of the one-step odometry factors ``idx`` at keyframe poses ``kf_xyt``
        (row ``i - k0`` holds keyframe ``i``)."""
        rel = between(kf_xyt[idx - k0], kf_xyt[idx + 1 - k0])
        return between(self.measured(idx), rel)  # ≈ Log(δ⁻¹ X_k⁻¹ X_k+1), small

    def online(
        self,
        k: int,
        pose_k: Any,
        in_graph: np.ndarray,
        estimate: Callable[[int], Any],
        cfg: Any,
        c: FloatArray,
    ) -> FloatArray:
        """The online calibration at keyframe ``k`` from the last ``cfg.calib_window``
        keyframes (one constant over the window, :func:`_calibration_lsq`), or ``c`` when no
        one-step odometry factor of the graph lies in the window.

        ``pose_k``: keyframe ``k``'s gtsam.Pose2 estimate; ``in_graph`` (K,): keyframes with a
        pose in the graph; ``estimate(i)``: their current gtsam.Pose2 (each read-out of iSAM2
        costs ~50 us, so this runs once per calibration segment: the calibration varies slowly).
        """
        k0 = max(0, k - cfg.calib_window)
        xw = np.zeros((k + 1 - k0, 3))  # keyframes k0..k (the window)
        for i in range(k0, k):
            if in_graph[i]:
                q = estimate(i)
                xw[i - k0] = (q.x(), q.y(), q.theta())
        xw[k - k0] = (pose_k.x(), pose_k.y(), pose_k.theta())
        has = np.append(in_graph[k0:k], True)  # k: its estimate pose_k
        idx = k0 + np.flatnonzero(has[:-1] & has[1:])
        if not idx.size:
            return c
        return _calibration_lsq(
            self.residuals(xw, idx, k0), self.J_k[idx], self.info_k[idx], self.c_used[idx],
            np.zeros(idx.size, dtype=np.int64), 1, np.zeros(0),
            cfg.calib_prior_sigmas, cfg.calib_walk_sigmas,
        )[0]  # fmt: skip

    def factor(
        self, gtsam: Any, xkey: Callable[[int], int], ka: int, kb: int, d: Any = None
    ) -> Any:
        """BetweenFactorPose2 of graph keyframes ``ka < kb``: the steps between composed
        (:func:`~stemmap.slam._graph_revisits.compose_increments`; one step: its own increment
        ``d`` and covariance)."""
        from stemmap.slam._graph_revisits import compose_increments

        if kb == ka + 1:
            d = self.measured(slice(ka, kb))[0] if d is None else d
            cov = self.cov_k[ka]
        else:
            d, cov = compose_increments(self.measured(slice(ka, kb)), self.cov_k[ka:kb])
        if (ka, kb) not in self.noise:
            self.noise[(ka, kb)] = gtsam.noiseModel.Gaussian.Covariance(cov)
        return gtsam.BetweenFactorPose2(
            xkey(ka), xkey(kb), gtsam.Pose2(float(d[0]), float(d[1]), float(d[2])),
            self.noise[(ka, kb)],
        )  # fmt: skip


def keyframe_odometry(
    problem: SlamProblem, cfg: Any, kf_times: FloatArray
) -> tuple[KeyframeOdometry, FloatArray]:
    """The :class:`KeyframeOdometry` of the keyframes at ``kf_times`` (settings of an
    :class:`~stemmap.slam._graph_config.Isam2Config`), and the dead-reckoned vehicle pose of
    each keyframe (for the GNSS plan)."""
    pre_k = preintegrate_spans(problem.motion, problem.controls, kf_times, problem.initial_pose)
    d_k, cov_k = _sensor_between(pre_k.deltas, pre_k.covs, problem.sensor_offset)
    # a standing vehicle still gets a (tiny) well-posed odometry factor
    cov_k = cov_k + np.diag([1e-3**2, 1e-3**2, 1e-4**2])[None]
    nk = kf_times.size
    odo = KeyframeOdometry(d_k, cov_k, cfg.calibrate and nk > 2, np.zeros((max(nk - 1, 0), 2)))
    if odo.calibrate:
        odo.J_k = _calibration_jacobians(problem, kf_times, d_k)
        odo.info_k = np.asarray(np.linalg.inv(cov_k), dtype=np.float64)
        odo.seg_k = np.arange(nk - 1) // cfg.calib_every
        odo.n_seg = int(odo.seg_k[-1]) + 1
        odo.dur_seg = np.diff(kf_times[:: cfg.calib_every])[: odo.n_seg - 1]
    return odo, pre_k.poses


@dataclass
class FrameOdometry:
    """The dead reckoning of every frame that :class:`~stemmap.slam.graph.Isam2Slam` uses
    between keyframes (the tracker's prediction and drift, the trajectory and its covariances).

    ``d_f`` / ``cov_f`` (F - 1): sensor-frame increment frame ``f`` -> ``f + 1`` and its GTSAM
    tangent covariance (:func:`_sensor_between`); ``rel_s`` (F, 3): sensor motion from each
    frame's keyframe to the frame; ``cum_dist`` / ``cum_xy`` / ``cum_th`` (F,): path length,
    position variance (half the trace) and heading variance of the odometry summed from the
    start; ``sp_dr`` (F, 3): dead-reckoned sensor poses (continuous heading).
    """

    d_f: FloatArray
    cov_f: FloatArray
    rel_s: FloatArray
    cum_dist: FloatArray
    cum_xy: FloatArray
    cum_th: FloatArray
    sp_dr: FloatArray


def frame_odometry(problem: SlamProblem, kf_of: np.ndarray, kf_frames: np.ndarray) -> FrameOdometry:
    """:class:`FrameOdometry` of ``problem``'s frames; ``kf_of`` the keyframe of each frame,
    ``kf_frames`` the frame of each keyframe."""
    from stemmap.slam._graph_result import sensor_dead_reckoning

    a, b = problem.sensor_offset
    pre = preintegrate_spans(
        problem.motion, problem.controls, problem.frames.times, problem.initial_pose
    )  # (bounded working memory on long drives)
    d_f, cov_f = _sensor_between(pre.deltas, pre.covs, (a, b))
    # of the per-frame odometry only the poses and distances are used from here on: the
    # vehicle increments and their (F, 3, 3) covariances (96 bytes per scan) are dropped
    poses, dist = pre.poses, pre.distance
    del pre
    # sensor motion from each frame's keyframe to the frame (dead reckoning, short)
    rel_s = sensor_increments(between(poses[kf_frames[kf_of]], poses), (a, b))
    return FrameOdometry(
        d_f,
        cov_f,
        rel_s,
        cum_dist=np.concatenate(([0.0], np.cumsum(dist))),
        cum_xy=np.concatenate(([0.0], np.cumsum(0.5 * (cov_f[:, 0, 0] + cov_f[:, 1, 1])))),
        cum_th=np.concatenate(([0.0], np.cumsum(cov_f[:, 2, 2]))),
        sp_dr=sensor_dead_reckoning(poses, a, b),
    )
