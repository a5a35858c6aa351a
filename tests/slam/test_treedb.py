"""Tree DB (visual-lidar paper §2.5) and the TreeDbSlam back-end."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.eval.matching import match_points
from stemmap.sim.forest import random_stand
from stemmap.sim.trajectory import loop_path, simulate_run
from stemmap.slam.base import (
    Controls,
    SlamProblem,
    TreeFrames,
    dead_reckoning,
    make_backend,
    observe,
)
from stemmap.slam.motion import UnicycleModel, preintegrate
from stemmap.slam.negative import SensorFov, expected_visibility
from stemmap.slam.treedb import (
    PRESETS,
    TreeDb,
    TreeDbSlam,
    range_bearing_jacobians,
    treedb_update,
)
from stemmap.types import wrap_angle

FOV = SensorFov(-math.pi / 2, math.pi / 2, 0.5, 15.0)


def sim_problem(seed: int = 1, laps: float = 1.2, noise: str = "wheel"):
    """A simulated loop (sim.trajectory.simulate_run) with exact-visibility tree detections.

    Detections come from ray-cast visibility of the true trees (occlusion included) plus
    3 cm / 0.3 deg noise, so the back-end tests are independent of the scan detector.
    """
    rng = np.random.default_rng(seed)
    stand = random_stand(90, (70.0, 56.0), min_spacing=2.0, rng=rng)
    path = loop_path((35.0, 28.0), (20.0, 13.0), laps=laps)
    run = simulate_run(
        stand, path, rate_hz=5.0, odometry_noise=noise, corridor_half_width=2.5, rng=seed
    )
    ptr, rr, bb, dd = [0], [], [], []
    for p in run.true_poses.poses:
        vis, occ = expected_visibility(run.stand.trees_xy, run.stand.radii, p, FOV)
        sel = np.flatnonzero(vis & ~occ)
        rel = run.stand.trees_xy[sel] - p[:2]
        rr.append(np.hypot(rel[:, 0], rel[:, 1]) + rng.normal(0, 0.03, sel.size))
        bb.append(np.arctan2(rel[:, 1], rel[:, 0]) - p[2] + rng.normal(0, 0.005, sel.size))
        dd.append(run.stand.diameters[sel])
        ptr.append(ptr[-1] + sel.size)
    frames = TreeFrames(
        run.true_poses.times,
        np.array(ptr),
        np.concatenate(rr),
        np.concatenate(bb),
        np.concatenate(dd),
    )
    odo = run.odometry
    problem = SlamProblem(
        Controls(odo.times, odo.speed, odo.yaw_rate, "unicycle"),
        frames,
        UnicycleModel(sigma_speed=0.1, sigma_steer=math.radians(2.0)),
        initial_pose=tuple(run.vehicle_poses.poses[0]),
        max_range=FOV.range_max,
        fov=(FOV.bearing_min, FOV.bearing_max),
    )
    return problem, run


@pytest.fixture(scope="module")
def sim():
    return sim_problem()


# ------------------------------------------------------------------------------------------
# treedb_update: eq. (2)
# ------------------------------------------------------------------------------------------


def test_weighted_average_is_running_mean_of_eq2():
    db = TreeDb()
    pts = np.array([[1.0, 2.0], [1.2, 2.1], [0.9, 1.8], [1.1, 2.2]])
    dia = np.array([0.30, 0.34, np.nan, 0.32])
    for p, d in zip(pts, dia, strict=True):
        db, idx = treedb_update(db, p[None], [d], gate=0.5)
        assert idx.tolist() == [0]
    # eq. (2) with c_{t-1} weights is exactly the arithmetic mean of all sightings
    np.testing.assert_allclose(db.xy[0], pts.mean(axis=0), atol=1e-12)
    assert db.count[0] == 4
    # diameter averaged over the 3 sightings that carried one
    np.testing.assert_allclose(db.diameter[0], np.nanmean(dia), atol=1e-12)
    assert db.diameter_count[0] == 3


def test_gate_separates_new_trees_and_one_detection_per_tree():
    db, _ = treedb_update(TreeDb(), [[0.0, 0.0], [3.0, 0.0]], [0.3, 0.3], gate=0.5)
    # two detections near tree 0: the closer one updates it, the other becomes a new entry
    db, idx = treedb_update(db, [[0.4, 0.0], [0.1, 0.0], [3.0, 0.6]], None, gate=0.5)
    assert idx.tolist() == [2, 0, 3]
    assert len(db) == 4
    assert db.count.tolist() == [2, 1, 1, 1]


def test_known_association_overrides_the_gate():
    db, _ = treedb_update(TreeDb(), [[0.0, 0.0], [3.0, 0.0]], None, gate=0.5)
    # detection 0 is 1.2 m from tree 0 (beyond the gate) but was matched by the localisation
    db, idx = treedb_update(db, [[1.2, 0.0], [3.1, 0.0]], None, gate=0.5, known=[0, -1])
    assert idx.tolist() == [0, 1] and len(db) == 2
    np.testing.assert_allclose(db.xy[0], [0.6, 0.0])
    with pytest.raises(InputError, match="known"):
        treedb_update(db, [[0.0, 0.0]], None, known=[5])


def test_promotion_at_count_threshold_paper_20():
    assert PRESETS["visual_lidar"].promote_count == 20
    db = TreeDb()
    for k in range(20):
        db, _ = treedb_update(db, [[5.0, 5.0], [9.0, 9.0]] if k < 19 else [[5.0, 5.0]], None)
    # tree 0 seen exactly 20 times, tree 1 only 19 times: only tree 0 is a landmark (the
    # boundary: we promote at count >= 20, docs/algorithms/slam-frontends.md "Tree DB")
    assert db.count.tolist() == [20, 19]
    assert db.landmarks(20).tolist() == [0]
    m = db.to_stem_map(20)
    assert len(m) == 1 and m.trees[0].n_obs == 20
    # one more sighting of tree 1 promotes it too
    db, _ = treedb_update(db, [[9.0, 9.0]], None)
    assert db.landmarks(20).tolist() == [0, 1]
    # TreeDbSlam uses the preset's threshold: with it at 21 nothing built above is a landmark
    # after 20 sightings (the count is what promotes, not the number of frames)
    assert db.landmarks(21).tolist() == []


@settings(max_examples=30, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=1, max_size=12, unique=True
    )
)
def test_db_entries_never_closer_than_gate_from_one_frame(points):
    xy = np.array(points)
    db, idx = treedb_update(TreeDb(), xy, None, gate=0.5)
    # first frame: every detection is a new entry, indices are a permutation
    assert sorted(idx.tolist()) == list(range(len(points)))
    db2, idx2 = treedb_update(db, xy, None, gate=0.5)
    # the same frame again re-identifies every tree (distance 0 <= gate, one-to-one)
    assert len(db2) == len(points)
    np.testing.assert_array_equal(idx2, idx)


def test_treedb_bad_input():
    with pytest.raises(InputError, match="shape"):
        treedb_update(TreeDb(), np.zeros((3, 3)))
    with pytest.raises(InputError, match="finite"):
        treedb_update(TreeDb(), [[np.nan, 0.0]])
    with pytest.raises(InputError, match="diameters"):
        treedb_update(TreeDb(), [[0.0, 0.0]], [0.1, 0.2])
    with pytest.raises(ConfigError):
        treedb_update(TreeDb(), [[0.0, 0.0]], gate=0.0)
    with pytest.raises(ConfigError, match="preset"):
        TreeDbSlam(preset="nope")
    with pytest.raises(ConfigError):
        TreeDbSlam(promote_count=0)


# ------------------------------------------------------------------------------------------
# observation Jacobians
# ------------------------------------------------------------------------------------------


def test_range_bearing_jacobians_match_numerical_derivatives(rng):
    off = (3.78, 0.5)
    for _ in range(5):
        pose = rng.uniform([-5, -5, -3], [5, 5, 3])
        m = rng.uniform(-20, 20, 2)
        z, Hx, Hm = range_bearing_jacobians(pose, m, off)
        r, b = observe(pose, m[None], off)
        np.testing.assert_allclose(z, [r[0], b[0]], atol=1e-12)
        eps = 1e-6
        for i in range(3):
            dp = np.zeros(3)
            dp[i] = eps
            zp, _, _ = range_bearing_jacobians(pose + dp, m, off)
            zm, _, _ = range_bearing_jacobians(pose - dp, m, off)
            num = (zp - zm) / (2 * eps)
            num[1] = math.remainder(num[1] * 2 * eps, 2 * math.pi) / (2 * eps)
            np.testing.assert_allclose(Hx[:, i], num, atol=1e-6)
        for i in range(2):
            dm = np.zeros(2)
            dm[i] = eps
            zp, _, _ = range_bearing_jacobians(pose, m + dm, off)
            zm, _, _ = range_bearing_jacobians(pose, m - dm, off)
            np.testing.assert_allclose(Hm[:, i], (zp - zm) / (2 * eps), atol=1e-6)


# ------------------------------------------------------------------------------------------
# back-end on a simulated loop
# ------------------------------------------------------------------------------------------


def test_treedb_slam_registered_and_localizing_beats_dead_reckoning(sim):
    problem, run = sim
    truth = run.vehicle_poses.poses
    backend = make_backend("treedb")
    assert isinstance(backend, TreeDbSlam)
    res = backend.run(problem)
    dr = dead_reckoning(problem)
    err = np.hypot(*(res.trajectory.poses[:, :2] - truth[:, :2]).T)
    err_dr = np.hypot(*(dr.poses[:, :2] - truth[:, :2]).T)
    rmse, rmse_dr = np.sqrt(np.mean(err**2)), np.sqrt(np.mean(err_dr**2))
    # wheel preset drifts metres over the ~150 m loop; landmark localisation keeps the pose
    # within a few decimetres (measured 0.13 m vs 3.5 m); require a 5x improvement
    assert rmse < rmse_dr / 5
    assert rmse < 0.5
    # promoted landmarks are real trees: >= 90 % within 0.5 m of a true tree
    m = match_points(res.stem_map.xy, run.stand.trees_xy, 0.5)
    assert m.n_matched >= 0.9 * len(res.stem_map)
    assert all(t.n_obs >= backend.promote_count for t in res.stem_map)
    assert len(res.trajectory) == len(problem.frames)


def test_treedb_pose_covariance_on_every_row(sim):
    """Issue 14: every row has a finite, positive-definite pose covariance, the derived one
    (no factor), growing from the fixed start; the run closes loops, so it is the linear
    graph's marginals (:meth:`TreeMapErrors.pose_covariances`). Against the truth it is not
    overconfident on this loop, whose detections (3 cm / 0.3 deg) are ten times better than
    the back-end's default noise model (0.3 m / 1 deg): median z² 0.01-0.04 (seeds 1-2),
    bound the calibrated 1.39."""
    problem, run = sim
    res = TreeDbSlam().run(problem)
    P = res.pose_covs
    assert res.stats["loop_closures"] >= 1
    assert P is not None and P.shape == (len(problem.frames), 3, 3)
    assert np.isfinite(P).all() and np.all(np.linalg.eigvalsh(P[1:]) > 0)
    np.testing.assert_allclose(P, np.swapaxes(P, 1, 2), atol=1e-12)
    assert np.trace(P[0, :2, :2]) < 1e-4 < np.trace(P[len(P) // 2, :2, :2])
    e = res.trajectory.poses[1:, :2] - run.vehicle_poses.poses[1:, :2]
    z2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(P[1:, :2, :2]), e)
    assert np.median(z2) < 1.386


def _mc_drive(rng, trees, sigmas, n=120, dt=0.2, r_max=12.0):
    """A 24 m arc through ``trees`` whose odometry and detections carry exactly the noise the
    back-end is told (``sigmas`` = speed m/s, yaw rate rad/s, range m, bearing rad; the
    odometry's one-second white equivalents): (problem, true poses)."""
    sv, sw, sr, sb = sigmas
    t = np.arange(n) * dt
    v, w = np.full(n, 1.0), np.full(n, 0.04)
    model = UnicycleModel(sigma_speed=sv, sigma_steer=sw)
    truth = preintegrate(model, Controls(t, v, w, "unicycle"), t, (0.0, 0.0, 0.0)).poses
    vm = v + rng.normal(0.0, sv / math.sqrt(dt), n)  # sample-and-hold: density sv² per second
    wm = w + rng.normal(0.0, sw / math.sqrt(dt), n)
    ptr, rr, bb = [0], [], []
    for p in truth:
        d = trees - p[:2]
        r = np.hypot(d[:, 0], d[:, 1])
        b = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - p[2])
        seen = (r < r_max) & (np.abs(b) < math.pi / 2)
        rr.append(r[seen] + rng.normal(0.0, sr, seen.sum()))
        bb.append(b[seen] + rng.normal(0.0, sb, seen.sum()))
        ptr.append(ptr[-1] + int(seen.sum()))
    frames = TreeFrames(
        t, np.array(ptr), np.concatenate(rr), np.concatenate(bb), np.full(ptr[-1], 0.3)
    )
    problem = SlamProblem(
        Controls(t, vm, wm, "unicycle"), frames, model, initial_pose=(0.0, 0.0, 0.0),
        max_range=r_max,
    )  # fmt: skip
    return problem, truth


def mc_pose_scores(run_backend, seeds=range(100, 140)):
    """Pose NEES and position z² (each (frames,) per drive) of every row after the first 2 s
    of the Monte-Carlo drives (:func:`_mc_drive`, seeds ``seeds``, one tree layout; noise
    models matching: speed 0.05 m/s, yaw rate 0.01 rad/s, range 0.05 m, bearing 0.01 rad).
    ``run_backend(problem, sigmas) -> SlamResult``; a drive that closes a loop fails (the
    forward analysis alone is what these drives check)."""
    rng0 = np.random.default_rng(0)
    trees = np.column_stack((rng0.uniform(-5, 30, 40), rng0.uniform(-8, 20, 40)))
    sigmas = (0.05, 0.01, 0.05, 0.01)
    nees, z2 = [], []
    for k in seeds:
        problem, truth = _mc_drive(np.random.default_rng(k), trees, sigmas)
        res = run_backend(problem, sigmas)
        assert res.stats["loop_closures"] == 0  # no loops: the forward analysis itself
        e = res.trajectory.poses[10:] - truth[10:]
        e[:, 2] = wrap_angle(e[:, 2])
        P = res.pose_covs[10:]
        nees.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(P), e))
        z2.append(np.einsum("ni,nij,nj->n", e[:, :2], np.linalg.inv(P[:, :2, :2]), e[:, :2]))
    return nees, z2


def demo_position_z2(backend, make):
    """Position z² of every reported row after the first on the ``stemmap demo`` drives
    (seeds 0-6, the motion noise ``stemmap demo`` hands ``backend``), run with ``make()``."""
    from stemmap.cli._demo import _stand_and_run
    from stemmap.cli._map import sim_problem as demo_problem

    z2 = []
    for seed in range(7):
        run = _stand_and_run(seed, 120)
        problem, _ = demo_problem(run, backend=backend)
        res = make().run(problem)
        true = run.vehicle_poses.interpolate(res.trajectory.times)
        e = res.trajectory.poses[1:, :2] - true[1:, :2]
        z2.append(np.einsum("ni,nij,nj->n", e, np.linalg.inv(res.pose_covs[1:, :2, :2]), e))
    return np.concatenate(z2)


def test_treedb_pose_covariance_is_calibrated_on_simulated_drives():
    """Issue 14: the reported pose covariance is the tree DB's actual error covariance, with no
    factor. 40 simulated drives (seeds 100-139) whose odometry and detection noise follow the
    models the back-end is given, trees handed over as the vehicle drives (the pose drifts
    with the map it localises on); every row after the first 2 s scored against the truth.

    Calibrated: pose NEES mean 3 (3 dof), position z² median 1.386. Measured 3.11 / 1.35 here
    (seeds 200-239: 3.13 / 1.34; 300-339: 3.29 / 1.53). The per-drive mean NEES scatters with
    std 1.5-2.0, so the pooled mean of 40 drives has std ~0.3: bound |NEES/3 - 1| < 0.25 (2.5
    std); position z² median within 1.5x. The VP-fitted chain factor it replaced (0.0038) gave
    NEES 4.53 / 4.98 / 4.59 and z² median 0.75 / 0.72 / 0.83 on the same seeds: fails both."""
    nees, z2 = mc_pose_scores(
        lambda problem, sg: TreeDbSlam(sigma_range=sg[2], sigma_bearing=sg[3], refine=False).run(
            problem
        )
    )
    assert abs(np.mean(nees) / 3.0 - 1.0) < 0.25
    assert 1.386 / 1.5 < np.median(z2) < 1.386 * 1.5


@pytest.mark.slow
def test_treedb_pose_covariance_on_the_demo_drives():
    """Issue 14: on the ``stemmap demo`` drives (seeds 0-6, the scan detector's detections, the
    motion noise ``stemmap demo`` hands the tree DB; nothing matches the back-end's models by
    construction) the derived pose covariance is within 2x of calibrated: pooled position z²
    median 0.89 (per seed 0.58-1.18; calibrated 1.386), where the VP-fitted chain factor
    (0.0038) gave 3.39 (per seed 2.8-8.4; docs/outputs.md)."""
    z2 = demo_position_z2("treedb", TreeDbSlam)
    assert 1.386 / 2 < np.median(z2) < 2 * 1.386


def test_tree_map_errors_graph_is_the_forward_analysis_without_loops_and_shrinks_with_one():
    """:meth:`TreeMapErrors.pose_covariances`: the Gauss-Markov chain over the keyframes
    reproduces the recorded covariances exactly when there is no loop (its regression is exact
    for the marginals); a loop constraint between the last keyframe and the start shrinks the
    end's covariance to about the constraint's own."""
    from stemmap.slam._tree_map_errors import TreeMapErrors
    from stemmap.slam.relaxation import LoopClosure

    n, kf = 60, list(range(0, 60, 6))
    err = TreeMapErrors(n, np.diag([0.3**2, math.radians(1.0) ** 2]))
    poses = np.column_stack((np.arange(n) * 0.5, np.zeros(n), np.zeros(n)))
    Q = np.diag([0.02**2, 0.01**2, 0.003**2])
    for f in range(n):
        if f:
            err.predict(np.array([[1, 0, 0], [0, 1, 0.5], [0, 0, 1.0]]), Q)
        err.record(f, f in kf and f > 0)
    out = err.pose_covariances(poses, kf, [], 2.385)
    # up to the graph's 1 mm floor added per chain step (10 steps: 1e-5 m²)
    np.testing.assert_allclose(out[1:], err.abs_cov[1:], rtol=1e-6, atol=1.1e-5)
    loop = LoopClosure(0, kf[-1], (float(poses[kf[-1], 0]), 0.0, 0.0), (0.05, 0.05, 0.002))
    closed = err.pose_covariances(poses, kf, [loop], 2.385)
    assert closed[kf[-1], 1, 1] < 0.1 * out[kf[-1], 1, 1]
    assert closed[kf[-1], 1, 1] < 2 * 0.05**2 and np.all(np.linalg.eigvalsh(closed[1:]) > 0)


def test_treedb_open_loop_is_the_papers_odometry_pipeline(sim):
    problem, _ = sim
    res = TreeDbSlam(localize=False).run(problem)
    dr = dead_reckoning(problem)
    # without landmark feedback the poses are exactly the odometry (paper's §2.5 mapping)
    np.testing.assert_allclose(res.trajectory.poses, dr.poses, atol=1e-9)
    assert res.stats["frames_localized"] == 0


def test_visual_lidar_preset_maps_only_trees_seen_20_times(sim):
    """The back-end publishes the DB entries promoted at the preset's count (20, §2.5): every
    mapped tree carries >= 20 sightings, and the same run with a count of 1 maps more trees,
    some seen fewer than 20 times (so the threshold, not the simulation, removed them)."""
    problem, _ = sim
    paper = TreeDbSlam(preset="visual_lidar", localize=False).run(problem).stem_map
    loose = TreeDbSlam(gate=PRESETS["visual_lidar"].gate, promote_count=1, localize=False)
    every = loose.run(problem).stem_map
    n_paper = [t.n_obs for t in paper.trees]
    n_every = [t.n_obs for t in every.trees]
    assert len(n_paper) >= 10 and min(n_paper) >= 20
    assert len(n_every) > len(n_paper) and min(n_every) < 20
    assert sum(n >= 20 for n in n_every) == len(n_paper)


@pytest.mark.slow
def test_treedb_on_victoria_park_first_300_s(datasets_dir):
    from _vp import screened_ate

    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.slam.base import duplicate_pairs

    vp = load_victoria_park(datasets_dir / "victoria_park").slice(0.0, 300.0)
    res = TreeDbSlam().run(vp.problem())
    assert len(res.trajectory) == len(vp.frames)
    # measured (issue 18, benchmark scorer, loop closure + relaxation): 1.24 m, 157 trees,
    # 0 pairs < 1 m, 4 closures (before: 1.19 m / 151 trees; dead reckoning 11.1 m, EKF
    # 1.11 m / 163 trees, iSAM2 0.94 m / 160 trees)
    assert screened_ate(vp, res) < 1.6
    assert 120 < len(res.stem_map) < 190
    assert duplicate_pairs(res.stem_map, 1.0) <= 0.02 * len(res.stem_map)


@pytest.mark.slow
def test_scans_to_trunks_to_map_with_the_scan_detector():
    """Whole chain on a simulated drive: ray-cast scans -> ScanTrunkDetector -> TreeDbSlam."""
    from stemmap.scan.detect import ScanTrunkDetector

    stand = random_stand(90, (70.0, 56.0), min_spacing=2.0, rng=1)
    path = loop_path((35.0, 28.0), (20.0, 13.0), laps=1.2)
    run = simulate_run(
        stand, path, rate_hz=5.0, odometry_noise="wheel", corridor_half_width=2.5, rng=1
    )
    obs = ScanTrunkDetector().detect_batch(run.scans)
    frames = TreeFrames.from_observations(obs, run.scans.times)
    odo = run.odometry
    problem = SlamProblem(
        Controls(odo.times, odo.speed, odo.yaw_rate, "unicycle"),
        frames,
        UnicycleModel(sigma_speed=0.1, sigma_steer=math.radians(2.0)),
        initial_pose=tuple(run.vehicle_poses.poses[0]),
    )
    res = TreeDbSlam().run(problem)
    truth = run.vehicle_poses.poses
    rmse = np.sqrt(np.mean(np.sum((res.trajectory.poses[:, :2] - truth[:, :2]) ** 2, axis=1)))
    rmse_dr = np.sqrt(
        np.mean(np.sum((dead_reckoning(problem).poses[:, :2] - truth[:, :2]) ** 2, axis=1))
    )
    # measured 0.24 m vs 3.5 m dead reckoning
    assert rmse < rmse_dr / 5
    m = match_points(res.stem_map.xy, run.stand.trees_xy, 0.5)
    assert m.n_matched >= 0.8 * len(res.stem_map) and m.n_matched >= 20
    # diameters from the detector's circle fits: mean error a few mm (measured 4 mm)
    d_err = res.stem_map.diameters[m.pairs[:, 0]] - run.stand.diameters[m.pairs[:, 1]]
    assert np.mean(np.abs(d_err)) < 0.02


def test_treedb_rejects_controls_of_the_wrong_kind(sim):
    from stemmap.slam.motion import AckermannModel

    problem, _ = sim
    bad = type(problem)(problem.controls, problem.frames, AckermannModel())
    with pytest.raises(InputError, match="kind"):
        TreeDbSlam().run(bad)


# ------------------------------------------------------------------------------------------
# loop closure with the tree DB (issue 18)
# ------------------------------------------------------------------------------------------


def test_treedb_from_detections_is_what_the_updates_build(rng):
    from stemmap.slam.treedb import treedb_from_detections

    trees = rng.uniform(0, 30, (8, 2))
    db = TreeDb()
    zs, ds, ts, es = [], [], [], []
    for k in range(12):
        seen = rng.choice(8, 5, replace=False)
        z = trees[seen] + rng.normal(0, 0.05, (5, 2))
        d = np.where(rng.uniform(size=5) < 0.8, rng.uniform(0.2, 0.4, 5), np.nan)
        db, idx = treedb_update(db, z, d, float(k), gate=0.5)
        zs.append(z), ds.append(d), ts.append(np.full(5, float(k))), es.append(idx)
    re = treedb_from_detections(
        np.concatenate(zs), np.concatenate(ds), np.concatenate(ts), np.concatenate(es), len(db)
    )
    # eq. (2)'s running count-weighted average is the mean: rebuilding gives the same DB
    np.testing.assert_allclose(re.xy, db.xy, atol=1e-12)
    np.testing.assert_allclose(re.diameter, db.diameter, atol=1e-12)
    np.testing.assert_array_equal(re.count, db.count)
    np.testing.assert_array_equal(re.diameter_count, db.diameter_count)
    np.testing.assert_allclose(re.sq_dev, db.sq_dev, atol=1e-12)
    np.testing.assert_array_equal(re.first_time, db.first_time)
    np.testing.assert_array_equal(re.last_time, db.last_time)
    # an entry without detections (merged away) is empty
    e = np.concatenate(es)
    e[e == 0] = 1
    merged = treedb_from_detections(
        np.concatenate(zs), np.concatenate(ds), np.concatenate(ts), e, len(db)
    )
    assert merged.count[0] == 0 and np.isnan(merged.xy[0]).all()
    assert merged.count[1] == db.count[0] + db.count[1]


def test_treedb_gate_candidates_restrict_matching():
    db, _ = treedb_update(TreeDb(), [[0.0, 0.0], [5.0, 0.0]], None, 0.0)
    _, idx = treedb_update(db, [[0.1, 0.0]], None, 1.0, candidates=[False, True])
    assert idx.tolist() == [2]  # the only nearby entry is not a candidate: a new entry
    with pytest.raises(InputError):
        treedb_update(db, [[0.1, 0.0]], None, 1.0, candidates=[True])


def test_treedb_loop_closure_after_a_blind_stretch():
    from test_forestrix import blind_revisit

    problem, run = blind_revisit()
    truth = run.vehicle_poses.poses
    res = TreeDbSlam(loop_gap_s=20.0).run(problem)
    res0 = TreeDbSlam(loop_closure=False).run(problem)
    err = np.hypot(*(res.trajectory.poses[:, :2] - truth[:, :2]).T)
    err0 = np.hypot(*(res0.trajectory.poses[:, :2] - truth[:, :2]).T)
    # measured (seed 3): end error 5.8 m and 91 trees without loop closure; 0.21 m and 62
    # trees with it (the filter alone re-localises on old landmarks it can no longer gate)
    assert err0[-1] > 3.0
    assert err[-1] < 0.5
    assert res.stats["loop_closures"] >= 1
    assert len(res0.stem_map) > 1.3 * len(res.stem_map)
    m = match_points(res.stem_map.xy, run.stand.trees_xy, 0.5)
    assert m.n_matched >= 0.7 * len(res.stem_map)
