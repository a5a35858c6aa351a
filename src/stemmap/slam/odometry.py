"""Loosely coupled EKF fusion of two odometry sources (visual-lidar paper §2.4; Munjer 2025 §3.5).

Both papers run each odometry (visual SLAM and LiDAR SLAM; ICP scan matching, IMU and wheels)
on its own and combine their *outputs* in an Extended Kalman Filter -- "loosely coupled". Neither
paper gives the filter's equations; we use the standard planar constant-velocity EKF of ROS
``robot_localization`` style, fusing each source's body-frame velocities (decision recorded in
docs/algorithms/slam-frontends.md):

* state ``x = (x, y, θ, v, ω)``: pose in the odometry frame, forward speed, yaw rate;
* prediction over ``dt`` (unicycle, mid-point heading)::

      x += v dt cos(θ + ω dt / 2),  y += v dt sin(θ + ω dt / 2),  θ += ω dt

  with random-walk process noise on ``(v, ω)`` of spectral density ``(σ_a², σ_α²)``;
* update with a source's ``(v, ω)`` measurement, ``H = [0 0 0 1 0; 0 0 0 0 1]``; a source may
  give only one of the two (NaN for the other).

A source that outputs poses (a SLAM odometry) is turned into velocities by
:func:`velocities_from_poses` (differencing consecutive poses in the body frame), which is what
"loosely coupled" means here.

Ours, on top of the papers: an optional chi-square innovation gate (``gate_prob``) rejects
measurements inconsistent with the other source -- wheel slip shows up as an encoder speed far
from the visual speed and is dropped instead of averaged in.
"""

from __future__ import annotations

import math
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
    "dead_reckon_source",
    "fuse_odometry",
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
    """

    times: FloatArray
    speed: FloatArray
    yaw_rate: FloatArray
    sigma_speed: float | FloatArray
    sigma_yaw_rate: float | FloatArray
    name: str = ""

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

    def __len__(self) -> int:
        return int(self.times.shape[0])


def velocities_from_poses(
    trajectory: Trajectory, *, sigma_speed: float, sigma_yaw_rate: float, name: str = ""
) -> OdometrySource:
    """Turn a pose-output odometry (e.g. a LiDAR or visual SLAM) into a velocity source.

    Velocity of interval ``[t_k, t_{k+1}]`` is ``between(p_k, p_{k+1}) / dt``, time-stamped at
    the interval's end (the moment it becomes known); the forward component is the speed (the
    lateral one is ignored: non-holonomic vehicle).
    """
    t = trajectory.times
    p = trajectory.poses
    if t.shape[0] < 2:
        raise InputError(f"{name or 'trajectory'}: need at least 2 poses to difference.")
    dt = np.diff(t)
    c, s = np.cos(p[:-1, 2]), np.sin(p[:-1, 2])
    dx = np.diff(p[:, 0])
    dy = np.diff(p[:, 1])
    fwd = c * dx + s * dy
    dth = wrap_angle(np.diff(p[:, 2]))
    return OdometrySource(t[1:], fwd / dt, dth / dt, sigma_speed, sigma_yaw_rate, name=name)


def dead_reckon_source(
    source: OdometrySource, initial_pose: ArrayLike = (0.0, 0.0, 0.0)
) -> Trajectory:
    """Integrate one source alone (zero-order hold of each sample until the next one).

    The baseline the fusion is compared against. NaN components are held at their last value.
    """
    t = source.times
    v = _ffill(source.speed)
    w = _ffill(source.yaw_rate)
    p0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    dt = np.diff(t)
    dth = w[:-1] * dt
    th = p0[2] + np.concatenate(([0.0], np.cumsum(dth)))
    mid = th[:-1] + 0.5 * dth
    x = p0[0] + np.concatenate(([0.0], np.cumsum(v[:-1] * dt * np.cos(mid))))
    y = p0[1] + np.concatenate(([0.0], np.cumsum(v[:-1] * dt * np.sin(mid))))
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
    """Output of :func:`fuse_odometry`.

    Attributes
    ----------
    trajectory : Trajectory
        Fused pose after every processed measurement time.
    covariances : ndarray (N, 3, 3)
        Pose covariance at those times.
    velocities : ndarray (N, 2)
        Fused (v, ω).
    n_rejected : ndarray (2,), int
        Measurements of source A / B rejected by the innovation gate.
    calibration : ndarray (2,)
        Final estimates of source A's yaw-rate bias (rad/s) and the speed-scale error of the
        non-reference source (zeros unless ``calibrate``).
    """

    trajectory: Trajectory
    covariances: FloatArray
    velocities: FloatArray
    n_rejected: NDArray[np.int64]
    calibration: FloatArray


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
    """Loosely coupled EKF fusion of two odometry sources (visual-lidar §2.4, Munjer §3.5).

    Parameters
    ----------
    source_a, source_b : OdometrySource
        E.g. wheel odometry (A) and visual or scan-matching odometry (B), same time base.
    initial_pose : (3,)
    accel_noise : float, m/s² /√Hz
        Spectral density of the random walk on speed (how fast the speed may change).
    yaw_accel_noise : float, rad/s² /√Hz
    gate_prob : float in (0, 1) or None
        Innovation gate (ours): a measurement whose squared Mahalanobis innovation exceeds the
        chi-square quantile of this probability is rejected. ``None`` = no gate (the papers).
    calibrate : bool
        Ours: augment the state with source A's yaw-rate bias ``b`` and source B's speed-scale
        error ``k`` (A measures ``(v, ω + b)``, B measures ``((1 + k) v, ω)``), both slow random
        walks. This encodes the visual-lidar paper's §2.4 observation: wheel odometry (A) has
        metric scale but a drifting heading, visual odometry (B) "estimates direction
        accurately" but "may have a different scale". Both errors are systematic, not white: a
        plain EKF only averages them down, the augmented one estimates them (A anchors the
        scale, B the heading). False = the papers' plain filter (``b = k = 0`` fixed).
    scale_reference : {"a", "b"}
        Which source is metric when calibrating: ``"a"`` (default, wheel) estimates B's speed
        scale as above; ``"b"`` estimates A's instead (e.g. B is LiDAR scan matching, or a
        visual odometry known to be well scaled). Two relative sources cannot tell whose scale
        is right; this is a modelling choice.
    bias_prior : float, rad/s
        Prior std of ``b``.
    scale_prior : float
        Prior std of ``k``.
    bias_walk, scale_walk : float, per √s
        Random-walk densities of ``b`` and ``k``.

    Returns
    -------
    FusedOdometry

    Raises
    ------
    InputError
        If a source is empty. ConfigError on bad noise values.
    """
    if len(source_a) == 0 or len(source_b) == 0:
        raise InputError("fuse_odometry: both odometry sources need at least one sample.")
    if not (accel_noise > 0 and yaw_accel_noise > 0):
        raise ConfigError("fuse_odometry: accel_noise and yaw_accel_noise must be > 0.")
    if gate_prob is not None and not 0.0 < gate_prob < 1.0:
        raise ConfigError(f"fuse_odometry: gate_prob must be in (0, 1) or None, got {gate_prob}.")
    if scale_reference not in ("a", "b"):
        raise ConfigError(
            f"fuse_odometry: scale_reference must be 'a' or 'b', got {scale_reference!r}."
        )
    if min(bias_prior, scale_prior, bias_walk, scale_walk) < 0:
        raise ConfigError("fuse_odometry: calibration priors and walks must be >= 0.")
    # merge both streams by time (stable: A before B at equal times)
    t_all = np.concatenate((source_a.times, source_b.times))
    src = np.concatenate((np.zeros(len(source_a), np.int64), np.ones(len(source_b), np.int64)))
    z_all = np.column_stack(
        (
            np.concatenate((source_a.speed, source_b.speed)),
            np.concatenate((source_a.yaw_rate, source_b.yaw_rate)),
        )
    )
    r_all = np.column_stack(
        (
            np.concatenate((source_a.sigma_speed, source_b.sigma_speed)) ** 2,
            np.concatenate((source_a.sigma_yaw_rate, source_b.sigma_yaw_rate)) ** 2,
        )
    )
    order = np.argsort(t_all, kind="stable")
    t_all, src, z_all, r_all = t_all[order], src[order], z_all[order], r_all[order]
    thr1 = chi2.ppf(gate_prob, 1) if gate_prob is not None else math.inf
    thr2 = chi2.ppf(gate_prob, 2) if gate_prob is not None else math.inf
    qa, qw = accel_noise**2, yaw_accel_noise**2
    qb = bias_walk**2 if calibrate else 0.0
    qk = scale_walk**2 if calibrate else 0.0

    # state: x, y, theta, v, omega, b (A's yaw-rate bias), k (speed-scale error of the source
    # that is not the scale reference)
    x = np.zeros(7)
    x[:3] = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    P = np.diag(
        [
            0.0,
            0.0,
            0.0,
            1e2,
            1e2,
            bias_prior**2 if calibrate else 0.0,
            scale_prior**2 if calibrate else 0.0,
        ]
    )
    n = t_all.shape[0]
    out_x = np.empty((n, 7))
    out_P = np.empty((n, 3, 3))
    rejected = np.zeros(2, dtype=np.int64)
    t_prev = float(t_all[0])
    F = np.eye(7)
    H = np.zeros((2, 7))
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
            P[5, 5] += qb * dt
            P[6, 6] += qk * dt
        z = z_all[i]
        have = np.isfinite(z)
        if np.any(have):
            # h_A = (s_A v, omega + b);  h_B = (s_B v, omega) with s = 1 + k for the source
            # whose scale is estimated (the other one is the metric reference)
            H[:] = 0.0
            scaled = (src[i] == 1) == (scale_reference == "a")
            sc = 1.0 + x[6] if scaled else 1.0
            pred = np.array([sc * x[3], x[4] + (x[5] if src[i] == 0 else 0.0)])
            H[0, 3] = sc
            if scaled:
                H[0, 6] = x[3]
            H[1, 4] = 1.0
            if src[i] == 0:
                H[1, 5] = 1.0
            Hs = H[have]
            y = z[have] - pred[have]
            S = Hs @ P @ Hs.T + np.diag(r_all[i][have])
            Sinv = np.linalg.inv(S)
            d2 = float(y @ Sinv @ y)
            if d2 > (thr2 if y.size == 2 else thr1):
                rejected[src[i]] += 1
            else:
                K = P @ Hs.T @ Sinv
                x = x + K @ y
                P = P - K @ S @ K.T
                P = 0.5 * (P + P.T)
        out_x[i] = x
        out_P[i] = P[:3, :3]
    # keep the last state per distinct time (Trajectory needs strictly increasing times)
    last = np.r_[np.diff(t_all) > 0, True]
    poses = out_x[last, :3].copy()
    poses[:, 2] = wrap_angle(poses[:, 2])
    traj = Trajectory(t_all[last], poses, frame="odom")
    return FusedOdometry(
        traj, out_P[last], out_x[last, 3:5], rejected, calibration=out_x[-1, 5:].copy()
    )
