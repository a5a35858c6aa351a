"""Joint smoothing of the FastSLAM path and map (stemmap.slam._fastslam_smooth)."""

from __future__ import annotations

import math

import numpy as np
from test_ekf_smooth import _drifted_chain, _observe, _relative  # tests/slam on sys.path
from test_fastslam import _first_frames
from test_treedb import sim_problem

from stemmap.slam._ekf_smooth import _ODO_FLOOR, _PRIOR_INFO
from stemmap.slam._fastslam_smooth import smooth_joint
from stemmap.slam.base import dead_reckoning
from stemmap.slam.fastslam import FastSlam
from stemmap.slam.treedb import range_bearing_jacobians


def _turn(n: int = 150):
    th = np.linspace(0.0, 1.5, n)  # an 86 degree turn
    xy = np.column_stack((20 * np.sin(th), 20 * (1 - np.cos(th))))
    return np.column_stack((xy, th))


def test_smooth_joint_recovers_path_and_trees_from_a_drifted_start():
    """Exact odometry and exact range-bearing measurements: the least-squares poses and trees
    are the true ones, from a start where the path drifted (heading error growing to 6 deg)
    and the trees were mapped from that drifted path -- FastSLAM's state after a drift."""
    rng = np.random.default_rng(5)
    true = _turn()
    lm = rng.uniform(-30, 50, size=(50, 2))
    a, b = 3.78, 0.5
    obs = _observe(true, lm, (a, b), 25.0, 4)
    seen = np.unique(obs[1])
    keep = np.isin(obs[1], seen)
    remap = np.searchsorted(seen, obs[1][keep])
    obs = (obs[0][keep], remap, obs[2][keep], obs[3][keep])
    lm = lm[seen]
    deltas, covs, drift, start = _drifted_chain(true)
    # each tree where the drifted path at its first sighting put it
    first = np.array([obs[0][obs[1] == j].min() for j in range(lm.shape[0])])
    rot = drift[first]
    c, s = np.cos(rot), np.sin(rot)
    piv = true[first, :2]
    lm0 = piv + np.column_stack(
        (c * (lm[:, 0] - piv[:, 0]) - s * (lm[:, 1] - piv[:, 1]),
         s * (lm[:, 0] - piv[:, 0]) + c * (lm[:, 1] - piv[:, 1]))
    ) + (start[first, :2] - true[first, :2])  # fmt: skip
    R1 = np.diag([0.3**2, math.radians(1.0) ** 2])
    x, L, C, stats = smooth_joint(start, deltas, covs, obs, lm0, (a, b), R1)
    assert np.abs(lm0 - lm).max() > 1.0  # the start is metres off
    np.testing.assert_allclose(x[:, :2], true[:, :2], atol=1e-5)
    np.testing.assert_allclose(x[:, 2], true[:, 2], atol=1e-7)
    np.testing.assert_allclose(L, lm, atol=1e-5)
    # d2 "after" is taken at the last linearisation point, one step before the end
    assert stats["smoother_meas_d2_after"] < 1e-6 < 1.0 < stats["smoother_meas_d2_before"]
    assert C.shape == (lm.shape[0], 2, 2) and np.all(np.linalg.eigvalsh(C) > 0)


def test_smooth_joint_tree_covariance_is_the_marginal_of_the_information():
    """The tree covariances are the 2x2 blocks of the inverse of the whole (poses + trees)
    Gauss-Newton information, built here densely from the same Jacobians."""
    rng = np.random.default_rng(1)
    true = _turn(40)
    n = true.shape[0]
    lm = rng.uniform(-10, 30, size=(12, 2))
    a, b = 1.0, 0.2
    sig = (0.2, math.radians(1.0))
    fr, lj, rz, bz = _observe(true, lm, (a, b), 40.0, 12, rng, sig)
    seen = np.unique(lj)
    lm, lj = lm[seen], np.searchsorted(seen, lj)
    deltas = _relative(true[:-1], true[1:]) + rng.normal(0, [0.02, 0.02, 0.002], (n - 1, 3))
    covs = np.broadcast_to(np.diag([0.03**2, 0.03**2, 0.003**2]), (n - 1, 3, 3)).copy()
    R1 = np.diag(np.square(sig))
    # huber_k large: no down-weighting, the information is the plain Gauss-Newton one
    x, L, C, _ = smooth_joint(true, deltas, covs, (fr, lj, rz, bz), lm, (a, b), R1, huber_k=1e9)
    m = L.shape[0]
    nv = 3 * n + 2 * m
    H = np.zeros((nv, nv))
    H[:3, :3] += _PRIOR_INFO * np.eye(3)
    om = np.linalg.inv(covs + _ODO_FLOOR)
    for k in range(n - 1):  # odometry factor k -> k + 1, numerical Jacobian
        J = np.zeros((3, nv))
        for v in range(6):
            d = np.zeros(nv)
            d[3 * k + v] = 1e-6
            xp = (x.ravel() + d[: 3 * n]).reshape(n, 3)
            xm = (x.ravel() - d[: 3 * n]).reshape(n, 3)
            J[:, 3 * k + v] = (
                _relative(xp[k : k + 1], xp[k + 1 : k + 2])[0]
                - _relative(xm[k : k + 1], xm[k + 1 : k + 2])[0]
            ) / 2e-6
        H += J.T @ om[k] @ J
    _, Jv, Jl = range_bearing_jacobians(x[fr], L[lj], (a, b))
    W = np.linalg.inv(R1)
    for i in range(fr.size):
        J = np.zeros((2, nv))
        J[:, 3 * fr[i] : 3 * fr[i] + 3] = Jv[i]
        J[:, 3 * n + 2 * lj[i] : 3 * n + 2 * lj[i] + 2] = Jl[i]
        H += J.T @ W @ J
    Hinv = np.linalg.inv(H)
    want = np.array(
        [Hinv[3 * n + 2 * j : 3 * n + 2 * j + 2, 3 * n + 2 * j :][:, :2] for j in range(m)]
    )
    np.testing.assert_allclose(C, want, rtol=1e-5, atol=1e-12)


def test_fastslam_smoothing_uses_the_best_lineage_associations_and_closes_the_loop():
    """Every detection the best particle's lineage put into a mapped tree is one smoother
    measurement (so their count per tree is the tree's n_obs), and the smoothed loop is at
    least as good as the raw filter's."""
    problem, run = sim_problem(seed=2, laps=1.2)
    truth = run.vehicle_poses.poses
    fs = FastSlam(n_particles=30, seed=3, record_diagnostics=True)
    res = fs.run(problem)
    assert res.stats["smoother_measurements"] == sum(t.n_obs for t in res.stem_map)
    assert res.stats["smoother_meas_d2_after"] <= res.stats["smoother_meas_d2_before"]
    raw = fs.diagnostics["raw_trajectory"]
    off = FastSlam(n_particles=30, seed=3, smooth=False).run(problem)
    np.testing.assert_array_equal(raw, off.trajectory.poses)

    def rmse(p):
        return float(np.sqrt(np.mean(np.sum((p[:, :2] - truth[:, :2]) ** 2, axis=1))))

    dr = rmse(dead_reckoning(problem).poses)
    # measured: raw 0.2-0.3 m, smoothed below it; dead reckoning metres
    assert rmse(res.trajectory.poses) <= rmse(raw) + 0.02
    assert rmse(res.trajectory.poses) < min(0.5, dr / 4)
    assert res.pose_covs is not None and np.all(np.linalg.eigvalsh(res.pose_covs) > 0)
    for t in res.stem_map:
        assert np.all(np.linalg.eigvalsh(t.cov) > 0)


def test_smoothing_off_leaves_the_filter_output():
    problem, _ = sim_problem(seed=2, laps=1.2)
    sub = _first_frames(problem, 200)
    a = FastSlam(n_particles=20, seed=7, smooth=False).run(sub)
    assert not any(k.startswith("smoother") for k in a.stats)
