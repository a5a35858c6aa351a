"""IMU / wheel simulation, the IMU CSV, the frame readers, pose-source fusion and the
``stemmap odometry`` command."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from stemmap.cli import app
from stemmap.errors import ConfigError, InputError
from stemmap.io.imu import InertialLog, read_imu_csv, write_imu_csv
from stemmap.io.lidar_frames import open_frames
from stemmap.io.scans import write_scans_npz
from stemmap.io.trajectory import read_trajectory_csv, read_trajectory_tum
from stemmap.odometry.fusion import PoseSource, fuse_sources
from stemmap.odometry.inertial import motion_prior
from stemmap.sim.drive import simulate_s_curve_drive
from stemmap.sim.imu import IMU_PRESETS, ImuNoise, simulate_imu
from stemmap.sim.motion_sensors import Odometry


def _controls(duration: float = 60.0, rate: float = 100.0) -> Odometry:
    t = np.arange(0.0, duration, 1.0 / rate)
    return Odometry(t, 3.0 + 0.5 * np.sin(t / 5.0), 0.2 * np.sin(t / 7.0))


def test_imu_sim_reproduces_its_error_model():
    truth = _controls()
    noise = ImuNoise(gyro_bias_walk=0.0, slip_rate=0.0)
    sim = simulate_imu(truth, noise=noise, rng=1)
    log = sim.log
    imu_rows = np.isfinite(log.gyro[:, 2])
    wheel_rows = np.isfinite(log.wheel_speed)
    assert imu_rows.sum() == len(truth)
    assert abs(wheel_rows.sum() - 50 * 60) <= 1
    # gyro: truth + constant bias + white noise
    err = log.gyro[imu_rows, 2] - truth.yaw_rate
    assert abs(err.mean() - noise.gyro_bias) < 4 * noise.gyro_noise / math.sqrt(err.size)
    assert err.std() == pytest.approx(noise.gyro_noise, rel=0.05)
    # accelerometer: gravity on z, centripetal v w on y (+ bias)
    acc = log.accel[imu_rows]
    assert acc[:, 2].mean() == pytest.approx(9.81 + noise.accel_bias, abs=0.005)
    assert np.mean(acc[:, 1] - truth.speed * truth.yaw_rate) == pytest.approx(
        noise.accel_bias, abs=0.005
    )
    # wheel: 2 % scale error
    k = np.clip(np.searchsorted(truth.times, log.times[wheel_rows], side="right") - 1, 0, None)
    ratio = log.wheel_speed[wheel_rows].sum() / truth.speed[k].sum()
    assert ratio == pytest.approx(noise.wheel_scale, abs=0.002)


def test_imu_sim_slips_and_presets():
    truth = _controls()
    sim = simulate_imu(truth, noise="mems", rng=2)
    assert sim.slipping.any() and not sim.slipping.all()
    perfect = simulate_imu(truth, noise="none", rng=2)
    rows = np.isfinite(perfect.log.gyro[:, 2])
    assert np.allclose(perfect.log.gyro[rows, 2], truth.yaw_rate)
    assert set(IMU_PRESETS) >= {"none", "xsens", "mems"}
    with pytest.raises(ConfigError, match="unknown IMU noise preset"):
        simulate_imu(truth, noise="nope")
    with pytest.raises(ConfigError, match="gyro_noise"):
        ImuNoise(gyro_noise=-1.0)


def test_imu_csv_round_trip(tmp_path):
    log = simulate_imu(_controls(5.0), rng=3).log
    p = tmp_path / "imu.csv"
    write_imu_csv(p, log)
    back = read_imu_csv(p)
    assert np.array_equal(back.times, log.times)
    for name in ("gyro", "accel", "wheel_speed"):
        a, b = getattr(back, name), getattr(log, name)
        assert np.array_equal(np.isnan(a), np.isnan(b))
        assert np.allclose(a[np.isfinite(a)], b[np.isfinite(b)])


def test_imu_csv_minimal_and_bad(tmp_path):
    p = tmp_path / "gyro.csv"
    p.write_text("# a gyro only\ntime_s,gyro_z\n0.0,0.1\n0.01,0.1\n")
    log = read_imu_csv(p)
    assert log.has_gyro and not log.has_wheel
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,gyro_z\n0.0,0.1\n0.0,0.1\n")
    with pytest.raises(InputError, match="does not increase"):
        read_imu_csv(bad)
    none = tmp_path / "none.csv"
    none.write_text("time_s,accel_x\n0.0,0.1\n")
    with pytest.raises(InputError, match="neither a gyro_z nor a wheel_speed"):
        read_imu_csv(none)
    with pytest.raises(InputError, match=r"does not exist|not found|missing"):
        read_imu_csv(tmp_path / "absent.csv")


def test_motion_prior_integrates_gyro_and_wheel():
    t = np.arange(0.0, 2.0, 0.01)
    log = InertialLog(
        t, np.column_stack((0 * t, 0 * t, np.full(t.size, 0.5))), np.zeros((t.size, 3)), 2 + 0 * t
    )
    prior = motion_prior(log)
    assert prior is not None
    d = prior(0.5, 1.5)  # 1 s at 2 m/s turning 0.5 rad/s: an arc
    assert d[2] == pytest.approx(0.5, abs=1e-9)
    chord = 2.0 * (2.0 / 0.5) * math.sin(0.25)  # 2 R sin(dtheta / 2)
    assert np.hypot(d[0], d[1]) == pytest.approx(chord, rel=1e-3)
    assert np.all(np.isnan(prior(1.5, 5.0)))  # outside the log
    no_wheel = InertialLog(t, log.gyro, log.accel, np.full(t.size, np.nan))
    assert motion_prior(no_wheel) is None


def test_pose_source_anchors_the_filter():
    """A pose source alone reproduces its poses; with a biased speed source the pose updates
    win (they are the frame)."""
    t = np.arange(0.0, 10.0, 0.1)
    poses = np.column_stack((2.0 * t, np.zeros_like(t), np.zeros_like(t)))
    cov = np.broadcast_to(np.diag([1e-4, 1e-4, 1e-6]), (t.size, 3, 3))
    ps = PoseSource(t, poses, cov, name="lidar")
    fused = fuse_sources([], poses=[ps])
    assert np.allclose(fused.trajectory.poses[-1], poses[-1], atol=0.02)
    from stemmap.odometry.fusion import OdometrySource

    wheel = OdometrySource(t, np.full(t.size, 2.2), np.full(t.size, np.nan), 0.1, 1.0, "wheel")
    both = fuse_sources([wheel], poses=[ps], speed_scale=[True])
    assert np.allclose(both.trajectory.poses[-1, :2], poses[-1, :2], atol=0.05)
    assert both.calibration[0] == pytest.approx(0.1, abs=0.03)  # wheel reads 10 % fast
    with pytest.raises(InputError, match="at least one sample"):
        fuse_sources([])


# ---- frames and the command -----------------------------------------------------------


@pytest.fixture(scope="module")
def scan_drive(tmp_path_factory):
    run, imu = simulate_s_curve_drive(
        60, (60.0, 40.0), amplitude=5.0, length_scale=10.0, n_waypoints=8, max_scans=120, seed=3
    )
    d = tmp_path_factory.mktemp("odo")
    write_scans_npz(d / "scans.npz", run.scans)
    write_imu_csv(d / "imu.csv", imu.log)
    return run, d


def _end_error(traj, run) -> float:
    """Position error at the last pose, in the first pose's frame (the command starts at 0)."""
    from stemmap.sim.unicycle import relative_poses

    truth = relative_poses(run.true_poses.poses[0], run.true_poses.poses[: len(traj)])
    return float(np.hypot(*(traj.poses[-1, :2] - truth[-1, :2])))


def test_cli_odometry_2d_scans_with_imu(scan_drive, tmp_path):
    run, d = scan_drive
    out = tmp_path / "traj.csv"
    res = CliRunner().invoke(
        app,
        [
            "odometry",
            str(d / "scans.npz"),
            "--imu",
            str(d / "imu.csv"),
            "--max-range",
            "80",
            "--min-range",
            "0.1",
            "--out",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    traj = read_trajectory_csv(out)
    assert len(traj) == len(run.scans)
    dist = float(np.sum(np.hypot(*np.diff(run.true_poses.poses[:, :2], axis=0).T)))
    assert _end_error(traj, run) < 0.01 * dist
    assert "calibration" in res.output
    assert (tmp_path / "traj.csv.run.json").is_file()


def test_cli_odometry_cloud_folder(scan_drive, tmp_path):
    """A folder of per-frame .xyz clouds named by their time, lidar only, TUM output."""
    run, _ = scan_drive
    folder = tmp_path / "frames"
    folder.mkdir()
    for scan in list(run.scans)[:60]:
        p = scan.points()
        xyz = np.column_stack((p, np.zeros(len(p))))
        np.savetxt(folder / f"{scan.time:.3f}.xyz", xyz)
    seq = open_frames(folder)
    assert len(seq) == 60 and seq.kind == "folder"
    out = tmp_path / "traj.tum"
    res = CliRunner().invoke(
        app,
        [
            "odometry",
            str(folder),
            "--max-range",
            "80",
            "--min-range",
            "0.1",
            "-q",
            "--out",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    traj = read_trajectory_tum(out)
    assert len(traj) == 60
    assert _end_error(traj, run) < 0.1


def test_frames_timing_rules(tmp_path):
    folder = tmp_path / "f"
    folder.mkdir()
    for name in ("a.xyz", "b.xyz"):
        np.savetxt(folder / name, np.ones((5, 3)))
    with pytest.raises(InputError, match=r"times\.csv"):
        open_frames(folder)
    seq = open_frames(folder, rate_hz=10.0)
    assert [t for t, _ in seq.files] == [0.0, 0.1]
    (folder / "times.csv").write_text("file,time_s\nb.xyz,1.0\na.xyz,2.0\n")
    seq = open_frames(folder)
    assert [(t, f.name) for t, f in seq.files] == [(1.0, "b.xyz"), (2.0, "a.xyz")]
    (folder / "times.csv").write_text("file,time_s\nc.xyz,1.0\n")
    with pytest.raises(InputError, match="not in the folder"):
        open_frames(folder)
    with pytest.raises(InputError, match="do not exist"):
        open_frames(tmp_path / "nothing")
    with pytest.raises(InputError, match="cannot tell the scan format"):
        open_frames(Path(folder / "a.xyz"))


def test_cli_odometry_bad_input_is_one_error_line(tmp_path):
    res = CliRunner().invoke(
        app, ["odometry", str(tmp_path / "none"), "--out", str(tmp_path / "t.csv")]
    )
    assert res.exit_code == 2
    assert "error:" in res.output and "do not exist" in res.output


def test_cli_odometry_laserscan_bag(scan_drive, tmp_path):
    """A ROS1 bag with a LaserScan topic is read as 2D frames (lidar only)."""
    from stemmap.io.rosbag import write_scans_bag
    from stemmap.types import ScanBatch

    run, _ = scan_drive
    sc = run.scans
    batch = ScanBatch(sc.ranges[:40], sc.times[:40], sc.angle_min, sc.angle_increment, 0.0, 80.0)
    bag = write_scans_bag(tmp_path / "drive.bag", batch)
    seq = open_frames(bag)
    assert seq.kind == "bag" and seq.msgtype == "laserscan" and seq.topic == "/scan"
    out = tmp_path / "traj.csv"
    res = CliRunner().invoke(
        app,
        ["odometry", str(bag), "--max-range", "80", "--min-range", "0.1", "-q", "--out", str(out)],
    )
    assert res.exit_code == 0, res.output
    traj = read_trajectory_csv(out)
    assert len(traj) == 40
    assert _end_error(traj, run) < 0.1
