"""``LidarOdometryResult.drift_xy_variance``: a random walk in distance, not in frames
(docs/algorithms/odometry.md "Drift estimate")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.odometry.lidar import LidarOdometryConfig, LidarOdometryResult


def _straight(n: int, length: float, cov_xy: float = 0.02**2) -> LidarOdometryResult:
    """``n`` frames along ``length`` metres of x, every increment with the floor covariance."""
    planar = np.zeros((n, 3))
    planar[:, 0] = np.linspace(0.0, length, n)
    cov = np.tile(np.diag([cov_xy, cov_xy, math.radians(0.1) ** 2]), (n, 1, 1))
    cov[0] = np.nan
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = planar[:, 0]
    status = np.array(["first"] + ["ok"] * (n - 1))
    return LidarOdometryResult(
        np.arange(n) / 10.0, poses, planar, cov, np.full(n, 100), status, LidarOdometryConfig()
    )


def test_independent_of_the_frame_rate() -> None:
    """30 m at 10 and at 75 frames per metre: the same variance, k² * 30 m (0.18 % of 30 m at
    k = 1 cm/sqrt(m)); the old per-frame sum differed by sqrt(7.5) in sigma."""
    k = LidarOdometryConfig().drift_xy_per_sqrt_m
    for n in (301, 2251):
        assert _straight(n, 30.0).drift_xy_variance(30.0) == pytest.approx(k**2 * 30.0)


def test_poorly_constrained_frames_raise_it() -> None:
    """A stretch whose covariance is 4x the floor's weighs 4x: half the path at 4x -> 2.5x."""
    res = _straight(101, 10.0)
    res.increment_cov[51:, :2, :2] *= 4.0
    base = _straight(101, 10.0).drift_xy_variance(10.0)
    assert res.drift_xy_variance(10.0) == pytest.approx(2.5 * base)


def test_held_frames_and_short_runs() -> None:
    res = _straight(11, 1.0)
    res.increment_cov[5] = np.nan  # a held frame weighs 1
    k2 = LidarOdometryConfig().drift_xy_per_sqrt_m ** 2
    assert res.drift_xy_variance(1.0) == pytest.approx(k2)
    assert _straight(1, 0.0).drift_xy_variance(0.0) == 0.0
    with pytest.raises(ConfigError):
        LidarOdometryConfig(drift_xy_per_sqrt_m=0.0)
