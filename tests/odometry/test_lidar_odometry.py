"""Lidar odometry (KISS-ICP) on simulated 16-beam frames and 2D scans, alone and fused with an
IMU and wheel speed in the EKF (Munjer 2025 §3.5)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.odometry.fusion import FusedOdometry, fuse_sources
from stemmap.odometry.inertial import fuse_front_ends, gyro_source, motion_prior, wheel_source
from stemmap.odometry.lidar import (
    LidarOdometry,
    LidarOdometryConfig,
    LidarOdometryResult,
    lidar_odometry,
)
from stemmap.sim import s_curve_path
from stemmap.sim.drive import LidarDrive, simulate_lidar_drive, simulate_s_curve_drive
from stemmap.sim.lidar import lidar_preset, random_stand3d
from stemmap.types import Trajectory


def _drift_percent(traj: Trajectory, truth: Trajectory) -> float:
    """End-point position error as % of the distance driven (both start at the true pose)."""
    end = traj.interpolate(truth.times[-1:])[0]
    dist = float(np.sum(np.hypot(*np.diff(truth.poses[:, :2], axis=0).T)))
    return 100.0 * float(np.hypot(*(end[:2] - truth.poses[-1, :2]))) / dist


def _dead_reckoning(drive_log, p0) -> FusedOdometry:
    return fuse_sources([gyro_source(drive_log), wheel_source(drive_log)], initial_pose=p0)


@pytest.fixture(scope="module")
def drive3d() -> LidarDrive:
    """A park-like stand (trees >= 4 m apart), 4 m/s along an S curve, VLP-16 at 10 Hz with a
    0.8 deg azimuth step (a quarter of the real density, for test time), XSens-class IMU,
    wheels 2 % fast with slips: 80 frames, ~32 m."""
    size = (90.0, 50.0)
    stand = random_stand3d(50, size, min_spacing=4.0, branches_per_tree=2, n_shrubs=3, rng=1)
    return simulate_lidar_drive(
        stand,
        s_curve_path(size, amplitude=8.0, length_scale=15.0, n_points=10),
        speed=4.0,
        lidar=lidar_preset("vlp16", azimuth_step_deg=0.8),
        max_frames=80,
        rng=3,
    )


@pytest.fixture(scope="module")
def runs3d(drive3d):
    d = drive3d
    p0 = d.true_poses.poses[0]
    frames = list(zip(d.times, d.frames, strict=True))
    lidar = lidar_odometry(frames, initial_pose=p0)
    aided = lidar_odometry(
        frames, initial_pose=p0, motion_prior=motion_prior(d.imu.log, initial_pose=p0)
    )
    fused = fuse_front_ends(lidar=aided, inertial=d.imu.log)
    return lidar, fused, _dead_reckoning(d.imu.log, p0)


@pytest.mark.slow
def test_lidar_odometry_3d_drift_bounded(drive3d, runs3d):
    """KISS-ICP on 16-beam frames: drift under 1 % of distance (the issue's target for
    lidar + IMU; lidar alone must already be within it on a well-structured stand)."""
    lidar, _, _ = runs3d
    assert isinstance(lidar, LidarOdometryResult)
    assert len(lidar) == len(drive3d.frames)
    assert not lidar.held.any()
    assert _drift_percent(lidar.trajectory(), drive3d.true_poses) < 1.0
    # heading: the yaw after 32 m within 1 degree
    dyaw = lidar.planar[-1, 2] - np.unwrap(drive3d.true_poses.poses[:, 2])[-1]
    assert abs(math.degrees(dyaw)) < 1.0


@pytest.mark.slow
def test_fused_3d_meets_target_and_beats_dead_reckoning(drive3d, runs3d):
    lidar, fused, dr = runs3d
    truth = drive3d.true_poses
    e_fused = _drift_percent(fused.trajectory, truth)
    e_dr = _drift_percent(dr.trajectory, truth)
    assert e_fused <= 1.0  # the target: lidar + IMU drift <= 1 % of distance
    assert e_fused < 0.5 * e_dr
    # with a lidar that registers every frame the EKF follows it (the lidar defines the
    # frame): adding the IMU must not cost more than 0.1 % of distance
    assert e_fused <= _drift_percent(lidar.trajectory(), truth) + 0.1
    # the filter learned the wheel scale (true 1.02, slips push it up) from the lidar
    names = dict(zip(fused.calibration_names, fused.calibration, strict=True))
    assert 0.0 < names["wheel.speed_scale"] < 0.06


@pytest.mark.slow
def test_fused_bridges_a_lidar_blackout(drive3d):
    """4 s of empty frames mid-drive (sensor blocked): lidar alone coasts at constant velocity
    through the S bend and cannot re-register (~20 % drift), dead reckoning drifts with the gyro
    bias and wheel scale (~2.5 %); the fused front end (IMU-aided ICP + EKF) beats both.
    (A 2.5 s gap on this drive is short enough for constant velocity to re-register.)"""
    d = drive3d
    p0 = d.true_poses.poses[0]
    frames = [
        (t, np.zeros((0, 3)) if 25 <= k < 65 else f.xyz)
        for k, (t, f) in enumerate(zip(d.times, d.frames, strict=True))
    ]
    lidar = lidar_odometry(frames, initial_pose=p0)
    assert int(lidar.held.sum()) == 40
    aided = lidar_odometry(
        frames, initial_pose=p0, motion_prior=motion_prior(d.imu.log, initial_pose=p0)
    )
    fused = fuse_front_ends(lidar=aided, inertial=d.imu.log)
    e_lidar = _drift_percent(lidar.trajectory(), d.true_poses)
    e_dr = _drift_percent(_dead_reckoning(d.imu.log, p0).trajectory, d.true_poses)
    e_fused = _drift_percent(fused.trajectory, d.true_poses)
    assert e_fused < min(e_lidar, e_dr)
    assert e_fused <= 1.0


@pytest.fixture(scope="module")
def drive2d():
    """2D scans (SICK LMS, 80 m) at 10 Hz along an S curve through a random stand at 3 m/s,
    with the same IMU + wheel model: ~120 m, 400 scans."""
    return simulate_s_curve_drive(
        150, (120.0, 60.0), amplitude=10.0, length_scale=15.0, n_waypoints=12, seed=3
    )


def test_lidar_odometry_2d_scans(drive2d):
    """Planar scans lifted to z = 0 register with the same code: drift < 1 % of distance, and
    the fused front end keeps lidar's accuracy (within 10 %), far below IMU + wheel dead
    reckoning."""
    run, imu = drive2d
    truth = run.true_poses
    p0 = truth.poses[0]
    cfg = LidarOdometryConfig(max_range=run.scanner.range_max, min_range=0.1)
    frames = list(zip(truth.times, run.scans, strict=True))
    lidar = lidar_odometry(frames, cfg, initial_pose=p0)
    assert np.allclose(lidar.poses[:, 2, 3], 0.0, atol=1e-6)  # stays in the plane
    aided = lidar_odometry(
        frames, cfg, initial_pose=p0, motion_prior=motion_prior(imu.log, initial_pose=p0)
    )
    fused = fuse_front_ends(lidar=aided, inertial=imu.log)
    e_lidar = _drift_percent(lidar.trajectory(), truth)
    e_fused = _drift_percent(fused.trajectory, truth)
    e_dr = _drift_percent(_dead_reckoning(imu.log, p0).trajectory, truth)
    assert e_lidar < 1.0
    # The fused front end must not lose what the better source gives: far below dead
    # reckoning, and within 10 % of lidar alone. (Until Dec 5 the test asked it to beat lidar
    # alone, 0.116 % against 0.159 %; with the 25-sub-beam scanner model of Dec 5 the scans'
    # edges are sharper and lidar alone drifts 0.063 %, the IMU-guided ICP 0.129 % and the
    # fused 0.067 %: on scans this clean the gyro's guess does not help ICP.)
    assert e_fused < 0.1 * e_dr
    assert e_fused <= 1.1 * e_lidar


# ---- degenerate inputs ------------------------------------------------------------------


def _ring(n: int = 400, r: float = 5.0) -> np.ndarray:
    """A few posts around the sensor, enough to register."""
    rng = np.random.default_rng(0)
    centres = np.array([[4.0, 2.0], [-3.0, 5.0], [6.0, -4.0], [-5.0, -3.0], [1.0, 7.0]])
    a = rng.uniform(0, 2 * np.pi, n)
    k = rng.integers(0, centres.shape[0], n)
    xy = centres[k] + 0.2 * np.column_stack((np.cos(a), np.sin(a)))
    return np.column_stack((xy, rng.uniform(0.5, 3.0, n)))


def test_empty_and_sparse_frames_are_held_not_fatal():
    lo = LidarOdometry(LidarOdometryConfig(max_range=30.0, remove_ground=False))
    s0 = lo.register(np.zeros((0, 3)), 0.0)
    assert s0.status == "held" and "0 usable points" in s0.reason
    assert np.allclose(s0.pose, np.eye(4))
    s1 = lo.register(_ring(), 0.1)
    assert s1.status == "first"
    s2 = lo.register(_ring()[:5], 0.2)  # too few points
    assert s2.status == "held" and np.all(np.isnan(s2.cov))
    nan_frame = _ring()
    nan_frame[::2] = np.nan  # NaN points are dropped, the rest registers
    s3 = lo.register(nan_frame, 0.3)
    assert s3.status == "ok"
    assert np.all(np.isfinite(s3.pose))
    assert np.linalg.norm(s3.pose[:2, 3]) < 0.05  # a static scene: no motion


def test_all_frames_empty_gives_a_held_trajectory():
    res = lidar_odometry([(0.1 * k, np.zeros((0, 3))) for k in range(5)])
    assert res.held.all()
    assert np.allclose(res.planar, 0.0)


def test_bad_inputs_raise_clear_errors():
    lo = LidarOdometry()
    with pytest.raises(InputError, match=r"\(N, 3\) or \(N, 2\)"):
        lo.register(np.zeros((10, 4)), 0.0)
    lo.register(_ring(), 1.0)
    with pytest.raises(InputError, match="not after the previous"):
        lo.register(_ring(), 1.0)
    with pytest.raises(InputError, match="2D but the earlier frames were 3D"):
        lo.register(_ring()[:, :2], 2.0)
    with pytest.raises(InputError, match="no frames"):
        lidar_odometry([])
    with pytest.raises(ConfigError, match="min_range < max_range"):
        LidarOdometryConfig(max_range=1.0, min_range=2.0)
    with pytest.raises(ConfigError, match="min_points"):
        LidarOdometryConfig(min_points=2)


def test_fusion_needs_a_speed_source(drive2d):
    _, imu = drive2d
    from stemmap.io.imu import InertialLog

    gyro_only = InertialLog(
        imu.log.times, imu.log.gyro, imu.log.accel, np.full(len(imu.log), np.nan)
    )
    with pytest.raises(InputError, match="nothing measures speed"):
        fuse_front_ends(inertial=gyro_only)
    with pytest.raises(InputError, match="no source"):
        fuse_front_ends()
