import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.sim import (
    OdometryNoise,
    Stand,
    VisualOdometryNoise,
    clear_corridor,
    compose_poses,
    integrate_unicycle,
    lawnmower_path,
    loop_path,
    random_stand,
    relative_poses,
    s_curve_path,
    simulate_run,
    straight_path,
)
from stemmap.sim.drive import simulate_s_curve_drive
from stemmap.types import Pose2, Trajectory


@pytest.fixture(scope="module")
def stand() -> Stand:
    return random_stand(50, (30.0, 30.0), min_spacing=1.5, rng=7)


@pytest.fixture(scope="module")
def loop_run(stand):
    return simulate_run(
        stand,
        loop_path((15.0, 15.0), (9.0, 6.0)),
        scanner="sick_lms",
        speed=1.5,
        rate_hz=10.0,
        odometry_noise="forest",
        corridor_half_width=1.0,
        rng=11,
    )


def test_run_shapes_and_frames(loop_run):
    s = len(loop_run)
    assert s > 100
    n = loop_run.scanner.n_beams
    assert loop_run.scans.ranges.shape == (s, n) == loop_run.hit_ids.shape == loop_run.mixed.shape
    assert loop_run.true_poses.poses.shape == (s, 3)
    np.testing.assert_array_equal(loop_run.true_poses.times, loop_run.scans.times)
    m = len(loop_run.odometry)
    assert loop_run.true_path.poses.shape == (m, 3) and loop_run.slipping.shape == (m,)
    assert len(loop_run.visual_odometry) == s - 1
    assert loop_run.params["n_scans"] == s
    # odometry at 50 Hz, scans at 10 Hz
    assert np.allclose(np.diff(loop_run.odometry.times), 0.02)
    assert np.allclose(np.diff(loop_run.scans.times), 0.1)


def test_loop_closes_and_follows_the_path(loop_run):
    start, end = loop_run.true_path.poses[0], loop_run.true_path.poses[-1]
    # the controller stops within one odometry step (1.5 m/s * 0.02 s = 3 cm) of the goal,
    # plus the resampling step of the path (5 cm)
    assert math.hypot(*(end[:2] - start[:2])) < 0.1
    # pure pursuit with 2 m lookahead on a 9 x 6 m ellipse cuts corners by at most ~0.3 m
    wp = loop_path((15.0, 15.0), (9.0, 6.0), n_points=2000)
    d = np.min(np.hypot(*(loop_run.true_path.xy[:, None, :] - wp[None]).transpose(2, 0, 1)), axis=1)
    assert d.max() < 0.35


def test_true_odometry_integrates_to_truth(loop_run):
    dr = loop_run.true_odometry.integrate(loop_run.true_path.poses[0])
    # exact arc integration: only float rounding accumulates over ~2,000 steps
    np.testing.assert_allclose(dr.poses[:, :2], loop_run.true_path.poses[:, :2], atol=1e-9)


def test_scan_poses_lie_on_the_true_path(loop_run):
    interp = loop_run.true_path.interpolate(loop_run.true_poses.times)
    # linear interpolation between 50 Hz samples vs the exact arc: chord sagitta << 1 mm
    np.testing.assert_allclose(loop_run.true_poses.poses[:, :2], interp[:, :2], atol=1e-4)


def test_scans_see_trees_with_ground_truth(loop_run):
    hit = loop_run.hit_ids
    valid = np.isfinite(loop_run.scans.ranges)
    assert np.all(hit[~valid] == -1)
    assert np.all(hit[valid] != -1)
    assert np.unique(hit[hit >= 0]).size > 0.5 * loop_run.stand.n_trees


def test_noisy_odometry_statistics(stand):
    noise = OdometryNoise(
        speed_scale=1.05, speed_noise=0.1, yaw_rate_bias=0.01, yaw_rate_noise=0.02
    )
    run = simulate_run(
        stand, straight_path((1.0, 1.0), (29.0, 25.0)), speed=1.0, odometry_noise=noise, rng=3
    )
    dv = run.odometry.speed - 1.05 * run.true_odometry.speed
    dw = run.odometry.yaw_rate - run.true_odometry.yaw_rate
    n = dv.size
    # mean of n samples of sigma 0.1 -> 4 sigma bound 0.4 / sqrt(n)
    assert abs(dv.mean()) < 4 * 0.1 / math.sqrt(n)
    assert abs(dv.std() / 0.1 - 1) < 4 / math.sqrt(2 * n)
    assert abs(dw.mean() - 0.01) < 4 * 0.02 / math.sqrt(n)
    assert abs(dw.std() / 0.02 - 1) < 4 / math.sqrt(2 * n)


def test_wheel_slip_inflates_measured_speed(stand):
    noise = OdometryNoise(slip_rate=0.5, slip_duration=1.0, slip_excess=0.5)
    run = simulate_run(stand, straight_path((1.0, 1.0), (29.0, 25.0)), odometry_noise=noise, rng=4)
    s = run.slipping
    assert 0 < s.sum() < s.size
    np.testing.assert_allclose(run.odometry.speed[s], 1.5 * run.true_odometry.speed[s])
    np.testing.assert_allclose(run.odometry.speed[~s], run.true_odometry.speed[~s])


def test_visual_odometry_is_unbiased_with_declared_covariance(loop_run):
    vo = loop_run.visual_odometry
    v = loop_run.vehicle_poses.poses
    truth = relative_poses(v[:-1], v[1:])
    err = vo.increments - truth
    err[:, 2] = (err[:, 2] + np.pi) % (2 * np.pi) - np.pi
    z = err / np.sqrt(np.diagonal(vo.covs, axis1=1, axis2=2))
    n = z.shape[0]
    # standardised residuals ~ N(0, 1): mean within 4/sqrt(n), std within 4/sqrt(2n)
    assert np.all(np.abs(z.mean(axis=0)) < 4 / math.sqrt(n))
    assert np.all(np.abs(z.std(axis=0) - 1) < 4 / math.sqrt(2 * n))


def test_vo_dropout_marks_missing_increments(stand):
    run = simulate_run(
        stand,
        straight_path((1.0, 1.0), (29.0, 25.0)),
        vo_noise=VisualOdometryNoise(dropout=0.2),
        rng=5,
    )
    missing = np.isnan(run.visual_odometry.increments).any(axis=1)
    assert 0.1 < missing.mean() < 0.3


def test_same_seed_same_run_different_seed_differs(stand):
    path = straight_path((1.0, 1.0), (20.0, 20.0))
    a = simulate_run(stand, path, rng=9, max_scans=50)
    b = simulate_run(stand, path, rng=9, max_scans=50)
    c = simulate_run(stand, path, rng=10, max_scans=50)
    np.testing.assert_array_equal(a.scans.ranges, b.scans.ranges)
    np.testing.assert_array_equal(a.odometry.speed, b.odometry.speed)
    assert not np.array_equal(a.odometry.speed, c.odometry.speed)
    assert len(a) == 50


def test_sensor_offset_is_applied(stand):
    off = Pose2(0.5, 0.1, 0.2)
    run = simulate_run(stand, straight_path((1.0, 1.0), (20.0, 20.0)), sensor_offset=off, rng=1)
    expect = compose_poses(run.vehicle_poses.poses, off.as_array())
    np.testing.assert_allclose(run.true_poses.poses, expect, atol=1e-12)


def test_explicit_trajectory_input(stand):
    t = np.linspace(0.0, 10.0, 11)
    poses = np.column_stack((1.0 + t, 2.0 + 0.5 * t, np.full(t.size, math.atan2(0.5, 1.0))))
    run = simulate_run(stand, Trajectory(t, poses), rate_hz=5.0, rng=2)
    assert len(run) == 51
    # straight constant-velocity input: controls recover speed |(1, 0.5)| and zero yaw rate
    np.testing.assert_allclose(run.true_odometry.speed, math.hypot(1.0, 0.5), rtol=1e-9)
    np.testing.assert_allclose(run.true_path.poses[-1, :2], poses[-1, :2], atol=1e-6)


def test_lawnmower_path_covers_strips():
    wp = lawnmower_path((0.0, 0.0, 30.0, 20.0), 4.0, margin=2.0)
    ys = np.unique(np.round(wp[:, 1], 6))
    assert wp[:, 0].min() >= 2.0 - 1e-9 and wp[:, 0].max() <= 28.0 + 1e-9
    assert {2.0, 6.0, 10.0, 14.0, 18.0} <= set(ys.tolist())


def test_s_curve_path_is_a_centred_sine():
    wp = s_curve_path((50.0, 30.0), amplitude=4.0, length_scale=6.0, n_points=9)
    np.testing.assert_allclose(wp[:, 0], np.linspace(5.0, 45.0, 9))
    np.testing.assert_allclose(wp[:, 1], 15.0 + 4.0 * np.sin(wp[:, 0] / 6.0))
    with pytest.raises(ConfigError, match="amplitude"):
        s_curve_path((50.0, 30.0), amplitude=15.0, length_scale=6.0, n_points=9)
    with pytest.raises(ConfigError, match="n_points"):
        s_curve_path((50.0, 30.0), amplitude=4.0, length_scale=6.0, n_points=1)
    with pytest.raises(ConfigError, match="margin"):
        s_curve_path((8.0, 30.0), amplitude=4.0, length_scale=6.0, n_points=9)


def test_s_curve_drive_is_an_s_and_reproducible():
    kw = {"amplitude": 4.0, "length_scale": 6.0, "n_waypoints": 12, "max_scans": 100}
    run, imu = simulate_s_curve_drive(40, (50.0, 30.0), seed=5, **kw)
    again, imu2 = simulate_s_curve_drive(40, (50.0, 30.0), seed=5, **kw)
    other, imu3 = simulate_s_curve_drive(40, (50.0, 30.0), seed=6, **kw)
    assert len(run) == 100
    np.testing.assert_array_equal(run.scans.ranges, again.scans.ranges)
    np.testing.assert_array_equal(run.stand.trees_xy, again.stand.trees_xy)
    np.testing.assert_array_equal(imu.log.gyro, imu2.log.gyro)
    assert not np.array_equal(run.stand.trees_xy, other.stand.trees_xy)
    assert not np.array_equal(imu.log.gyro, imu3.log.gyro)
    # an S: the heading swings both ways by more than 15 degrees, the yaw rate changes sign
    th = np.unwrap(run.true_poses.poses[:, 2])
    assert th.max() > math.radians(15) and th.min() < -math.radians(15)
    assert run.true_odometry.yaw_rate.max() > 0.1 and run.true_odometry.yaw_rate.min() < -0.1
    # the IMU samples the drive's true controls (100 Hz), the wheels at 50 Hz
    assert np.isfinite(imu.log.gyro[:, 2]).sum() == len(run.true_odometry)
    # no trunk inside the 2 m corridor the vehicle drove
    d = np.min(np.hypot(*(run.stand.trees_xy[:, None] - run.true_path.poses[None, :, :2]).T), 0)
    assert np.all(d - run.stand.radii > 2.0 - 0.3)


def test_clear_corridor_removes_trees_on_the_path():
    st = Stand([[5.0, 0.2], [5.0, 3.0]], [0.3, 0.3], bounds=(0, -5, 10, 5))
    out = clear_corridor(st, [[0.0, 0.0], [10.0, 0.0]], half_width=1.0)
    np.testing.assert_allclose(out.trees_xy, [[5.0, 3.0]])


def test_bad_inputs_raise(stand):
    with pytest.raises(InputError, match="waypoints"):
        simulate_run(stand, np.zeros((1, 2)))
    with pytest.raises(ConfigError, match="preset"):
        simulate_run(stand, straight_path((0, 0), (5, 5)), scanner="velodyne")
    with pytest.raises(ConfigError, match="odometry noise preset"):
        simulate_run(stand, straight_path((0, 0), (5, 5)), odometry_noise="bumpy")
    with pytest.raises(ConfigError):
        simulate_run(stand, straight_path((0, 0), (5, 5)), speed=0.0)
    with pytest.raises(ConfigError):
        OdometryNoise(speed_scale=0.0)


@settings(max_examples=40, deadline=None)
@given(
    v=st.lists(st.floats(-2, 2), min_size=1, max_size=20),
    w=st.floats(-1.5, 1.5),
    th=st.floats(-3.1, 3.1),
)
def test_unicycle_steps_compose(v, w, th):
    # integrating a sequence then taking relative poses gives back each single step's exact
    # arc: the integration is frame-independent and has no accumulated drift (1e-9 m)
    dt = 0.1
    ws = np.full(len(v), w)
    poses = integrate_unicycle([1.0, -2.0, th], v, ws, dt)
    inc = relative_poses(poses[:-1], poses[1:])
    for k in range(len(v)):
        single = integrate_unicycle([0.0, 0.0, 0.0], [v[k]], [w], dt)[1]
        np.testing.assert_allclose(inc[k], single, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(v=st.floats(0.1, 3.0), w=st.floats(0.05, 1.5), th=st.floats(-3.1, 3.1))
def test_unicycle_constant_controls_stay_on_the_circle(v, w, th):
    # constant (v, w): the path is a circle of radius v / w centred left of the start pose
    poses = integrate_unicycle([2.0, 3.0, th], np.full(50, v), np.full(50, w), 0.05)
    rad = v / w
    centre = np.array([2.0 - rad * np.sin(th), 3.0 + rad * np.cos(th)])
    np.testing.assert_allclose(np.hypot(*(poses[:, :2] - centre).T), rad, rtol=1e-9, atol=1e-9)


def test_clear_corridor_handles_clutter_and_truth_objects():
    from stemmap.sim import add_clutter

    st_ = add_clutter(
        random_stand(30, (30.0, 30.0), rng=12), n_bushes=6, n_walls=2, n_rocks=3, rng=13
    )
    path = np.array([[0.0, 15.0], [30.0, 15.0]])
    out = clear_corridor(st_, path, half_width=1.5)

    def dist(q):
        return np.abs(q[:, 1] - 15.0)  # the path is the line y = 15 across the stand

    assert np.all(dist(out.trees_xy) - out.radii > 1.5)
    assert np.all(dist(out.clutter_xy) - out.clutter_radius > 1.5)
    clutter_seg = out.segments[out.segment_owner < 0]
    crosses = (clutter_seg[:, 1] - 15.0) * (clutter_seg[:, 3] - 15.0) <= 0
    assert not crosses.any()  # no wall or rock edge left across the road
    assert np.all(dist(out.clutter_objects_xy) - out.clutter_objects_extent > 1.5)
    assert len(out.clutter_kinds) == out.clutter_objects_xy.shape[0]


def test_motion_skew_casts_each_beam_from_its_own_pose(stand):
    from stemmap.sim import cast_rays, scanner_preset

    model = scanner_preset("rplidar", range_noise_rel=0.0, dropout=0.0, beam_divergence=0.0)
    path = straight_path((2.0, 2.0), (28.0, 25.0))
    run = simulate_run(
        stand,
        path,
        scanner=model,
        speed=2.0,
        rate_hz=10.0,
        motion_skew=True,
        corridor_half_width=1.0,
        max_scans=20,
        rng=3,
    )
    dt_beam = run.params["beam_time_increment_s"]
    assert dt_beam == pytest.approx(math.radians(1.0) / (2 * math.pi * 10.0))
    close, total = 0, 0
    for k in (1, 4, 7, 10, 13, 16, 19):
        t_beam = run.scans.times[k] + dt_beam * np.arange(model.n_beams)
        poses = run.true_path.interpolate(t_beam)
        for i in range(0, model.n_beams, 2):
            r, _ = cast_rays(poses[i, :2], [poses[i, 2] + model.angles[i]], run.stand, 12.0)
            if np.isfinite(r[0]) and np.isfinite(run.scans.ranges[k, i]):
                total += 1
                # slices hold the pose of their middle beam: <= 2 m/s * 1.6 ms = 3 mm offset
                close += abs(r[0] - run.scans.ranges[k, i]) < 0.005
    assert total > 20 and close >= 0.95 * total
    # the scan time stays the first beam's time
    np.testing.assert_allclose(run.true_poses.times, run.scans.times)
