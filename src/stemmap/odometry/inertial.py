"""Gyro and wheel-speed odometry sources, and their EKF fusion with lidar odometry
(Munjer 2025 §3.5, Fig. 6: ICP scan matching + IMU + wheel encoders in one EKF).

The filter is :func:`stemmap.odometry.fusion.fuse_sources`; this module builds its sources
from an :class:`~stemmap.io.imu.InertialLog` and decides which calibration states are
observable:

* the gyro's yaw-rate bias is estimated only when another source measures yaw rate (lidar
  or a camera): against the gyro alone it is unobservable;
* the wheels' speed scale is estimated only when another source measures speed;
* lidar (and any extra pose source) is the metric and heading reference.

The vehicle reference point is taken to be the lidar's: a lidar mounted ahead of the axle
sees a lateral velocity in turns, which the non-holonomic speed model ignores.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import InputError
from stemmap.io.imu import InertialLog
from stemmap.odometry.fusion import (
    FusedOdometry,
    OdometrySource,
    dead_reckon_source,
    fuse_sources,
)
from stemmap.types import FloatArray, LaserScan, PointCloud, Trajectory

if TYPE_CHECKING:
    from stemmap.odometry.lidar import LidarOdometryConfig, LidarOdometryResult

__all__ = [
    "fuse_front_ends",
    "gyro_source",
    "lidar_inertial_odometry",
    "motion_prior",
    "wheel_source",
]

#: Default 1-sigma of one gyro yaw-rate sample (rad/s): white noise of an MTi-class MEMS gyro
#: at 100 Hz (0.07 deg/s) rounded up to cover vibration on rough ground.
GYRO_SIGMA = math.radians(0.5)
#: Default 1-sigma of one wheel-speed sample (m/s).
WHEEL_SIGMA = 0.1


def gyro_source(
    log: InertialLog, *, sigma: float = GYRO_SIGMA, name: str = "gyro"
) -> OdometrySource | None:
    """The IMU's yaw rate (``gyro_z``) as an :class:`OdometrySource` (no speed); None when
    the log has no gyro sample."""
    ok = np.isfinite(log.gyro[:, 2])
    if not ok.any():
        return None
    t = log.times[ok]
    return OdometrySource(t, np.full(t.shape[0], np.nan), log.gyro[ok, 2], 1.0, sigma, name=name)


def wheel_source(
    log: InertialLog, *, sigma: float = WHEEL_SIGMA, name: str = "wheel"
) -> OdometrySource | None:
    """The wheel speed as an :class:`OdometrySource` (no yaw rate); None without samples."""
    ok = np.isfinite(log.wheel_speed)
    if not ok.any():
        return None
    t = log.times[ok]
    return OdometrySource(
        t, log.wheel_speed[ok], np.full(t.shape[0], np.nan), sigma, 1.0, name=name
    )


def fuse_front_ends(
    *,
    lidar: LidarOdometryResult | None = None,
    inertial: InertialLog | None = None,
    extra: Sequence[OdometrySource] = (),
    initial_pose: ArrayLike | None = None,
    gyro_sigma: float = GYRO_SIGMA,
    wheel_sigma: float = WHEEL_SIGMA,
    gate_prob: float | None = 0.999,
) -> FusedOdometry:
    """EKF fusion of lidar odometry, gyro yaw rate and wheel speed (Munjer 2025 §3.5).

    Parameters
    ----------
    lidar : LidarOdometryResult, optional
        Scan-matching odometry (:func:`~stemmap.odometry.lidar.lidar_odometry`).
    inertial : InertialLog, optional
        Gyro and / or wheel-speed samples.
    extra : sequence of OdometrySource
        Further metric velocity sources (e.g. a camera's visual odometry).
    initial_pose : (3,), optional
        Default: the lidar's first pose, else the origin.
    gyro_sigma, wheel_sigma : float
        Per-sample 1-sigma of the gyro (rad/s) and wheel speed (m/s).
    gate_prob : float or None
        Innovation gate of :func:`~stemmap.odometry.fusion.fuse_sources` (rejects wheel
        slips that disagree with the lidar).

    Returns
    -------
    FusedOdometry

    Raises
    ------
    InputError
        When no source is given, or nothing measures speed (a gyro alone cannot be integrated
        into positions).
    """
    sources: list[OdometrySource] = []
    bias: list[bool] = []
    scale: list[bool] = []
    pose_src = [] if lidar is None else [lidar.pose_source()]
    reference = list(extra)
    metric = bool(pose_src or reference)
    gyro = wheel = None
    if inertial is not None:
        gyro = gyro_source(inertial, sigma=gyro_sigma)
        wheel = wheel_source(inertial, sigma=wheel_sigma)
    if gyro is not None:
        sources.append(gyro)
        bias.append(metric)
        scale.append(False)
    if wheel is not None:
        sources.append(wheel)
        bias.append(False)
        scale.append(metric)
    for s in reference:
        sources.append(s)
        bias.append(False)
        scale.append(False)
    if not (sources or pose_src):
        raise InputError("odometry fusion: no source given (lidar frames, IMU or wheel speed).")
    if wheel is None and not metric:
        raise InputError(
            "odometry fusion: nothing measures speed: a gyro alone gives heading, not position; "
            "add lidar frames or a wheel_speed column."
        )
    if initial_pose is None:
        p0 = lidar.planar[0] if lidar is not None else np.zeros(3)
    else:
        p0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    return fuse_sources(
        sources,
        poses=pose_src,
        yaw_rate_bias=bias,
        speed_scale=scale,
        initial_pose=p0,
        gate_prob=gate_prob,
    )


def motion_prior(
    log: InertialLog, *, initial_pose: ArrayLike = (0.0, 0.0, 0.0)
) -> Callable[[float, float], FloatArray] | None:
    """Planar motion between two times by dead reckoning the gyro and wheel speed (each held
    between its samples): the ICP starting guess of
    :func:`stemmap.odometry.lidar.lidar_odometry` ("ICP + IMU", Munjer 2025 §3.5).

    Returns None when the log lacks either a gyro or a wheel speed (no planar motion can be
    predicted from one of them alone). Outside the log's time span the motion is NaN (the
    caller falls back to its own model).
    """
    gyro = gyro_source(log)
    wheel = wheel_source(log)
    if gyro is None or wheel is None:
        return None
    merged = OdometrySource(log.times, log.wheel_speed, log.gyro[:, 2], 1.0, 1.0, name="imu")
    dr = dead_reckon_source(merged, initial_pose)
    t_lo, t_hi = float(dr.times[0]), float(dr.times[-1])

    def prior(t0: float, t1: float) -> FloatArray:
        if not (t_lo <= t0 <= t_hi and t_lo <= t1 <= t_hi):
            return np.full(3, np.nan)
        a, b = dr.interpolate([t0, t1])
        d = b[:2] - a[:2]
        c, s = math.cos(a[2]), math.sin(a[2])
        return np.array(
            [c * d[0] + s * d[1], -s * d[0] + c * d[1], math.remainder(b[2] - a[2], math.tau)]
        )

    return prior


def lidar_inertial_odometry(
    frames: Iterable[tuple[float, ArrayLike | PointCloud | LaserScan]],
    inertial: InertialLog | None = None,
    config: LidarOdometryConfig | None = None,
    *,
    extra: Sequence[OdometrySource] = (),
) -> tuple[Trajectory, LidarOdometryResult, FusedOdometry | None]:
    """The paper's odometry front end end to end (Munjer 2025 §3.5, Fig. 6): KISS-ICP on every
    frame, started from the gyro + wheel dead reckoning (:func:`motion_prior`), then the EKF
    (:func:`fuse_front_ends`) of lidar, gyro, wheels and ``extra``.

    Returns
    -------
    trajectory : one planar pose per frame (frame ``odom``: the first lidar pose's frame); the
        lidar's own trajectory when there is nothing to fuse
    lidar : the scan-matching result
    fused : the EKF result, None without ``inertial`` and ``extra``
    """
    from stemmap.odometry.lidar import lidar_odometry

    prior = motion_prior(inertial) if inertial is not None else None
    lidar = lidar_odometry(frames, config, motion_prior=prior)
    if inertial is None and not extra:
        return lidar.trajectory(), lidar, None
    if len(lidar) < 2:
        raise InputError(f"the lidar odometry has {len(lidar)} frame(s); fusion needs 2.")
    fused = fuse_front_ends(lidar=lidar, inertial=inertial, extra=extra)
    poses = fused.trajectory.interpolate(lidar.times)
    return Trajectory(lidar.times, poses, frame="odom"), lidar, fused
