"""Tree covariance with the observing poses' errors propagated and correlated (issue 14)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_treedb import sim_problem  # shared simulated loop (tests/slam/test_treedb.py)

from stemmap.errors import InputError
from stemmap.slam.refine import world_observation_jacobians
from stemmap.slam.tree_covariance import (
    associate_per_frame,
    averaged_tree_covariances,
    mapped_tree_covariances,
)


def _brute_force(idx, n_trees, Jp, P, M, info=None):
    """The double sum of the module doc, written out (cross-covariance
    ``rho_kl P_k^(1/2) P_l^(1/2)``, ``rho = sqrt(min(s) / max(s))``, ``s = tr P``)."""
    from scipy.linalg import sqrtm

    out = np.full((n_trees, 2, 2), np.nan)
    for t in range(n_trees):
        k = np.flatnonzero(idx == t)
        if k.size == 0:
            continue
        if info is None:
            W = [np.eye(2) / k.size for _ in k]
        else:
            tot = np.linalg.inv(sum(info[q] for q in k))
            W = [tot @ info[q] for q in k]
        c = np.zeros((2, 2))
        for a, qa in enumerate(k):
            c += W[a] @ M[qa] @ W[a].T
            for b, qb in enumerate(k):
                sa, sb = np.trace(P[qa]), np.trace(P[qb])
                rho = math.sqrt(min(sa, sb) / max(sa, sb))
                Pc = rho * np.real(sqrtm(P[qa])) @ np.real(sqrtm(P[qb]))
                c += W[a] @ Jp[qa] @ Pc @ Jp[qb].T @ W[b].T
        out[t] = c
    return out


def _random_spd(rng, n, d, scale=1.0):
    A = rng.normal(size=(n, d, d)) * scale
    return A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(d)


@pytest.mark.parametrize("weighted", [False, True])
def test_suffix_sums_equal_the_double_sum(weighted: bool) -> None:
    rng = np.random.default_rng(3)
    k, n_trees = 40, 5
    idx = rng.integers(-1, n_trees - 1, k)  # tree 4 has no detection, some are unassigned
    Jp = rng.normal(size=(k, 2, 3))
    P = _random_spd(rng, k, 3, 0.3)
    M = _random_spd(rng, k, 2, 0.1)
    info = np.linalg.inv(_random_spd(rng, k, 2, 0.5)) if weighted else None
    got = averaged_tree_covariances(idx, n_trees, Jp, P, M, information=info)
    want = _brute_force(idx, n_trees, Jp, P, M, info)
    assert np.isnan(got[4]).all() and np.isnan(want[4]).all()
    np.testing.assert_allclose(got[:4], want[:4], rtol=1e-9, atol=1e-12)


def test_random_walk_pose_error_monte_carlo() -> None:
    """A tree seen from 30 consecutive frames of a drive whose pose error is a random walk:
    the model (cross-covariance = the earlier frame's marginal) is the exact covariance of
    the mean, checked against 20 000 sampled drives; treating the frames as independent
    would be ~ 20x too small."""
    rng = np.random.default_rng(0)
    nf, q = 30, np.diag([0.02, 0.01, 1e-4])
    poses = np.column_stack((np.linspace(0.0, 6.0, nf), np.zeros(nf), np.zeros(nf)))
    tree = np.array([3.0, 4.0])
    rel = tree - poses[:, :2]
    r, b = np.hypot(rel[:, 0], rel[:, 1]), np.arctan2(rel[:, 1], rel[:, 0])
    Jp, Jz = world_observation_jacobians(poses, r, b)
    Rz = np.diag([0.03**2, math.radians(0.5) ** 2])
    M = Jz @ Rz @ np.swapaxes(Jz, 1, 2)
    P0 = np.diag([0.5, 0.5, 0.002])
    P = P0 + np.arange(nf)[:, None, None] * q  # marginals of the random walk
    idx = np.zeros(nf, dtype=np.int64)
    model = averaged_tree_covariances(idx, 1, Jp, P, M)[0]
    # sample: start error ~ P0, independent increments ~ q, detection noise ~ Rz
    n_mc = 20000
    L0, Lq = np.linalg.cholesky(P0), np.linalg.cholesky(q)
    dp = (rng.normal(size=(n_mc, 3)) @ L0.T)[:, None, :] + np.cumsum(
        np.concatenate((np.zeros((n_mc, 1, 3)), rng.normal(size=(n_mc, nf - 1, 3)) @ Lq.T), axis=1),
        axis=1,
    )
    v = rng.normal(size=(n_mc, nf, 2)) * np.sqrt(np.diag(Rz))
    err = np.einsum("fij,nfj->nfi", Jp, dp) + np.einsum("fij,nfj->nfi", Jz, v)
    emp = np.cov(err.mean(axis=1).T)
    np.testing.assert_allclose(model, emp, rtol=0.05, atol=2e-3)
    indep = sum(Jp[f] @ P[f] @ Jp[f].T + M[f] for f in range(nf)) / nf**2
    assert np.trace(indep) < 0.1 * np.trace(emp)


def test_n_equal_pose_errors_gain_nothing_from_n() -> None:
    """Seen n times from one pose error: the pose term does not shrink like 1/n."""
    Jp = np.tile(np.array([[1.0, 0.0, -4.0], [0.0, 1.0, 2.0]]), (50, 1, 1))
    P = np.tile(np.diag([0.1, 0.2, 0.001]), (50, 1, 1))
    M = np.tile(np.eye(2) * 0.01, (50, 1, 1))
    one = averaged_tree_covariances(np.zeros(1, np.int64), 1, Jp[:1], P[:1], M[:1])[0]
    many = averaged_tree_covariances(np.zeros(50, np.int64), 1, Jp, P, M)[0]
    pose_part = Jp[0] @ P[0] @ Jp[0].T
    np.testing.assert_allclose(many, pose_part + M[0] / 50, rtol=1e-12)
    assert np.trace(many) > 0.9 * np.trace(one)


def test_association_one_detection_per_tree_and_frame() -> None:
    trees = [[0.0, 0.0], [5.0, 0.0]]
    det = [[0.1, 0.0], [0.05, 0.0], [4.0, 0.0], [0.2, 0.0]]
    idx = associate_per_frame(trees, det, [0, 0, 0, 1], gate=0.5)
    assert idx.tolist() == [-1, 0, -1, 0]


def test_bad_shapes_are_input_errors() -> None:
    with pytest.raises(InputError):
        averaged_tree_covariances(
            [0, 0], 1, np.zeros((3, 2, 3)), np.zeros((2, 3, 3)), np.zeros((2, 2, 2))
        )
    with pytest.raises(InputError):
        mapped_tree_covariances(
            [[0.0, 0.0]],
            np.zeros((2, 3)),
            np.zeros((2, 3, 3)),
            [0, 1],
            [1.0],
            [0.0],
            sigma_range=0.1,
            sigma_bearing=0.01,
            gate=1.0,
        )


@pytest.fixture(scope="module")
def sim():
    return sim_problem()


@pytest.mark.parametrize("backend", ["treedb", "forestrix"])
def test_backend_tree_covariance_carries_the_pose_uncertainty(sim, backend: str) -> None:
    """The reported tree covariance holds the pose covariance of the frames that saw the tree:
    it is the model of :mod:`stemmap.slam.tree_covariance` at the reported pose covariances,
    far above what the detections alone give (zero pose covariance), and at least the pose
    term of the tree's best-known observing frame times the share of the correlated part.
    A covariance that ignores pose uncertainty (the old scatter / n, or per-frame independent
    pose errors shrinking like 1/n) fails the last two checks."""
    from stemmap.slam.base import make_backend

    problem, _run = sim
    res = make_backend(backend).run(problem)
    fr = problem.frames
    sm = res.stem_map
    cov = np.array([t.cov for t in sm])
    assert np.isfinite(cov).all() and np.all(np.linalg.eigvalsh(cov) > 0)
    cfg = make_backend(backend)
    gate = cfg.gate if backend == "treedb" else cfg.new_tree_gate
    args = (sm.xy, res.trajectory.poses)
    kw = {
        "sigma_range": cfg.sigma_range,
        "sigma_bearing": cfg.sigma_bearing,
        "sensor_offset": problem.sensor_offset,
        "gate": gate,
    }
    frm = (fr.ptr, fr.ranges, fr.bearings)
    no_pose, n = mapped_tree_covariances(*args, np.zeros((len(fr), 3, 3)), *frm, **kw)
    with_pose, _ = mapped_tree_covariances(*args, res.pose_covs, *frm, **kw)
    ok = n > 0
    if backend == "forestrix":  # equal weights: the reported one is exactly the model
        np.testing.assert_allclose(cov[ok], with_pose[ok], rtol=1e-9, atol=1e-15)
    ratio = np.trace(cov[ok], axis1=1, axis2=2) / np.trace(no_pose[ok], axis1=1, axis2=2)
    assert np.median(ratio) > 5.0
    # the least a tree can inherit: the position part of its least uncertain observing pose
    frame = fr.frame_index
    from stemmap.slam.base import observation_to_world

    z = observation_to_world(
        res.trajectory.poses[frame], fr.ranges, fr.bearings, problem.sensor_offset
    )
    idx = associate_per_frame(sm.xy, z, frame, gate)
    tr_pose = np.trace(res.pose_covs[frame][:, :2, :2], axis1=1, axis2=2)
    least = np.full(len(sm), np.inf)
    np.minimum.at(least, idx[idx >= 0], tr_pose[idx >= 0])
    tr = np.trace(cov, axis1=1, axis2=2)
    assert np.median(tr[ok] / least[ok]) > 0.5
