"""A Munjer-like lidar drive: a 16-beam spinning lidar at 10 Hz, an IMU and wheel encoders on a
vehicle driving through a 3D stand, with ground truth (the odometry test bed of Munjer 2025).

The vehicle motion comes from :func:`stemmap.sim.trajectory.simulate_run` (pure pursuit along
waypoints, exact unicycle truth) run on the stand's 2D footprint; each lidar frame is one
instantaneous revolution (no motion skew) from the true pose at its time, cast with
:mod:`stemmap.sim.lidar`; the IMU and wheel speed come from :func:`stemmap.sim.imu.simulate_imu`
on the same controls.

:func:`simulate_s_curve_drive` is the planar counterpart used by the odometry tests and
benchmark: a 2D scanner and the same IMU model along an S curve through a random stand.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import ConfigError
from stemmap.sim.forest import Stand, random_stand
from stemmap.sim.imu import ImuNoise, ImuSim, simulate_imu
from stemmap.sim.lidar import LidarModel, Stand3D, _scan_from, lidar_preset
from stemmap.sim.paths import s_curve_path
from stemmap.sim.trajectory import SimRun, distance_to_polyline, simulate_run
from stemmap.types import FloatArray, PointCloud, Trajectory

__all__ = ["LidarDrive", "clear_corridor3d", "simulate_lidar_drive", "simulate_s_curve_drive"]


def clear_corridor3d(stand: Stand3D, path: ArrayLike, half_width: float) -> Stand3D:
    """Remove stems whose surface, branches whose start and shrub spheres whose surface lie
    within ``half_width`` (m) of the path polyline (the 3D twin of
    :func:`stemmap.sim.trajectory.clear_corridor`)."""
    p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] < 2:
        raise ConfigError("clear_corridor3d needs a path with at least 2 points.")
    keep_t = distance_to_polyline(stand.base_xy, p) - stand.dbh / 2 > half_width
    keep_b = distance_to_polyline(stand.branches[:, :2], p) > half_width
    keep_s = distance_to_polyline(stand.spheres[:, :2], p) - stand.spheres[:, 3] > half_width
    return Stand3D(
        stand.base_xy[keep_t],
        stand.dbh[keep_t],
        stand.heights[keep_t],
        stand.lean[keep_t],
        stand.taper[keep_t],
        branches=stand.branches[keep_b],
        spheres=stand.spheres[keep_s],
        ground=stand.ground,
    )


@dataclass(frozen=True, eq=False)
class LidarDrive:
    """Output of :func:`simulate_lidar_drive`.

    Attributes
    ----------
    stand : Stand3D
        The stand after clearing the corridor.
    frames : tuple of PointCloud
        One revolution per lidar time, sensor frame (x forward, z up), field ``label``.
    times : ndarray (F,), s
    true_poses : Trajectory
        Sensor (= vehicle reference point) pose at each frame, world frame.
    run : SimRun
        The 2D drive: ``true_path`` / ``true_odometry`` at the IMU rate, and 2D scans at the
        lidar times (``run.scans``, the ``scanner`` model) if wanted as a planar lidar.
    imu : ImuSim
        Gyro, accelerometer and wheel speed.
    """

    stand: Stand3D
    frames: tuple[PointCloud, ...]
    times: FloatArray
    true_poses: Trajectory
    run: SimRun
    imu: ImuSim


def simulate_lidar_drive(
    stand: Stand3D,
    waypoints: ArrayLike,
    *,
    speed: float = 4.0,
    lidar: LidarModel | str = "vlp16",
    lidar_rate_hz: float = 10.0,
    imu_rate_hz: float = 100.0,
    imu_noise: ImuNoise | str = "xsens",
    height: float = 0.8,
    corridor_half_width: float = 2.0,
    max_frames: int | None = None,
    scanner: str = "rplidar",
    rng: np.random.Generator | int | None = None,
) -> LidarDrive:
    """Drive a vehicle with a spinning lidar, an IMU and wheel encoders through ``stand``.

    Parameters
    ----------
    stand : Stand3D
    waypoints : array_like (K, 2), metres
        Followed by pure pursuit at ``speed`` (m/s; Munjer's robot: 3-5 m/s was our brief).
    lidar : LidarModel or preset name (``"vlp16"``)
    lidar_rate_hz : float
        Revolutions per second (a VLP-16 at 10 Hz).
    imu_rate_hz : float
        IMU rate; the true controls are sampled at this rate.
    imu_noise : ImuNoise or preset name (:data:`stemmap.sim.imu.IMU_PRESETS`)
    height : float, metres
        Lidar height above the ground.
    corridor_half_width : float, metres
        Stems, branches and shrubs this close to the path are removed first.
    max_frames : int, optional
        Stop after this many lidar frames.
    scanner : str
        2D scanner preset of the companion planar drive (``run.scans``).
    rng : Generator or seed
    """
    gen = np.random.default_rng(rng)
    g_run, g_lidar, g_imu = gen.spawn(3)
    model = lidar_preset(lidar) if isinstance(lidar, str) else lidar
    wp = np.asarray(waypoints, dtype=np.float64).reshape(-1, 2)
    stand = clear_corridor3d(stand, wp, corridor_half_width)
    flat = Stand(stand.trees_xy, stand.dbh)
    run = simulate_run(
        flat,
        wp,
        scanner=scanner,
        speed=speed,
        rate_hz=lidar_rate_hz,
        odom_rate_hz=imu_rate_hz,
        odometry_noise="none",
        max_scans=max_frames,
        rng=g_run,
    )
    truth = run.vehicle_poses
    frames = []
    for t, (x, y, th) in zip(truth.times, truth.poses, strict=True):
        origin = np.array([x, y, float(stand.ground_z([x, y])[0]) + height])
        pts, lab, _ = _scan_from(stand, model, origin, float(th), g_lidar)
        frames.append(PointCloud(pts, time=float(t), frame="lidar", fields={"label": lab}))
    imu = simulate_imu(run.true_odometry, noise=imu_noise, rng=g_imu)
    return LidarDrive(
        stand,
        tuple(frames),
        truth.times.copy(),
        replace(truth, frame="world"),
        run,
        imu,
    )


def simulate_s_curve_drive(
    n_trees: int,
    size: tuple[float, float],
    *,
    amplitude: float,
    length_scale: float,
    n_waypoints: int,
    min_spacing: float = 3.0,
    scanner: str = "sick_lms",
    speed: float = 3.0,
    scan_rate_hz: float = 10.0,
    imu_rate_hz: float = 100.0,
    imu_noise: ImuNoise | str = "xsens",
    corridor_half_width: float = 2.0,
    max_scans: int | None = None,
    seed: int = 0,
) -> tuple[SimRun, ImuSim]:
    """A planar odometry test drive: 2D scans, an IMU and wheel speed along an S curve through
    a random stand, with exact truth (the 2D form of the Munjer 2025 §2, §3.5 test bed).

    The stand is :func:`stemmap.sim.forest.random_stand` (``n_trees`` in ``size``, at least
    ``min_spacing`` apart); the waypoints are :func:`stemmap.sim.paths.s_curve_path`; the
    vehicle follows them by pure pursuit in :func:`stemmap.sim.trajectory.simulate_run`
    (exact wheel odometry, trees within ``corridor_half_width`` of the path removed, one scan
    per ``1 / scan_rate_hz``, controls at ``imu_rate_hz``), and
    :func:`stemmap.sim.imu.simulate_imu` samples the gyro, accelerometer and wheel speed from
    the true controls.

    Parameters
    ----------
    n_trees : int
    size : (width, height), metres
    amplitude, length_scale : float, metres
        The S curve: ``y = height / 2 + amplitude * sin(x / length_scale)``.
    n_waypoints : int
    min_spacing : float, metres
    scanner : str
        2D scanner preset (:data:`stemmap.sim.SCANNER_PRESETS`).
    speed : float, m/s
    scan_rate_hz, imu_rate_hz : float
    imu_noise : ImuNoise or preset name (:data:`stemmap.sim.imu.IMU_PRESETS`)
    corridor_half_width : float, metres
    max_scans : int, optional
        Stop after this many scans.
    seed : int
        The stand is drawn with ``seed``, the drive with ``seed + 1`` and the IMU with
        ``seed + 2`` (three independent streams, so a caller can keep one fixed).

    Returns
    -------
    run : SimRun
        The drive (``run.stand`` is the cleared stand; ``run.scans``, ``run.true_poses``,
        ``run.true_odometry``).
    imu : ImuSim
    """
    stand = random_stand(n_trees, size, min_spacing=min_spacing, rng=seed)
    waypoints = s_curve_path(
        size, amplitude=amplitude, length_scale=length_scale, n_points=n_waypoints
    )
    run = simulate_run(
        stand,
        waypoints,
        scanner=scanner,
        speed=speed,
        rate_hz=scan_rate_hz,
        odom_rate_hz=imu_rate_hz,
        odometry_noise="none",
        corridor_half_width=corridor_half_width,
        max_scans=max_scans,
        rng=seed + 1,
    )
    return run, simulate_imu(run.true_odometry, noise=imu_noise, rng=seed + 2)
