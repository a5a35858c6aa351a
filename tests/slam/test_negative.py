"""False-tree removal with negative information (Öhman 2007 §2.2, Fig. 5)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_treedb import FOV, sim_problem  # shared simulated loop (tests/slam/test_treedb.py)

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import observation_to_world, sensor_poses
from stemmap.slam.negative import (
    SensorFov,
    expected_visibility,
    negative_information,
    remove_false_trees,
    remove_false_trees_after,
)
from stemmap.slam.treedb import TreeDbSlam
from stemmap.types import StemMap, Tree


def test_visibility_window_and_occlusion():
    fov = SensorFov(-math.pi / 2, math.pi / 2, 0.5, 15.0)
    trees = np.array(
        [
            [5.0, 0.0],  # ahead, visible, big (occluder)
            [10.0, 0.0],  # straight behind tree 0: occluded
            [10.0, 3.0],  # ahead-left, clear line of sight
            [-5.0, 0.0],  # behind the sensor: out of the field of view
            [20.0, 0.0],  # beyond range
        ]
    )
    radii = np.array([0.4, 0.15, 0.15, 0.15, 0.15])
    in_view, occluded = expected_visibility(trees, radii, np.zeros(3), fov)
    assert in_view.tolist() == [True, True, True, False, False]
    assert occluded.tolist() == [False, True, False, False, False]
    # a thin tree in front of a thick one hides only part of it: not occluded
    in_view, occluded = expected_visibility(
        np.array([[5.0, 0.0], [10.0, 0.0]]), np.array([0.05, 0.5]), np.zeros(3), fov
    )
    assert occluded.tolist() == [False, False]


@pytest.fixture(scope="module")
def sim():
    return sim_problem(seed=4, laps=1.0)


def _world_detections(problem, poses):
    fr = problem.frames
    idx = fr.frame_index
    return observation_to_world(poses[idx], fr.ranges, fr.bearings, problem.sensor_offset)


def test_injected_false_trees_are_removed_true_trees_kept(sim, rng):
    problem, run = sim
    truth_xy = run.stand.trees_xy
    truth_d = run.stand.diameters
    # false trees: branches/bushes accepted as trees, placed where the vehicle looked
    # (within 3..10 m of the path, at least 2 m from any real tree)
    path = run.true_poses.poses[:, :2]
    fake = []
    while len(fake) < 15:
        p = path[rng.integers(len(path))] + rng.uniform(-10, 10, 2)
        dp = np.min(np.hypot(*(path - p).T))
        dt = np.min(np.hypot(*(truth_xy - p).T))
        if 3.0 <= dp <= 10.0 and dt >= 2.0:
            fake.append(p)
    fake = np.array(fake)
    xy = np.vstack((truth_xy, fake))
    dia = np.concatenate((truth_d, np.full(len(fake), 0.2)))
    stem_map = StemMap(
        tuple(
            Tree(i, float(x), float(y), float(d))
            for i, ((x, y), d) in enumerate(zip(xy, dia, strict=True))
        )
    )
    poses = run.vehicle_poses.poses
    sp = sensor_poses(poses, problem.sensor_offset)
    det = _world_detections(problem, poses)
    cleaned, res = remove_false_trees(stem_map, sp, problem.frames.ptr, det, FOV, gate=0.5)
    is_fake = np.arange(len(xy)) >= len(truth_xy)
    seen = res.hits + res.misses > 0
    # every fake tree that came into view is removed; every real tree seen is kept
    assert np.all(~res.keep[is_fake & seen])
    assert np.count_nonzero(is_fake & seen) >= 10
    assert np.all(res.keep[~is_fake])
    # real trees: detected whenever expected (exact-visibility detections)
    assert np.all(res.misses[~is_fake] <= 1)
    kept_ids = {t.id for t in cleaned}
    assert kept_ids.isdisjoint(set(np.flatnonzero(is_fake & seen).tolist()))
    assert all(0.0 <= t.confidence <= 1.0 for t in cleaned)


def test_log_odds_rule_and_min_expected():
    fov = SensorFov(-math.pi, math.pi, 0.0, 50.0)
    trees = np.array([[10.0, 0.0], [0.0, 10.0]])
    sp = np.zeros((10, 3))
    # tree 0 detected in 3 of 10 frames, tree 1 never
    ptr = np.array([0, 1, 2, 3, 3, 3, 3, 3, 3, 3, 3])
    det = np.array([[10.0, 0.0]] * 3)
    oh = negative_information(trees, [0.3, 0.3], sp, ptr, det, fov)
    assert oh.hits.tolist() == [3, 0] and oh.misses.tolist() == [7, 10]
    # Öhman: misses > hits removes both
    assert oh.keep.tolist() == [False, False]
    # log-odds with p_d = 0.3: 3 hits in 10 is what a real tree gives -> kept
    lo = negative_information(trees, [0.3, 0.3], sp, ptr, det, fov, rule="log_odds", p_detect=0.3)
    assert lo.keep.tolist() == [True, False]
    few = negative_information(trees, [0.3, 0.3], sp[:2], ptr[:3], det[:2], fov, min_expected=3)
    assert few.keep.tolist() == [True, True]


def test_post_step_on_a_backend_result(sim):
    problem, _ = sim
    res = TreeDbSlam(promote_count=3).run(problem)
    cleaned, info = remove_false_trees_after(res, problem, range_min=0.5, gate=0.7)
    assert len(cleaned) == len(res.stem_map) - info.n_removed
    # no false detections were simulated: almost nothing should be removed (<= 10 %)
    assert info.n_removed <= 0.1 * len(res.stem_map)


def test_negative_bad_input():
    fov = SensorFov()
    with pytest.raises(InputError, match="frame_ptr"):
        negative_information(
            np.zeros((1, 2)), [0.3], np.zeros((2, 3)), [0, 0], np.zeros((0, 2)), fov
        )
    with pytest.raises(InputError, match="diameters"):
        negative_information(
            np.zeros((2, 2)), [0.3], np.zeros((1, 3)), [0, 0], np.zeros((0, 2)), fov
        )
    with pytest.raises(InputError):
        negative_information(
            np.zeros((1, 2)), [0.3], np.zeros((1, 3)), [0, 2], np.zeros((1, 2)), fov
        )
    with pytest.raises(ConfigError):
        SensorFov(1.0, -1.0)
    from stemmap.slam.base import SlamResult
    from stemmap.types import Trajectory

    problem, _ = sim_problem(seed=4, laps=0.2)
    bad = SlamResult(Trajectory([0.0, 1.0], np.zeros((2, 3))), StemMap(()))
    with pytest.raises(InputError, match="frames"):
        remove_false_trees_after(bad, problem)
    with pytest.raises(ConfigError):
        SensorFov(range_min=5.0, range_max=1.0)
    with pytest.raises(ConfigError, match="rule"):
        negative_information(
            np.zeros((1, 2)), [0.3], np.zeros((1, 3)), [0, 0], np.zeros((0, 2)), fov, rule="x"
        )  # type: ignore[arg-type]
