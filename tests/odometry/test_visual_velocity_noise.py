"""The EKF's visual odometry noise (odometry.visual.visual_velocity_sigma) against the VO's
frame-to-frame errors on the rendered S-curve drive at three camera rates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.odometry.fusion import velocities_from_poses
from stemmap.odometry.visual import (
    VISUAL_STEP_RATE_HZ,
    VISUAL_STEP_SIGMA,
    VisualFrame,
    planar_from_camera,
    run_visual_odometry,
    visual_velocity_sigma,
)
from stemmap.types import Trajectory


def test_velocity_noise_is_white_in_time():
    """One step at VISUAL_STEP_RATE_HZ has the error VISUAL_STEP_SIGMA; the variance added per
    second (sigma_v^2 dt) is the same at every frame interval."""
    dt0 = 1.0 / VISUAL_STEP_RATE_HZ
    sv, sw = visual_velocity_sigma(dt0)
    assert sv * dt0 == pytest.approx(VISUAL_STEP_SIGMA[0])
    assert sw * dt0 == pytest.approx(VISUAL_STEP_SIGMA[1])
    for dt in (0.01, 0.025, 0.2, 1.0):
        v, w = visual_velocity_sigma(dt)
        assert v**2 * dt == pytest.approx(sv**2 * dt0)
        assert w**2 * dt == pytest.approx(sw**2 * dt0)
    for bad in (0.0, -0.1, math.inf, math.nan):
        with pytest.raises(ConfigError):
            visual_velocity_sigma(bad)


def _z2(drive, stride: int) -> float:
    """Mean z^2 per degree of freedom (speed, yaw rate) of the VO's velocity errors on every
    ``stride``-th frame of the drive under :func:`visual_velocity_sigma`."""
    frames = drive.frames[::stride]
    res = run_visual_odometry([VisualFrame(f.time, f.left, f.right) for f in frames], drive.stereo)
    est = planar_from_camera(res, drive.camera.vehicle_from_camera())
    xy = drive.truth_in_start_frame()[::stride]
    th = drive.truth.poses[::stride, 2] - drive.truth.poses[0, 2]
    truth = Trajectory(est.times, np.column_stack((xy, th)))
    a = velocities_from_poses(est, sigma_speed=1.0, sigma_yaw_rate=1.0)
    b = velocities_from_poses(truth, sigma_speed=1.0, sigma_yaw_rate=1.0)
    ok = res.ok[1:] & res.ok[:-1]
    sv, sw = visual_velocity_sigma(0.1 * stride)
    zv = np.mean(((a.speed - b.speed)[ok] / sv) ** 2)
    zw = np.mean(((a.yaw_rate - b.yaw_rate)[ok] / sw) ** 2)
    return 0.5 * float(zv + zw)


def test_velocity_noise_is_calibrated_at_three_camera_rates(drive):
    """The 10 Hz drive and every 2nd and 3rd of its frames (5 and 3.3 Hz): z^2 measured 0.65,
    0.57 and 1.03. The noise was fitted on the benchmark's 10 m drives (seed 0's first 4.9 m
    are this drive), so this checks the form, not a held-out value. Bounds: within 3x of 1
    at each rate (16-49 intervals per rate: a chi-square mean of so few, heavy-tailed steps
    varies by ~2x) and within 2.5x of each other; the noise until Dec 4 (one 10 Hz step's
    error at every rate) measured 0.65, 1.16 and 3.07 here: 4.8x apart."""
    z = [_z2(drive, s) for s in (1, 2, 3)]
    assert all(1 / 3 < v < 3 for v in z), z
    assert max(z) / min(z) < 2.5, z
