"""Stereo / RGB-D visual odometry (odometry/visual.py) on rendered orchard frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.odometry.visual import (
    StereoCalibration,
    VisualFrame,
    VisualOdometry,
    VisualOdometryConfig,
    VoStatus,
    planar_from_camera,
    run_visual_odometry,
    visual_odometry_source,
)


def _path_length(xy: np.ndarray) -> float:
    return float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))


def _run(drive, frames, cal, cfg=None):
    res = run_visual_odometry(frames, cal, cfg)
    est = planar_from_camera(res, drive.camera.vehicle_from_camera())
    return res, est


def test_stereo_drift_below_two_percent(drive):
    """The issue's target: drift <= 2 % of the distance. Measured 0.5 % end error on this 4.9 m
    drive (0.05 m). The bound is the target itself, not the measurement: 2 % is what the
    EKF and the tree database are designed around."""
    frames = [VisualFrame(f.time, f.left, f.right) for f in drive.frames]
    res, est = _run(drive, frames, drive.stereo)
    truth = drive.truth_in_start_frame()
    dist = _path_length(truth)
    err = np.hypot(*(est.poses[:, :2] - truth).T)
    assert res.ok.all()
    assert err[-1] < 0.02 * dist
    assert err.max() < 0.02 * dist + 0.02
    # heading: the S-curve turns by ~8 deg; the estimate follows within 1 deg
    dth = est.poses[:, 2] - (drive.truth.poses[:, 2] - drive.truth.poses[0, 2])
    assert np.max(np.abs(dth)) < math.radians(1.0)
    # PnP RANSAC worked on many points, and keyframes were re-made along the way
    assert np.median(res.n_inliers[1:]) > 60
    assert 2 <= np.sum(res.status == VoStatus.KEYFRAME) < len(res) // 2


def test_rgbd_mode_on_true_depth(drive):
    """The RGB-D path (depth image instead of the right image) on the true depth of the same
    frames. Measured 2.1 % end error: worse than stereo because corners on occlusion
    boundaries (leaf spheres against the sky and each other) get a depth without a stereo
    consistency check; 4 % bounds it with margin."""
    frames = [VisualFrame(f.time, f.left, depth=f.depth) for f in drive.frames]
    res, est = _run(drive, frames, drive.rgbd)
    truth = drive.truth_in_start_frame()
    assert res.ok.all()
    assert np.hypot(*(est.poses[-1, :2] - truth[-1])) < 0.04 * _path_length(truth)


def test_tracking_survives_blank_frames_and_recovers(drive):
    """Three black frames mid-drive: no exception; they are LOST / NO_KEYFRAME with poses
    extrapolated at constant velocity; tracking resumes; the end error stays within 3 % (the
    extrapolation over 0.3 s of a near-constant 1 m/s motion adds a few cm)."""
    frames = []
    for k, f in enumerate(drive.frames):
        if 20 <= k < 23:
            blank = np.zeros_like(f.left)
            frames.append(VisualFrame(f.time, blank, blank))
        else:
            frames.append(VisualFrame(f.time, f.left, f.right))
    res, est = _run(drive, frames, drive.stereo)
    st = res.status
    assert set(st[20:23].tolist()) <= {VoStatus.LOST, VoStatus.NO_KEYFRAME}
    assert st[23] == VoStatus.LOST  # recovery: extrapolated pose, new keyframe
    assert np.all(np.isin(st[24:], (VoStatus.TRACKED, VoStatus.KEYFRAME)))
    assert not res.ok[20:24].any() and res.ok[24:].all()
    assert np.all(np.isfinite(res.poses))
    truth = drive.truth_in_start_frame()
    assert np.hypot(*(est.poses[-1, :2] - truth[-1])) < 0.03 * _path_length(truth)
    # the fusion source drops the intervals touching an extrapolated pose (20..23 and 23->24)
    src = visual_odometry_source(
        res, drive.camera.vehicle_from_camera(), sigma_speed=0.04, sigma_yaw_rate=0.01
    )
    assert len(src) == len(res) - 1 - 5


def test_outliers_from_a_sticker_on_the_lens_are_rejected(drive):
    """A textured patch fixed in the image (dirt on the lens, with a 12 px stereo disparity, so
    it triangulates as an object 1.6 m ahead that moves with the camera). Its corners track
    perfectly and pass the forward-backward check; only PnP RANSAC can reject them. Without the
    rejection the estimate would be dragged towards standing still."""
    rng = np.random.default_rng(3)
    patch = rng.integers(0, 255, (40, 60, 1)).repeat(3, axis=2).astype(np.uint8)
    frames = []
    for f in drive.frames:
        left, right = f.left.copy(), f.right.copy()
        left[120:160, 200:260] = patch
        right[120:160, 188:248] = patch
        frames.append(VisualFrame(f.time, left, right))
    res, est = _run(drive, frames, drive.stereo)
    truth = drive.truth_in_start_frame()
    assert res.ok.all()
    assert np.hypot(*(est.poses[-1, :2] - truth[-1])) < 0.02 * _path_length(truth)
    tracked = res.status == VoStatus.TRACKED
    assert np.all(res.n_inliers[tracked] <= res.n_tracks[tracked])


def test_featureless_first_frames_do_not_crash():
    cal = StereoCalibration(100.0, 100.0, 63.5, 47.5, 128, 96, baseline=0.1)
    blank = np.zeros((96, 128), np.uint8)
    vo = VisualOdometry(cal)
    assert vo.process(VisualFrame(0.0, blank, blank)) == VoStatus.NO_KEYFRAME
    assert vo.process(VisualFrame(0.1, blank, blank)) == VoStatus.NO_KEYFRAME
    np.testing.assert_allclose(vo.pose, np.eye(4))


def test_bad_inputs_raise_clear_errors(drive):
    f = drive.frames[0]
    with pytest.raises(InputError, match="right image"):
        run_visual_odometry([VisualFrame(0.0, f.left)], drive.stereo)
    with pytest.raises(InputError, match="depth image"):
        run_visual_odometry([VisualFrame(0.0, f.left)], drive.rgbd)
    with pytest.raises(InputError, match="calibration says"):
        run_visual_odometry([VisualFrame(0.0, f.left[:-2], f.right[:-2])], drive.stereo)
    with pytest.raises(InputError, match="increase"):
        run_visual_odometry(
            [VisualFrame(1.0, f.left, f.right), VisualFrame(1.0, f.left, f.right)], drive.stereo
        )
    with pytest.raises(InputError, match="no frames"):
        run_visual_odometry([], drive.stereo)
    with pytest.raises(ConfigError):
        VisualOdometryConfig(min_inliers=3)
    with pytest.raises(ConfigError):
        StereoCalibration(0.0, 1.0, 0.0, 0.0, 10, 10)


def test_planar_from_camera_recovers_the_vehicle_path(drive):
    """Feeding the true camera poses gives back the true vehicle path (mount round trip)."""
    from stemmap.odometry.visual import VisualOdometryResult

    n = len(drive.frames)
    res = VisualOdometryResult(
        drive.truth.times,
        np.array([f.world_from_camera for f in drive.frames]),
        np.full(n, int(VoStatus.TRACKED)),
        np.zeros(n, np.int64),
        np.zeros(n, np.int64),
    )
    est = planar_from_camera(res, drive.camera.vehicle_from_camera())
    np.testing.assert_allclose(est.poses[:, :2], drive.truth_in_start_frame(), atol=1e-9)
    np.testing.assert_allclose(
        est.poses[:, 2], drive.truth.poses[:, 2] - drive.truth.poses[0, 2], atol=1e-9
    )


def test_source_noise_scales_with_the_inlier_count():
    """``inlier_exponent``: each interval's noise is ``sigma (n / n_ref) ** -p`` with ``n`` the
    fewer PnP inliers of its two frames; the first keyframe (no PnP, 0 inliers) does not limit
    its interval, and ``p = 0`` keeps the constant."""
    from stemmap.odometry.visual import VisualOdometryResult

    n = 4
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 2, 3] = 0.1 * np.arange(n)  # camera z = forward
    res = VisualOdometryResult(
        np.arange(n) * 0.2,
        poses,
        np.array([VoStatus.KEYFRAME, VoStatus.TRACKED, VoStatus.TRACKED, VoStatus.KEYFRAME]),
        np.array([0, 220, 60, 130]),
        np.array([0, 200, 50, 120]),
    )
    vfc = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    src = visual_odometry_source(
        res, vfc, sigma_speed=0.05, sigma_yaw_rate=0.01, inlier_exponent=2.0
    )
    expect = (np.array([200.0, 50.0, 50.0]) / 100.0) ** -2.0
    assert np.allclose(src.sigma_speed, 0.05 * expect)
    assert np.allclose(src.sigma_yaw_rate, 0.01 * expect)
    assert np.allclose(src.speed, 0.5)
    const = visual_odometry_source(res, vfc, sigma_speed=0.05, sigma_yaw_rate=0.01)
    assert np.allclose(const.sigma_speed, 0.05)
    with pytest.raises(ConfigError):
        visual_odometry_source(res, vfc, sigma_speed=0.05, sigma_yaw_rate=0.01, inlier_exponent=-1)


@pytest.mark.parametrize("mode", ["stereo", "rgbd"])
def test_keyframe_points_have_the_true_depth(drive, mode):
    """Triangulation itself (stereo disparity, or the depth image): keyframe 3D points made at
    frames 0, 10 and 25 against the renderer's true depth at their (rounded) pixels. Measured:
    stereo median z / z_true 1.012-1.018 per frame (quartiles 0.96-1.07: 0.1 px of disparity
    is 2.6 % at 4.5 m), RGB-D exactly 1 (bilinear on the true depth, 85-134 points). A 5 %
    baseline or depth-scale error fails here; the RGB-D drive test above does not see the
    latter (that path is 2.2 % short, and 5 % longer depths make it 2.7 % long). Every point
    back-projects to its pixel."""
    ratios = []
    for k in (0, 10, 25):
        f = drive.frames[k]
        if mode == "stereo":
            cal, frame = drive.stereo, VisualFrame(f.time, f.left, f.right)
        else:
            cal, frame = drive.rgbd, VisualFrame(f.time, f.left, depth=f.depth)
        vo = VisualOdometry(cal)
        assert vo.process(frame) == VoStatus.KEYFRAME
        pts, uv = vo._kf_pts, vo._uv  # the keyframe's points (no public accessor)
        assert pts.shape[0] >= 80
        iu, iv = np.rint(uv).astype(int).T
        z_true = f.depth[iv, iu]
        ok = np.isfinite(z_true)
        ratios.append(pts[ok, 2] / z_true[ok])
        np.testing.assert_allclose(pts[:, 0] / pts[:, 2] * cal.fx + cal.cx, uv[:, 0], atol=1e-3)
        np.testing.assert_allclose(pts[:, 1] / pts[:, 2] * cal.fy + cal.cy, uv[:, 1], atol=1e-3)
    r = np.concatenate(ratios)
    if mode == "stereo":
        assert abs(np.median(r) - 1.0) < 0.03
        assert np.median(np.abs(r - 1.0)) < 0.08
    else:
        assert np.median(np.abs(r - 1.0)) < 1e-3


def test_distance_is_not_short_at_40_hz():
    """At 40 Hz (2.5 cm per frame, image steps mostly under 1.5 px) the distance is not short.

    Tracking frame to frame chained each step's KLT shortfall (steps 4-5 % short, more under
    0.5 px) into the tracks: the reported distance was 3 % short at 40 Hz against 0.4 % at
    5 Hz (docs/algorithms/visual-odometry.md, "Distance shortfall at high frame rates"). Tracked
    from the keyframe image, on the first 2 m of the benchmark's S-curve (81 frames, 9 stands
    jittered by seed): distance -0.02 % mean, sd 0.45 %, worst -0.93 %; chained from the previous
    image -3.7 %, sd 1.1 %, every stand below -1.8 %. The 1.5 % bound is 3 sd of the fixed code
    and fails the chained tracking on all 9 stands (here stand 0: -0.55 % against -4.3 %)."""
    from stemmap.eval.trajectory import path_length
    from stemmap.sim.forest import row_stand
    from stemmap.sim.render import StereoCamera, iter_stereo, stand3d_from_stand
    from stemmap.types import Trajectory

    cam = StereoCamera(rate_hz=40.0)
    t = np.arange(81) / 40.0
    x = -2.0 + t
    truth = Trajectory(
        t,
        np.column_stack((x, 2.0 + 0.3 * np.sin(x / 4.0), np.arctan2(0.075 * np.cos(x / 4.0), 1.0))),
        frame="world",
    )
    stand = stand3d_from_stand(row_stand(3, 10, row_spacing=4.0, tree_spacing=3.0, rng=1), rng=2)
    k = cam.K
    cal = StereoCalibration(cam.fx, cam.fx, k[0, 2], k[1, 2], cam.width, cam.height, baseline=0.12)
    frames = (VisualFrame(f.time, f.left, f.right) for f in iter_stereo(stand, truth, cam, rng=0))
    res = run_visual_odometry(frames, cal)
    est = planar_from_camera(res, cam.vehicle_from_camera())
    assert res.ok.all()
    ratio = path_length(est) / path_length(truth, min_step=0.0)
    assert abs(ratio - 1.0) < 0.015, ratio
