"""Loosely coupled EKF fusion of odometry sources (visual-lidar paper §2.4; Munjer 2025 §3.5).

Both papers run each odometry (visual SLAM and LiDAR SLAM; ICP scan matching, IMU and wheels)
on its own and combine their *outputs* in an Extended Kalman Filter -- "loosely coupled". Neither
paper gives the filter's equations; we use the standard planar constant-velocity EKF of ROS
``robot_localization`` style, fusing each source's body-frame velocities (decision recorded in
docs/algorithms/slam-frontends.md):

* state ``x = (x, y, θ, v, ω)``: pose in the odometry frame, forward speed, yaw rate;
* prediction over ``dt`` (unicycle, mid-point heading)::

      x += v dt cos(θ + ω dt / 2),  y += v dt sin(θ + ω dt / 2),  θ += ω dt

  with random-walk process noise on ``(v, ω)`` of spectral density ``(σ_a², σ_α²)``;
* update with a source's ``(v, ω)`` measurement (any number of sources, :func:`fuse_sources`;
  :func:`fuse_odometry` is the two-source form), ``H = [0 0 0 1 0; 0 0 0 0 1]``; a source may
  give only one of the two (NaN for the other).

A source that outputs poses (a SLAM odometry) is turned into velocities by
:func:`velocities_from_poses` (differencing consecutive poses in the body frame), which is what
"loosely coupled" means here.

Pose-output odometries can also be fused by their increments alone, without this filter:
:mod:`stemmap.odometry.increments` (each source's relative motion with its own error model).

Ours, on top of the papers: an optional chi-square innovation gate (``gate_prob``) rejects
measurements inconsistent with the other source -- wheel slip shows up as an encoder speed far
from the visual speed and is dropped instead of averaged in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.stats import chi2

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, Trajectory, wrap_angle

__all__ = [
    "FusedOdometry",
    "OdometrySource",
    "PoseSource",
    "dead_reckon_source",
    "fuse_odometry",
    "fuse_sources",
    "velocities_from_poses",
]


@dataclass(frozen=True, eq=False)
class OdometrySource:
    """Body-frame velocities reported by one odometry source.

    Parameters
    ----------
    times : ndarray (N,), s, strictly increasing
    speed : ndarray (N,), m/s (NaN = this sample carries no speed)
    yaw_rate : ndarray (N,), rad/s (NaN = no yaw rate)
    sigma_speed : float or ndarray (N,), m/s
        1-sigma noise of each speed sample.
    sigma_yaw_rate : float or ndarray (N,), rad/s
    name : str
    interval_start : ndarray (N,), s, optional
        For a velocity *measured over an interval* (a pose-output odometry differenced by
        :func:`velocities_from_poses`): sample ``k`` is the mean velocity over
        ``[interval_start[k], times[k]]``, known at ``times[k]``. :func:`fuse_sources` and
        :func:`dead_reckon_source` apply it to that interval. None = instantaneous samples
        (a gyro, wheel encoders), each held from its time until the next one.
    """

    times: FloatArray
    speed: FloatArray
    yaw_rate: FloatArray
    sigma_speed: float | FloatArray
    sigma_yaw_rate: float | FloatArray
    name: str = ""
    interval_start: FloatArray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64).reshape(-1)
        n = t.shape[0]
        label = self.name or "odometry source"
        for fname in ("speed", "yaw_rate"):
            arr = np.asarray(getattr(self, fname), dtype=np.float64).reshape(-1)
            if arr.shape[0] != n:
                raise InputError(f"{label}: {fname} has {arr.shape[0]} samples, times has {n}.")
            object.__setattr__(self, fname, arr)
        for fname in ("sigma_speed", "sigma_yaw_rate"):
            arr = np.broadcast_to(np.asarray(getattr(self, fname), dtype=np.float64), (n,))
            if np.any(~(arr > 0)):
                raise ConfigError(f"{label}: {fname} must be > 0, got min {arr.min(initial=0)}.")
            object.__setattr__(self, fname, np.array(arr))
        if not np.all(np.isfinite(t)):
            raise InputError(f"{label}: times must be finite.")
        if n > 1 and np.any(np.diff(t) <= 0):
            k = int(np.argmin(np.diff(t)))
            raise InputError(
                f"{label}: times must increase strictly; time goes from {t[k]} to {t[k + 1]} at "
                f"sample {k + 1}."
            )
        object.__setattr__(self, "times", t)
        if self.interval_start is not None:
            t0 = np.asarray(self.interval_start, dtype=np.float64).reshape(-1)
            if t0.shape[0] != n or not np.all(t0 < t):
                raise InputError(
                    f"{label}: interval_start needs one start per sample, each before its "
                    f"sample time ({t0.shape[0]} starts for {n} samples)."
                )
            if n > 1 and np.any(np.diff(t0) <= 0):
                raise InputError(f"{label}: interval_start must increase strictly.")
            object.__setattr__(self, "interval_start", t0)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def take(self, keep: NDArray[np.bool_]) -> OdometrySource:
        """The samples where ``keep`` is True (per-sample sigmas and interval starts kept)."""
        t0 = None if self.interval_start is None else self.interval_start[keep]
        return OdometrySource(
            self.times[keep],
            self.speed[keep],
            self.yaw_rate[keep],
            np.asarray(self.sigma_speed)[keep],
            np.asarray(self.sigma_yaw_rate)[keep],
            name=self.name,
            interval_start=t0,
        )


@dataclass(frozen=True, eq=False)
class PoseSource:
    """Planar poses in the odometry frame with covariances, e.g. a scan-to-map lidar
    odometry: an absolute measurement of ``(x, y, θ)`` for :func:`fuse_sources`.

    Parameters
    ----------
    times : ndarray (N,), s, strictly increasing
    poses : ndarray (N, 3), m, m, rad
    covs : ndarray (N, 3, 3); a row with a NaN is skipped (no measurement)
    name : str
    drift : ndarray (N, 3, 3), optional
        For an odometry whose frame drifts (a scan-to-map odometry: its pose error is jitter
        ``covs`` about a slowly drifting path, not a white error about the truth): the
        covariance of the drift the source's frame takes on between pose ``k - 1`` and
        ``k``, as a body-frame increment error ``(dx, dy, dθ)`` at pose ``k``.
        :func:`fuse_sources` then estimates the source's frame offset (3 states, a random walk
        with this noise) and the velocity sources can correct the source's drift; None = the
        poses are absolute (the offset is fixed at the identity).
    """

    times: FloatArray
    poses: FloatArray
    covs: FloatArray
    name: str = ""
    drift: FloatArray | None = None

    def __post_init__(self) -> None:
        label = self.name or "pose source"
        t = np.asarray(self.times, dtype=np.float64).reshape(-1)
        p = np.asarray(self.poses, dtype=np.float64).reshape(-1, 3)
        c = np.asarray(self.covs, dtype=np.float64).reshape(-1, 3, 3)
        if not (p.shape[0] == c.shape[0] == t.shape[0]):
            raise InputError(
                f"{label}: {t.shape[0]} times, {p.shape[0]} poses and {c.shape[0]} covariances."
            )
        if not np.all(np.isfinite(t)) or (t.shape[0] > 1 and np.any(np.diff(t) <= 0)):
            raise InputError(f"{label}: times must be finite and strictly increasing.")
        for name, arr in (("times", t), ("poses", p), ("covs", c)):
            object.__setattr__(self, name, arr)
        if self.drift is not None:
            d = np.broadcast_to(np.asarray(self.drift, dtype=np.float64), c.shape)
            if not np.all(np.isfinite(d)) or np.any(np.linalg.eigvalsh(d) < -1e-15):
                raise ConfigError(f"{label}: drift must be finite positive semi-definite.")
            object.__setattr__(self, "drift", np.array(d))

    def __len__(self) -> int:
        return int(self.times.shape[0])


def velocities_from_poses(
    trajectory: Trajectory,
    *,
    sigma_speed: float | FloatArray,
    sigma_yaw_rate: float | FloatArray,
    name: str = "",
) -> OdometrySource:
    """Turn a pose-output odometry (e.g. a LiDAR or visual SLAM) into a velocity source.

    Velocity of interval ``[t_k, t_{k+1}]`` is ``between(p_k, p_{k+1}) / dt``, time-stamped at
    the interval's end (the moment it becomes known) with ``interval_start = t_k``, so the
    filter applies it to the interval it describes; the forward component is the speed (the
    lateral one is ignored: non-holonomic vehicle). The speed is the arc length of a constant
    (v, ω) motion between the two poses: the chord projected on the mid-interval heading,
    divided by ``sinc(Δθ / 2)``. ``sigma_speed`` / ``sigma_yaw_rate`` may be one value or one
    per interval (N - 1), e.g. a scan matcher's increment covariance divided by ``dt``.
    """
    t = trajectory.times
    p = trajectory.poses
    if t.shape[0] < 2:
        raise InputError(f"{name or 'trajectory'}: need at least 2 poses to difference.")
    dt = np.diff(t)
    dth = wrap_angle(np.diff(p[:, 2]))
    mid = p[:-1, 2] + 0.5 * dth
    dx = np.diff(p[:, 0])
    dy = np.diff(p[:, 1])
    fwd = (np.cos(mid) * dx + np.sin(mid) * dy) / np.sinc(dth / (2.0 * np.pi))
    return OdometrySource(
        t[1:], fwd / dt, dth / dt, sigma_speed, sigma_yaw_rate, name=name, interval_start=t[:-1]
    )


def dead_reckon_source(
    source: OdometrySource, initial_pose: ArrayLike = (0.0, 0.0, 0.0)
) -> Trajectory:
    """Integrate one source alone (zero-order hold of each sample until the next one).

    The baseline the fusion is compared against. NaN components are held at their last value.
    A source with ``interval_start`` is integrated interval by interval (sample ``k`` over
    ``[times[k-1], times[k]]``, the first from its own start; a gap between intervals takes
    the next sample) and the trajectory starts at ``interval_start[0]``.
    """
    v = _ffill(source.speed)
    w = _ffill(source.yaw_rate)
    if source.interval_start is not None:
        t = np.concatenate((source.interval_start[:1], source.times))
    else:
        t = source.times
        v, w = v[:-1], w[:-1]
    p0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    dt = np.diff(t)
    dth = w * dt
    th = p0[2] + np.concatenate(([0.0], np.cumsum(dth)))
    mid = th[:-1] + 0.5 * dth
    x = p0[0] + np.concatenate(([0.0], np.cumsum(v * dt * np.cos(mid))))
    y = p0[1] + np.concatenate(([0.0], np.cumsum(v * dt * np.sin(mid))))
    return Trajectory(t, np.column_stack((x, y, wrap_angle(th))), frame="odom")


def _ffill(a: FloatArray) -> FloatArray:
    ok = np.isfinite(a)
    if not np.any(ok):
        return np.zeros_like(a)
    idx = np.where(ok, np.arange(a.shape[0]), 0)
    np.maximum.accumulate(idx, out=idx)
    out = a[idx]
    first = int(np.argmax(ok))
    out[:first] = a[first]
    return out


@dataclass(frozen=True, eq=False)
class FusedOdometry:
    """Output of :func:`fuse_sources` / :func:`fuse_odometry`.

    Attributes
    ----------
    trajectory : Trajectory
        Fused pose after every processed measurement time.
    covariances : ndarray (N, 3, 3)
        Pose covariance at those times.
    velocities : ndarray (N, 2)
        Fused (v, ω) after the measurements of each time: for interval sources, the velocity
        of the interval that starts there (the zero-order hold to the next time).
    n_rejected : ndarray (S,), int
        Measurements of each source rejected by the innovation gate (velocity sources first,
        then pose sources).
    calibration : ndarray (C,)
        Final estimates of the augmented calibration states, named by ``calibration_names``
        (``"<source>.yaw_rate_bias"`` in rad/s, ``"<source>.speed_scale"`` as the relative
        error ``k``: the source reads ``(1 + k) v``; then ``"<pose source>.frame_offset_x"``,
        ``_y`` (m), ``_theta`` (rad) of each drifting pose source). :func:`fuse_odometry`
        always returns ``[bias of A, scale error of the non-reference source]`` (zeros unless
        calibrating).
    calibration_names : tuple of str
    source_names : tuple of str
        Label of each entry of ``n_rejected`` (a source's ``name``, else ``source<i>`` /
        ``poses<j>``), so rejection counts are never paired with the wrong source.
    """

    trajectory: Trajectory
    covariances: FloatArray
    velocities: FloatArray
    n_rejected: NDArray[np.int64]
    calibration: FloatArray
    calibration_names: tuple[str, ...] = ()
    source_names: tuple[str, ...] = ()


_SIGMAS = ("sigma_speed", "sigma_yaw_rate")


def _ekf_update(
    x: FloatArray, P: FloatArray, H: FloatArray, y: FloatArray, R: FloatArray, gate: float
) -> bool:
    """In-place EKF update with innovation ``y``; False (and no change) when the squared
    Mahalanobis innovation exceeds ``gate``."""
    S = H @ P @ H.T + R
    Sinv = np.linalg.inv(S)
    if float(y @ Sinv @ y) > gate:
        return False
    K = P @ H.T @ Sinv
    x += K @ y
    P -= K @ S @ K.T
    P[:] = 0.5 * (P + P.T)
    return True


def _offset_pose(o: FloatArray, p: FloatArray) -> FloatArray:
    """``o ⊕ p``: a pose of the output frame seen in a pose source's drifted frame."""
    c, s = math.cos(o[2]), math.sin(o[2])
    return np.array([o[0] + c * p[0] - s * p[1], o[1] + s * p[0] + c * p[1], o[2] + p[2]])


def _drift_step(
    x: FloatArray, P: FloatArray, oi: int, z: FloatArray, drift: FloatArray, dim: int
) -> FloatArray:
    """Random-walk step of a pose source's frame offset ``o`` (state ``x[oi:oi+3]``) and the
    Jacobian of its measurement ``z = o ⊕ p``.

    The source's drift since its previous pose is a body-frame increment error ``δ`` at its
    pose ``z``: ``(o + Δo) ⊕ p = z ⊕ δ``, to first order ``Δo = J_o⁻¹ diag(R(z_θ), 1) δ`` with
    ``J_o = ∂(o ⊕ p)/∂o``, so ``P_oo += G drift Gᵀ``. Returns ``H`` (3, dim) at the state.
    """
    o = x[oi : oi + 3]
    p = x[:3]
    c, s = math.cos(o[2]), math.sin(o[2])
    h = _offset_pose(o, p)
    if np.any(drift):
        cz, sz = math.cos(z[2]), math.sin(z[2])
        G = np.array(
            [
                [cz, -sz, z[1] - o[1]],
                [sz, cz, -(z[0] - o[0])],
                [0.0, 0.0, 1.0],
            ]
        )
        P[oi : oi + 3, oi : oi + 3] += G @ drift @ G.T
    H = np.zeros((3, dim))
    H[:, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    H[:, oi : oi + 3] = [[1.0, 0.0, -(h[1] - o[1])], [0.0, 1.0, h[0] - o[0]], [0.0, 0.0, 1.0]]
    return H


def _flags(flags: Sequence[bool] | None, n: int, what: str) -> list[bool]:
    if flags is None:
        return [False] * n
    out = [bool(f) for f in flags]
    if len(out) != n:
        raise ConfigError(f"fuse_sources: {what} has {len(out)} flags for {n} sources.")
    return out


def fuse_sources(
    sources: Sequence[OdometrySource],
    *,
    poses: Sequence[PoseSource] = (),
    gate_poses: bool = False,
    yaw_rate_bias: Sequence[bool] | None = None,
    speed_scale: Sequence[bool] | None = None,
    initial_pose: ArrayLike = (0.0, 0.0, 0.0),
    accel_noise: float = 0.5,
    yaw_accel_noise: float = 0.5,
    gate_prob: float | None = 0.999,
    bias_prior: float = math.radians(1.0),
    scale_prior: float = 0.05,
    bias_walk: float = 1e-4,
    scale_walk: float = 1e-4,
) -> FusedOdometry:
    """Loosely coupled EKF fusion of any number of odometry sources (Munjer §3.5, visual-lidar
    §2.4).

    Munjer et al. (2025) fuse ICP scan-matching odometry, the IMU and the wheel encoders in an
    EKF (their Fig. 6) without giving its equations; this is the planar constant-velocity
    filter described in the module docstring, with one velocity measurement model per source:
    source ``s`` measures ``((1 + k_s) v, ω + b_s)`` where ``b_s`` (a yaw-rate bias, e.g. a
    gyro's) and ``k_s`` (a speed-scale error, e.g. a wheel radius error) are augmented states
    only for the sources flagged in ``yaw_rate_bias`` / ``speed_scale`` (else fixed at 0).
    Typical use: ``[gyro, wheel, lidar]`` with ``yaw_rate_bias=[True, False, False]`` and
    ``speed_scale=[False, True, False]`` -- the lidar is the metric and heading reference, the
    filter learns the gyro bias and the wheel scale from it and bridges lidar dropouts with
    calibrated inertial + wheel dead reckoning.

    Pose sources (a scan-to-map lidar odometry) update the pose directly: ``z = (x, y, θ)``,
    ``H = [I₃ 0]``, the heading innovation wrapped to (-π, π], gated with 3 degrees of freedom.
    Such a source defines the odometry frame; the velocity sources bridge its gaps and smooth
    between its frames. A pose source with ``drift`` (:class:`PoseSource`) does not: it
    measures ``z = o ⊕ p``, its frame offset ``o`` (3 augmented states, starting at the
    identity) a random walk with the source's drift, so the velocity sources correct its
    drift as well as its jitter (ours: an absolute pose whose error in fact drifts makes the
    filter overconfident, its covariance stuck at the jitter; docs/algorithms/slam-frontends.md).

    Parameters
    ----------
    sources : sequence of OdometrySource
        Same time base. At equal times, earlier sources are applied first. A source with
        ``interval_start`` (e.g. from :func:`velocities_from_poses`) is applied at the start
        of each sample's interval, so the filter predicts every interval with the velocity
        measured over it (offline this is exact; online it is one interval of latency); the
        interval ends are output times too.
    poses : sequence of PoseSource
        Absolute pose measurements in the output frame; applied after the velocity sources at
        equal times.
    gate_poses : bool
        Gate pose measurements too. Off by default: a pose source defines the frame, and a
        scan-to-map odometry that jumped stays jumped, so gating it would lock it out for
        good once the filter and the source disagree (seen on a simulated 2D drive: after a
        run of accepted wheel slips every later lidar pose was rejected).
    yaw_rate_bias, speed_scale : sequence of bool, optional
        Per source: estimate its yaw-rate bias / its speed-scale error. Never flag every source
        that carries speed for scale: relative sources cannot tell whose scale is right.
    initial_pose : (3,)
    accel_noise : float, m/s² /√Hz
        Spectral density of the random walk on speed (how fast the speed may change).
    yaw_accel_noise : float, rad/s² /√Hz
    gate_prob : float in (0, 1) or None
        Innovation gate (ours): a measurement whose squared Mahalanobis innovation exceeds the
        chi-square quantile of this probability is rejected. ``None`` = no gate (the papers).
    bias_prior : float, rad/s
        Prior std of each yaw-rate bias.
    scale_prior : float
        Prior std of each scale error.
    bias_walk, scale_walk : float, per √s
        Random-walk densities of the biases and scale errors.

    Returns
    -------
    FusedOdometry

    Raises
    ------
    InputError
        If no source is given or a source is empty.
    ConfigError
        On bad noise values or flag lists of the wrong length.
    """
    srcs = list(sources)
    psrcs = list(poses)
    counts = [len(s) for s in srcs] + [len(p) for p in psrcs]
    if not counts or min(counts) == 0:
        raise InputError("fuse_sources: every odometry source needs at least one sample.")
    if not (accel_noise > 0 and yaw_accel_noise > 0):
        raise ConfigError("fuse_sources: accel_noise and yaw_accel_noise must be > 0.")
    if gate_prob is not None and not 0.0 < gate_prob < 1.0:
        raise ConfigError(f"fuse_sources: gate_prob must be in (0, 1) or None, got {gate_prob}.")
    if min(bias_prior, scale_prior, bias_walk, scale_walk) < 0:
        raise ConfigError("fuse_sources: calibration priors and walks must be >= 0.")
    n_src = len(srcs)
    fb = _flags(yaw_rate_bias, n_src, "yaw_rate_bias")
    fk = _flags(speed_scale, n_src, "speed_scale")
    # augmented state index of each source's bias / scale (-1 = not estimated)
    names: list[str] = []
    bias_idx = np.full(n_src, -1, dtype=np.int64)
    scale_idx = np.full(n_src, -1, dtype=np.int64)
    for i, s in enumerate(srcs):
        label = s.name or f"source{i}"
        if fb[i]:
            bias_idx[i] = 5 + len(names)
            names.append(f"{label}.yaw_rate_bias")
        if fk[i]:
            scale_idx[i] = 5 + len(names)
            names.append(f"{label}.speed_scale")
    n_cal = len(names)
    # frame offset (x, y, θ) of each drifting pose source (PoseSource.drift), after the
    # calibration states; -1 = absolute poses
    off_idx = np.full(len(psrcs), -1, dtype=np.int64)
    for j, ps in enumerate(psrcs):
        if ps.drift is not None:
            off_idx[j] = 5 + len(names)
            label = ps.name or f"poses{j}"
            names.extend(f"{label}.frame_offset_{c}" for c in ("x", "y", "theta"))
    dim = 5 + len(names)

    # merge the streams by time (stable: lower source index first at equal times)
    # a velocity measured over an interval is applied to that interval: processed at the
    # interval's start (an end-stamped one would be applied one interval late: at 5 Hz in a
    # 0.8 rad/s turn that lag cost ~9 deg of heading per turn); its end becomes an output epoch
    z0 = np.zeros(0)
    tv = (
        np.concatenate([s.times if s.interval_start is None else s.interval_start for s in srcs])
        if srcs
        else z0
    )
    ends = [s.times for s in srcs if s.interval_start is not None]
    t_ends = np.concatenate(ends) if ends else z0
    z_all = np.zeros((tv.shape[0], 2))
    r_all = np.zeros((tv.shape[0], 2))
    if srcs:
        z_all = np.column_stack(
            (np.concatenate([s.speed for s in srcs]), np.concatenate([s.yaw_rate for s in srcs]))
        )
        sig = [np.concatenate([np.asarray(getattr(s, f)) for s in srcs]) for f in _SIGMAS]
        r_all = np.column_stack(sig) ** 2
    zp = np.concatenate([p.poses for p in psrcs]) if psrcs else np.zeros((0, 3))
    rp = np.concatenate([p.covs for p in psrcs]) if psrcs else np.zeros((0, 3, 3))
    t_all = np.concatenate([tv, *(p.times for p in psrcs), t_ends])
    # source index -1: an output epoch without a measurement
    src = np.concatenate(
        (np.repeat(np.arange(len(counts), dtype=np.int64), counts), np.full(t_ends.shape, -1))
    )
    row = np.concatenate(
        (np.arange(tv.shape[0]), np.arange(zp.shape[0]), np.zeros(t_ends.shape, np.int64))
    )
    order = np.argsort(t_all, kind="stable")
    t_all, src, row = t_all[order], src[order], row[order]
    thr1 = chi2.ppf(gate_prob, 1) if gate_prob is not None else math.inf
    thr2 = chi2.ppf(gate_prob, 2) if gate_prob is not None else math.inf
    thr3 = chi2.ppf(gate_prob, 3) if gate_prob is not None else math.inf
    qa, qw = accel_noise**2, yaw_accel_noise**2
    q_aug = np.array([bias_walk**2 if n.endswith("bias") else scale_walk**2 for n in names[:n_cal]])
    dp = np.concatenate([p.drift for p in psrcs if p.drift is not None] or [np.zeros((0, 3, 3))])
    drift_all = np.full((zp.shape[0], 3, 3), np.nan)
    if dp.shape[0]:
        has = np.concatenate([np.full(len(p), p.drift is not None) for p in psrcs])
        drift_all[has] = dp
    pose_src = np.concatenate([np.full(len(p), j) for j, p in enumerate(psrcs)] or [z0]).astype(
        np.int64
    )

    x = np.zeros(dim)
    x[:3] = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    p_aug = [bias_prior**2 if n.endswith("bias") else scale_prior**2 for n in names[:n_cal]]
    p_aug += [0.0] * (dim - 5 - n_cal)  # every pose source starts in the output frame
    P = np.diag([0.0, 0.0, 0.0, 1e2, 1e2, *p_aug])
    n = t_all.shape[0]
    out_x = np.empty((n, 5))
    out_P = np.empty((n, 3, 3))
    rejected = np.zeros(n_src + len(psrcs), dtype=np.int64)
    Hp = Hp_abs = np.zeros((3, dim))
    Hp[:, :3] = np.eye(3)
    t_prev = float(t_all[0])
    F = np.eye(dim)
    H = np.zeros((2, dim))
    for i in range(n):
        dt = float(t_all[i]) - t_prev
        t_prev = float(t_all[i])
        if dt > 0:
            v, w, th = x[3], x[4], x[2]
            m = th + 0.5 * w * dt
            cm, sm = math.cos(m), math.sin(m)
            x[0] += v * dt * cm
            x[1] += v * dt * sm
            x[2] = th + w * dt
            F[0, 2] = -v * dt * sm
            F[0, 3] = dt * cm
            F[0, 4] = -0.5 * v * dt * dt * sm
            F[1, 2] = v * dt * cm
            F[1, 3] = dt * sm
            F[1, 4] = 0.5 * v * dt * dt * cm
            F[2, 4] = dt
            P = F @ P @ F.T
            P[3, 3] += qa * dt
            P[4, 4] += qw * dt
            P[5 : 5 + n_cal, 5 : 5 + n_cal] += np.diag(q_aug * dt)
        s_i = int(src[i])
        if s_i < 0:  # output epoch only
            pass
        elif s_i >= n_src:  # pose measurement
            r_i = int(row[i])
            Rm = rp[r_i]
            oi = int(off_idx[pose_src[r_i]])
            if oi >= 0:
                Hp = _drift_step(x, P, oi, zp[r_i], drift_all[r_i], dim)
            if np.all(np.isfinite(Rm)):
                h = x[:3] if oi < 0 else _offset_pose(x[oi : oi + 3], x[:3])
                y = zp[r_i] - h
                y[2] = math.remainder(y[2], 2.0 * math.pi)
                thr = thr3 if gate_poses else math.inf
                if not _ekf_update(x, P, Hp, y, Rm, thr):
                    rejected[s_i] += 1
            if oi >= 0:
                Hp = Hp_abs
        else:
            z = z_all[row[i]]
            have = np.isfinite(z)
            if np.any(have):
                bi, ki = int(bias_idx[s_i]), int(scale_idx[s_i])
                H[:] = 0.0
                sc = 1.0 + x[ki] if ki >= 0 else 1.0
                pred = np.array([sc * x[3], x[4] + (x[bi] if bi >= 0 else 0.0)])
                H[0, 3] = sc
                if ki >= 0:
                    H[0, ki] = x[3]
                H[1, 4] = 1.0
                if bi >= 0:
                    H[1, bi] = 1.0
                y = z[have] - pred[have]
                R = np.diag(r_all[row[i]][have])
                if not _ekf_update(x, P, H[have], y, R, thr2 if y.size == 2 else thr1):
                    rejected[s_i] += 1
        out_x[i] = x[:5]
        out_P[i] = P[:3, :3]
    # keep the last state per distinct time (Trajectory needs strictly increasing times)
    last = np.r_[np.diff(t_all) > 0, True]
    fused_poses = out_x[last, :3].copy()
    fused_poses[:, 2] = wrap_angle(fused_poses[:, 2])
    traj = Trajectory(t_all[last], fused_poses, frame="odom")
    return FusedOdometry(
        traj,
        out_P[last],
        out_x[last, 3:5],
        rejected,
        calibration=x[5:].copy(),
        calibration_names=tuple(names),
        source_names=tuple(
            [s.name or f"source{i}" for i, s in enumerate(srcs)]
            + [ps.name or f"poses{j}" for j, ps in enumerate(psrcs)]
        ),
    )


def fuse_odometry(
    source_a: OdometrySource,
    source_b: OdometrySource,
    *,
    initial_pose: ArrayLike = (0.0, 0.0, 0.0),
    accel_noise: float = 0.5,
    yaw_accel_noise: float = 0.5,
    gate_prob: float | None = 0.999,
    calibrate: bool = False,
    scale_reference: Literal["a", "b"] = "a",
    bias_prior: float = math.radians(1.0),
    scale_prior: float = 0.05,
    bias_walk: float = 1e-4,
    scale_walk: float = 1e-4,
) -> FusedOdometry:
    """Two-source form of :func:`fuse_sources` (visual-lidar §2.4, Munjer §3.5).

    Parameters
    ----------
    source_a, source_b : OdometrySource
        E.g. wheel odometry (A) and visual or scan-matching odometry (B), same time base.
    calibrate : bool
        Ours: augment the state with source A's yaw-rate bias ``b`` and the speed-scale error
        ``k`` of the source that is not the scale reference. This encodes the visual-lidar
        paper's §2.4 observation: wheel odometry (A) has metric scale but a drifting heading,
        visual odometry (B) "estimates direction accurately" but "may have a different scale".
        Both errors are systematic, not white: a plain EKF only averages them down, the
        augmented one estimates them. False = the papers' plain filter (``b = k = 0`` fixed).
    scale_reference : {"a", "b"}
        Which source is metric when calibrating: ``"a"`` (default, wheel) estimates B's speed
        scale; ``"b"`` estimates A's instead (e.g. B is LiDAR scan matching).
    Other parameters : see :func:`fuse_sources`.

    Returns
    -------
    FusedOdometry
        ``n_rejected`` has 2 entries, ``calibration`` is ``[b, k]``.
    """
    if len(source_a) == 0 or len(source_b) == 0:
        raise InputError("fuse_odometry: both odometry sources need at least one sample.")
    if scale_reference not in ("a", "b"):
        raise ConfigError(
            f"fuse_odometry: scale_reference must be 'a' or 'b', got {scale_reference!r}."
        )
    return fuse_sources(
        [source_a, source_b],
        yaw_rate_bias=[True, False],
        speed_scale=[scale_reference == "b", scale_reference == "a"],
        initial_pose=initial_pose,
        accel_noise=accel_noise,
        yaw_accel_noise=yaw_accel_noise,
        gate_prob=gate_prob,
        bias_prior=bias_prior if calibrate else 0.0,
        scale_prior=scale_prior if calibrate else 0.0,
        bias_walk=bias_walk if calibrate else 0.0,
        scale_walk=scale_walk if calibrate else 0.0,
    )
