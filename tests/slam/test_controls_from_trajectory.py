"""Controls from a pose-output odometry that dead-reckon through every pose, lateral steps
included (:meth:`Controls.from_trajectory`; ``controls_from_trajectory(lateral="keep")``, the
motion input a pose odometry can give every back-end), and every back-end with no landmark
returns the odometry's own path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import BACKENDS, Controls, SlamProblem, TreeFrames, make_backend
from stemmap.slam.motion import compose, rollout
from stemmap.slam.munjer import controls_from_trajectory
from stemmap.types import Trajectory


def _path(steps: np.ndarray, t0: float = 0.0, dt: float = 0.2) -> Trajectory:
    poses = np.zeros((steps.shape[0] + 1, 3))
    for k, d in enumerate(steps):
        poses[k + 1] = compose(poses[k], d)
    return Trajectory(t0 + np.arange(poses.shape[0]) * dt, poses)


def _ekf_like_path(t0: float = 0.0) -> Trajectory:
    """200 poses at 5 Hz, 0.2 m forward steps with 1 cm sideways noise (an EKF path after pose
    updates), one backward step, a stop and a turn on the spot."""
    rng = np.random.default_rng(4)
    n = 199
    steps = np.column_stack(
        (
            0.2 + rng.normal(0.0, 0.01, n),
            rng.normal(0.0, 0.01, n),  # sideways
            rng.normal(0.02, 0.01, n),
        )
    )
    steps[50, 0] = -0.05  # backwards
    steps[60] = 0.0  # standing still
    steps[61, :2] = 0.0  # turning on the spot
    steps[70] = (0.0, 0.05, 0.0)  # a purely sideways step
    return _path(steps, t0)


def _pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    pos = float(np.max(np.hypot(*(a[:, :2] - b[:, :2]).T)))
    ang = float(np.max(np.abs(np.angle(np.exp(1j * (a[:, 2] - b[:, 2]))))))
    return pos, ang


@pytest.mark.parametrize("t0", [0.0, 1.7e9])  # Unix time stamps too
def test_controls_dead_reckon_through_every_pose(t0: float) -> None:
    traj = _ekf_like_path(t0)
    controls, model = controls_from_trajectory(traj, lateral="keep")
    poses = rollout(model, controls, traj.times, traj.poses[0])
    pos, ang = _pose_error(poses, traj.poses)
    assert pos < 1e-9 and ang < 1e-9, (pos, ang)
    assert model.sigma_lateral == model.sigma_speed  # the steps' sideways error is modelled
    # the default, speed and yaw rate per interval, loses the sideways part
    drop, plain_model = controls_from_trajectory(traj)
    plain = rollout(plain_model, drop, traj.times, traj.poses[0])
    assert plain_model.sigma_lateral == 0.0
    assert np.hypot(*(plain[-1, :2] - traj.poses[-1, :2])) > 0.1
    with pytest.raises(ConfigError):
        controls_from_trajectory(traj, lateral="sideways")  # type: ignore[arg-type]


def test_an_arc_path_keeps_one_control_per_interval() -> None:
    """Wheel-odometry-like steps (constant speed and yaw rate per interval) are arcs: one
    control each (their velocity), plus the held last one; no turn on the spot is added."""
    dt, v = 0.2, np.linspace(0.5, 1.5, 30)
    w = 0.3 * np.sin(np.arange(30))
    th = w * dt
    steps = np.column_stack((v * dt * np.cos(th / 2), v * dt * np.sin(th / 2), th))
    traj = _path(steps, dt=dt)
    c = Controls.from_trajectory(traj)
    assert len(c) == len(traj)
    np.testing.assert_allclose(c.speed[:-1], v, rtol=1e-12)
    np.testing.assert_allclose(c.steer[:-1], w, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(c.times, traj.times)


def test_split_intervals_give_the_turn_its_fraction_of_the_time() -> None:
    traj = _ekf_like_path()
    c = Controls.from_trajectory(traj, turn_fraction=0.25)
    turns = np.flatnonzero(~np.isin(c.times, traj.times))
    assert turns.size > 150  # nearly every EKF step has a sideways part
    assert np.all(c.speed[turns] == 0.0)
    k = np.searchsorted(traj.times, c.times[turns]) - 1
    frac = (traj.times[k + 1] - c.times[turns]) / np.diff(traj.times)[k]
    np.testing.assert_allclose(frac, 0.25, rtol=1e-9)
    # the held last control is the last interval's mean velocity
    assert c.times[-1] == traj.times[-1]
    with pytest.raises(ConfigError):
        Controls.from_trajectory(traj, turn_fraction=1.0)
    with pytest.raises(InputError):
        Controls.from_trajectory(Trajectory([0.0], [[0.0, 0.0, 0.0]]))


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_backend_without_landmarks_returns_the_odometry_path(name: str) -> None:
    """No detection at all: each back-end's trajectory is the motion source's path (FastSLAM
    with zero motion noise, so that its particles do not spread)."""
    traj = _ekf_like_path()
    sigma = (0.0, 0.0) if name == "fastslam" else (0.05, math.radians(1.0))
    controls, model = controls_from_trajectory(
        traj, sigma_speed=sigma[0], sigma_yaw_rate=sigma[1], lateral="keep"
    )
    problem = SlamProblem(
        controls,
        TreeFrames.empty_frames(traj.times),
        model,
        initial_pose=tuple(float(v) for v in traj.poses[0]),
    )
    res = make_backend(name).run(problem)
    pos, ang = _pose_error(res.trajectory.poses, traj.poses)
    assert pos < 1e-6 and ang < 1e-6, (pos, ang)
