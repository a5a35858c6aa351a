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


# --- Öhman Fig. 5 as drawn: raw scan rays cast through the mapped trees -----------------------


def _ray_scene(seed: int):
    """A 40 x 30 m stand scanned from a drive through it (sick_lms: 0.5 deg, 1 cm noise, mixed
    pixels), a map of the true trees with 2 cm (per axis) position / 2 cm diameter error (a
    converged SLAM map; ``position_tol`` 5 cm is 2.5 sigma) and 12 injected false trees (branch
    or bush echoes accepted as trees: 12-30 cm) in free space within 2-12 m of the path, >= 1 m
    from any true trunk's surface."""
    from stemmap.sim.forest import random_stand
    from stemmap.sim.scanner import simulate_scans

    rng = np.random.default_rng(seed)
    stand = random_stand(45, (40.0, 30.0), min_spacing=2.0, rng=rng)
    xs = np.linspace(2.0, 38.0, 60)
    poses = np.column_stack((xs, np.full_like(xs, 15.0), np.zeros_like(xs)))
    # thread the path between trees: drop poses inside or grazing a trunk
    clear = np.array([np.min(np.hypot(*(stand.trees_xy - p[:2]).T) - stand.radii) > 0.5
                      for p in poses])  # fmt: skip
    poses = poses[clear]
    scans, _, _ = simulate_scans(stand, poses, "sick_lms", rng=rng)
    fake = []
    while len(fake) < 12:
        p = np.array([rng.uniform(0, 40), rng.uniform(3, 27)])
        gap = np.min(np.hypot(*(stand.trees_xy - p).T) - stand.radii)
        dp = np.min(np.hypot(*(poses[:, :2] - p).T))
        if gap >= 1.0 and 2.0 <= dp <= 12.0:
            fake.append(p)
    xy = np.vstack((stand.trees_xy + rng.normal(0, 0.02, stand.trees_xy.shape), fake))
    dia = np.concatenate(
        (stand.diameters + rng.normal(0, 0.02, stand.n_trees), rng.uniform(0.12, 0.30, 12))
    )
    trees = [Tree(i, float(xy[i, 0]), float(xy[i, 1]), float(dia[i])) for i in range(len(dia))]
    stem_map = StemMap(tuple(trees))
    return stand, stem_map, poses, scans


@pytest.mark.parametrize("seed", [0, 5])
def test_rays_through_mapped_trees_remove_false_trees_keep_true(seed):
    from stemmap.slam.negative import remove_false_trees_by_rays

    stand, stem_map, poses, scans = _ray_scene(seed)
    cleaned, res = remove_false_trees_by_rays(stem_map, poses, scans)
    n_true = stand.n_trees
    is_fake = np.arange(len(stem_map)) >= n_true
    # every false tree the scanner looked at is crossed by beams returning from far behind
    # it, and none returns from it: removed (measured over seeds 0-7: 0 hits, 4-75 pass-through
    # beams; the few with < 3 lie behind the start of the drive, never in the field of view)
    evidence = res.hits + res.misses >= 3
    assert np.count_nonzero(is_fake & evidence) >= 10
    assert not res.keep[is_fake & evidence].any()
    assert np.all(res.hits[is_fake] == 0)
    # every true tree is kept: its core beams return from its surface (measured: 0-1
    # pass-through beams per seed against ~1800 hits)
    assert np.all(res.keep[~is_fake])
    assert np.count_nonzero(evidence[~is_fake]) >= 0.8 * n_true
    assert res.misses[~is_fake].sum() <= 0.002 * res.hits[~is_fake].sum()
    assert {t.id for t in cleaned} == set(range(n_true)) | set(
        np.flatnonzero(is_fake & ~evidence).tolist()
    )
    # a map 14 cm off everywhere (beyond position_tol) loses true trees; telling the rule the
    # map error (position_tol 0.15 m) keeps them, at the price of not judging thin trees
    shifted = StemMap(tuple(Tree(t.id, t.x + 0.1, t.y - 0.1, t.diameter)
                            for t in stem_map.trees[:n_true]))  # fmt: skip
    _, bad = remove_false_trees_by_rays(shifted, poses, scans)
    _, tol = remove_false_trees_by_rays(shifted, poses, scans, position_tol=0.15)
    assert not bad.keep.all()
    assert tol.keep.all()


def test_ray_rule_counts_and_errors():
    from stemmap.slam.negative import ray_pass_through
    from stemmap.types import ScanBatch

    # one beam straight ahead from the origin, a mapped tree of 0.4 m at 5 m
    def scan(r):
        return ScanBatch(np.array([[r]]), np.zeros(1), 0.0, 0.01, 0.05, 30.0)

    pose = np.zeros((1, 3))
    tree = np.array([[5.0, 0.0]])
    cases = {4.85: (1, 0, 0), 5.0: (1, 0, 0), 6.0: (0, 1, 0), np.inf: (0, 1, 0), 3.0: (0, 0, 1),
             5.4: (0, 0, 0)}  # fmt: skip
    for r, (h, m, o) in cases.items():
        res = ray_pass_through(tree, [0.4], pose, scan(r), min_expected=1)
        assert (res.hits[0], res.misses[0], res.occluded[0]) == (h, m, o), r
    # no return but the tree is beyond the scanner's range: no evidence
    far = ScanBatch(np.array([[np.inf]]), np.zeros(1), 0.0, 0.01, 0.05, 5.2)
    assert ray_pass_through(tree, [0.4], pose, far).misses[0] == 0
    # a beam 0.15 m off the centre of a 0.4 m tree is outside the core (0.1 m): not counted
    off = ray_pass_through([[5.0, 0.15]], [0.4], pose, scan(np.inf), min_expected=1)
    assert off.misses[0] == 0
    with pytest.raises(InputError):
        ray_pass_through(tree, [0.4], np.zeros((2, 3)), scan(5.0))
    with pytest.raises(ConfigError):
        ray_pass_through(tree, [0.4], pose, scan(5.0), pass_margin=0.1, hit_tol=0.2)
    with pytest.raises(ConfigError):
        ray_pass_through(tree, [0.4], pose, scan(5.0), core_fraction=0.0)
