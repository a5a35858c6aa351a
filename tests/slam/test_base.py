"""SLAM interface: input validation, frames, observation model, registry, dead reckoning."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import (
    BACKENDS,
    Controls,
    SlamProblem,
    TreeFrames,
    dead_reckoning,
    make_backend,
    observation_to_world,
    observe,
    sensor_poses,
)
from stemmap.slam.motion import AckermannModel, UnicycleModel
from stemmap.types import StemObservations


def test_controls_reject_backwards_time_and_bad_lengths():
    with pytest.raises(InputError, match="backwards"):
        Controls([0.0, 1.0, 0.5], [1, 1, 1], [0, 0, 0], "ackermann")
    with pytest.raises(InputError, match="speed"):
        Controls([0.0, 1.0], [1.0], [0, 0], "ackermann")
    with pytest.raises(InputError, match="kind"):
        Controls([0.0], [1.0], [0.0], "bicycle")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="finite"):
        Controls([0.0, 1.0], [1.0, np.nan], [0, 0], "unicycle")


def test_controls_slice_keeps_hold_value():
    c = Controls(np.arange(10.0), np.arange(10.0), np.zeros(10), "unicycle")
    s = c.slice(3.5, 6.0)
    np.testing.assert_array_equal(s.times, [3, 4, 5, 6])
    assert not s.times.flags.writeable


def test_treeframes_validation():
    with pytest.raises(InputError, match="ptr"):
        TreeFrames([0.0, 1.0], [0, 1], [1.0], [0.0], [0.1])
    with pytest.raises(InputError, match="ranges"):
        TreeFrames([0.0], [0, 1], [-1.0], [0.0], [0.1])
    with pytest.raises(InputError, match="backwards"):
        TreeFrames([1.0, 0.0], [0, 0, 0], [], [], [])
    f = TreeFrames([0.0, 1.0], [0, 2, 3], [1.0, 2.0, 3.0], [0.1, 4.0, -0.1], [0.1, 0.2, 0.3])
    assert f.bearings[1] == pytest.approx(4.0 - 2 * math.pi)  # wrapped to (-pi, pi]
    r, _, _ = f.frame(1)
    np.testing.assert_array_equal(r, [3.0])
    np.testing.assert_array_equal(f.frame_index, [0, 0, 1])
    sub = f.slice(0.5, 2.0)
    assert len(sub) == 1 and sub.n_detections == 1 and sub.ptr[0] == 0


def test_from_observations_computes_polar_and_groups_by_frame():
    centers = np.array([[3.0, 4.0], [0.0, -2.0], [1.0, 0.0]])
    obs = StemObservations(
        centers=centers,
        radii=[0.1, 0.2, 0.3],
        covs=np.zeros((3, 3, 3)),
        n_points=[5, 5, 5],
        arc_deg=[90, 90, 90],
        widths=[np.nan] * 3,
        quality=[1, 1, 1],
        index=[2, 0, 2],
        times=[0, 0, 0],
    )
    f = TreeFrames.from_observations(obs, [0.0, 0.1, 0.2])
    np.testing.assert_array_equal(f.ptr, [0, 1, 1, 3])
    np.testing.assert_allclose(f.ranges, [2.0, 5.0, 1.0])
    np.testing.assert_allclose(f.bearings, [-math.pi / 2, math.atan2(4, 3), 0.0])
    np.testing.assert_allclose(f.diameters, [0.4, 0.2, 0.6])
    with pytest.raises(InputError, match="index"):
        TreeFrames.from_observations(obs, [0.0, 0.1])


def test_observation_model_round_trip():
    rng = np.random.default_rng(3)
    pose = np.array([2.0, -1.0, 0.7])
    lm = rng.uniform(-20, 20, size=(50, 2))
    off = (3.78, 0.5)
    r, b = observe(pose, lm, off)
    np.testing.assert_allclose(observation_to_world(pose, r, b, off), lm, atol=1e-9)
    s = sensor_poses(pose, off)
    np.testing.assert_allclose(
        s[:2],
        pose[:2]
        + np.array(
            [3.78 * math.cos(0.7) - 0.5 * math.sin(0.7), 3.78 * math.sin(0.7) + 0.5 * math.cos(0.7)]
        ),
    )


def test_make_backend_unknown_name():
    with pytest.raises(ConfigError, match="unknown SLAM back-end"):
        make_backend("nope")
    assert set(BACKENDS) == {"treedb", "ekf", "fastslam", "forestrix", "isam2"}


def test_dead_reckoning_straight_line():
    t = np.arange(0, 10.01, 0.05)
    c = Controls(t, np.full(t.size, 2.0), np.zeros(t.size), "unicycle")
    frames = TreeFrames.empty_frames(np.arange(0, 10.01, 1.0))
    p = SlamProblem(c, frames, UnicycleModel(), initial_pose=(1.0, 0.0, math.pi / 2))
    traj = dead_reckoning(p)
    np.testing.assert_allclose(traj.poses[:, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(traj.poses[:, 1], 2.0 * frames.times, atol=1e-9)
    assert len(traj) == len(frames)
    with pytest.raises(InputError):
        SlamProblem(c, TreeFrames.empty_frames([]), AckermannModel())
