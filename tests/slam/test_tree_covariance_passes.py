"""The tree DB's / Forestrix's reported tree covariance with the detections' own covariances
correlated within a pass (Dec 6; stemmap.slam.tree_covariance module doc)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from test_treedb import sim_problem  # shared simulated loop (tests/slam/test_treedb.py)

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import TreeFrames
from stemmap.slam.forestrix import ForestrixSlam
from stemmap.slam.refine import world_observation_jacobians
from stemmap.slam.tree_covariance import (
    averaged_tree_covariances,
    mapped_tree_covariances,
    pass_groups,
)
from stemmap.slam.treedb import TreeDbSlam
from stemmap.types import StemObservations


def _spd(rng: np.random.Generator, n: int, d: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, d, d)) * scale
    return A @ np.swapaxes(A, 1, 2) + 1e-4 * np.eye(d)


def _random_case(seed: int = 0):
    rng = np.random.default_rng(seed)
    k, n_trees = 60, 5
    idx = rng.integers(-1, n_trees - 1, k)  # the last tree has no detection
    return idx, n_trees, rng.normal(size=(k, 2, 3)), _spd(rng, k, 3, 0.2), _spd(rng, k, 2, 0.1)


@pytest.mark.parametrize("weighted", [False, True])
def test_rho_zero_is_the_independent_covariance(weighted: bool) -> None:
    """rho 0 states the old covariance; a vanishing rho through the correlated path (passes,
    shared part) gives it too, to rounding: the new term is the old one's continuation."""
    idx, n, Jp, P, M = _random_case()
    info = np.linalg.inv(_spd(np.random.default_rng(1), idx.size, 2, 0.5)) if weighted else None
    old = averaged_tree_covariances(idx, n, Jp, P, M, information=info)
    t = np.arange(idx.size, dtype=float)
    kw = {"shared": M, "passes": pass_groups(idx, t, 10.0)}
    same = averaged_tree_covariances(idx, n, Jp, P, M, information=info, rho=0.0, **kw)
    tiny = averaged_tree_covariances(idx, n, Jp, P, M, information=info, rho=1e-300, **kw)
    np.testing.assert_array_equal(same, old)
    assert np.isnan(tiny[n - 1]).all()
    np.testing.assert_allclose(tiny[: n - 1], old[: n - 1], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("k", [2, 10, 100])
def test_n_perfectly_correlated_detections_state_one_detection(k: int) -> None:
    """n detections of one pass with the same covariance M, fully correlated (rho 1): the
    mean is no more precise than one detection, M; independent (rho 0): M / n; in between
    Kish's design effect M (1 + (n - 1) rho) / n. Exact poses (zero pose covariance)."""
    M = np.tile(np.array([[4e-4, 1e-4], [1e-4, 2e-4]]), (k, 1, 1))
    z = (np.zeros(k, np.int64), 1, np.zeros((k, 2, 3)), np.zeros((k, 3, 3)), M)
    one = averaged_tree_covariances(*z, rho=1.0)[0]
    np.testing.assert_allclose(one, M[0], rtol=1e-12)
    np.testing.assert_allclose(averaged_tree_covariances(*z)[0], M[0] / k, rtol=1e-12)
    half = averaged_tree_covariances(*z, rho=0.5)[0]
    np.testing.assert_allclose(half, M[0] * (1 + (k - 1) * 0.5) / k, rtol=1e-12)


def test_passes_are_independent_of_each_other() -> None:
    """Two passes of 20 detections each, fully correlated within a pass: the tree's mean is
    the average of two independent pass means, M / 2; one pass holding all 40: M. The pose
    term adds unchanged (it has its own correlation model)."""
    k = 40
    M = np.tile(np.eye(2) * 1e-3, (k, 1, 1))
    Jp = np.tile(np.array([[1.0, 0.0, -2.0], [0.0, 1.0, 3.0]]), (k, 1, 1))
    P = np.tile(np.diag([0.01, 0.02, 1e-4]), (k, 1, 1))
    idx = np.zeros(k, np.int64)
    t = np.r_[np.arange(20.0), 100.0 + np.arange(20.0)]
    two = averaged_tree_covariances(idx, 1, Jp, P, M, passes=pass_groups(idx, t, 5.0), rho=1.0)
    one = averaged_tree_covariances(idx, 1, Jp, P, M, rho=1.0)
    pose = Jp[0] @ P[0] @ Jp[0].T  # equal marginals: fully correlated, not shrunk by 1/n
    np.testing.assert_allclose(two[0], pose + M[0] / 2, rtol=1e-12)
    np.testing.assert_allclose(one[0], pose + M[0], rtol=1e-12)


def test_stated_covariance_matches_sampled_correlated_errors() -> None:
    """Detections of 3 passes, each detection's error the sum of an independent part and a
    part equicorrelated (rho 0.6) within its pass, different covariances per detection: the
    stated covariance of the weighted mean equals the covariance of 40 000 sampled means
    (relative standard error of a variance there ~0.7 %; 5 % tolerance), and treating the
    detections as independent states less than half of it."""
    rng = np.random.default_rng(4)
    k, rho = 24, 0.6
    idx = np.zeros(k, np.int64)
    passes = np.repeat(np.arange(3), 8)
    S = _spd(rng, k, 2, 0.05)
    A = _spd(rng, k, 2, 0.02)
    info = np.linalg.inv(A + S)
    zeros = (np.zeros((k, 2, 3)), np.zeros((k, 3, 3)))
    stated = averaged_tree_covariances(
        idx, 1, *zeros, A + S, information=info, shared=S, passes=passes, rho=rho
    )[0]
    indep = averaged_tree_covariances(idx, 1, *zeros, A + S, information=info)[0]
    W = np.linalg.inv(info.sum(axis=0)) @ info
    ev, V = np.linalg.eigh(S)
    root = (V * np.sqrt(ev)[:, None, :]) @ np.swapaxes(V, 1, 2)
    n_mc = 40000
    common = rng.normal(size=(n_mc, 3, 2))  # one per pass: correlation rho between detections
    own = rng.normal(size=(n_mc, k, 2))
    shared = math.sqrt(rho) * common[:, passes] + math.sqrt(1 - rho) * own
    err = np.einsum("kij,nkj->nki", root, shared) + np.einsum(
        "kij,nkj->nki", np.linalg.cholesky(A), rng.normal(size=(n_mc, k, 2))
    )
    mean = np.einsum("kij,nkj->ni", W, err)
    emp = np.cov(mean.T)
    np.testing.assert_allclose(stated, emp, rtol=0.05, atol=0.05 * np.abs(emp).max())
    assert np.trace(indep) < 0.5 * np.trace(emp)


def test_pass_groups_split_at_gaps_and_per_tree() -> None:
    idx = np.array([0, 1, 0, 0, 1, -1, 0])
    t = np.array([0.0, 0.0, 1.0, 9.0, 2.0, 3.0, 10.0])
    g = pass_groups(idx, t, 5.0)
    assert g[5] == -1
    assert g[0] == g[2] and g[3] == g[6] and g[0] != g[3]
    assert g[1] == g[4] and len({g[0], g[3], g[1]}) == 3
    with pytest.raises(InputError):
        pass_groups(idx, t[:3], 5.0)


def test_a_pass_across_two_trees_is_refused() -> None:
    M = np.tile(np.eye(2) * 1e-3, (4, 1, 1))
    z = (np.array([0, 0, 1, 1]), 2, np.zeros((4, 2, 3)), np.zeros((4, 3, 3)), M)
    with pytest.raises(InputError):
        averaged_tree_covariances(*z, passes=np.array([0, 0, 0, 1]), rho=0.5)


def test_from_observations_keeps_the_full_polar_covariance() -> None:
    """``noise_cov`` is ``J C Jᵀ`` whole: its diagonal's roots are ``noise`` (unchanged), and
    mapping it back with ``J_z`` (``J⁻¹``) gives the detector's x-y covariance, correlation
    included; frames selected keep it."""
    rng = np.random.default_rng(2)
    k = 12
    c = rng.uniform(1.0, 10.0, size=(k, 2)) * rng.choice([-1, 1], size=(k, 2))
    cov = np.full((k, 3, 3), np.nan)
    cov[:, :2, :2] = _spd(rng, k, 2, 0.02)
    cov[:, 2, 2] = 1e-4
    cov[3] = np.nan  # a detection without covariance
    one = np.ones(k)
    idx = np.repeat(np.arange(4), 3)
    obs = StemObservations(
        c, 0.1 * one, cov, np.full(k, 20), 90 * one, 0.2 * one, one, idx, idx.astype(float)
    )
    fr = TreeFrames.from_observations(obs, np.arange(4.0))
    assert fr.noise is not None and fr.noise_cov is not None
    np.testing.assert_allclose(np.sqrt(np.diagonal(fr.noise_cov, axis1=1, axis2=2)), fr.noise)
    assert np.isnan(fr.noise_cov[3]).all() and np.isnan(fr.noise[3]).all()
    _, Jz = world_observation_jacobians(np.zeros((k, 3)), fr.ranges, fr.bearings)
    back = Jz @ fr.noise_cov @ np.swapaxes(Jz, 1, 2)
    ok = np.arange(k) != 3
    np.testing.assert_allclose(back[ok], cov[ok, :2, :2], rtol=1e-9, atol=1e-15)
    sub = fr.select_frames(1, 3)
    assert sub.noise_cov is not None
    np.testing.assert_array_equal(sub.noise_cov, fr.noise_cov[3:9])
    with pytest.raises(InputError):
        TreeFrames(fr.times, fr.ptr, fr.ranges, fr.bearings, fr.diameters, noise_cov=np.zeros(3))


@pytest.fixture(scope="module")
def problem():
    """The shared simulated loop with every detection's true noise as its own covariance,
    diag(3 cm², 0.3°²), except every fifth detection (none)."""
    pb, _run = sim_problem(laps=0.6)
    fr = pb.frames
    nc = np.tile(np.diag([0.03**2, 0.005**2]), (fr.n_detections, 1, 1))
    nc[::5] = np.nan
    frames = dataclasses.replace(fr, noise_cov=nc)
    return dataclasses.replace(pb, frames=frames)


@pytest.mark.parametrize("cls", [TreeDbSlam, ForestrixSlam])
def test_backend_estimates_do_not_read_the_covariance_options(problem, cls) -> None:
    """Trajectory, tree positions and pose covariances are the same with the options off;
    own covariances equal to the constant noise with rho 0 give the old covariance."""
    on = cls().run(problem)
    off = cls(tree_cov_detections=False, tree_cov_pass_rho=0.0).run(problem)
    np.testing.assert_array_equal(on.trajectory.poses, off.trajectory.poses)
    np.testing.assert_array_equal(on.stem_map.xy, off.stem_map.xy)
    np.testing.assert_array_equal(on.pose_covs, off.pose_covs)
    c_on = np.array([t.cov for t in on.stem_map])
    c_off = np.array([t.cov for t in off.stem_map])
    assert not np.allclose(c_on, c_off)
    assert np.isfinite(c_on).all() and np.all(np.linalg.eigvalsh(c_on) > 0)
    cfg = cls()
    const = np.diag([cfg.sigma_range**2, cfg.sigma_bearing**2])
    fr = problem.frames
    same = dataclasses.replace(fr, noise_cov=np.tile(const, (fr.n_detections, 1, 1)))
    res = cls(tree_cov_pass_rho=0.0).run(dataclasses.replace(problem, frames=same))
    np.testing.assert_allclose(
        np.array([t.cov for t in res.stem_map]), c_off, rtol=1e-9, atol=1e-15
    )


def test_detections_without_own_covariance_are_not_correlated(problem) -> None:
    """pass_rho correlates only detections with their own covariance: with none, it changes
    nothing (Victoria Park's detections have none)."""
    pb = problem
    fr = pb.frames
    res = TreeDbSlam(tree_cov_pass_rho=0.0).run(pb)
    args = (res.stem_map.xy, res.trajectory.poses, res.pose_covs, fr.ptr, fr.ranges, fr.bearings)
    kw = {"sigma_range": 0.3, "sigma_bearing": math.radians(1.0), "gate": 0.5}
    none = np.full((fr.n_detections, 2, 2), np.nan)
    a, _ = mapped_tree_covariances(*args, **kw)
    b, _ = mapped_tree_covariances(*args, **kw, detection_covs=none, times=fr.times, pass_rho=0.9)
    np.testing.assert_array_equal(a, b)
    c, _ = mapped_tree_covariances(
        *args, **kw, detection_covs=fr.noise_cov, times=fr.times, pass_rho=0.9
    )
    d, _ = mapped_tree_covariances(*args, **kw, detection_covs=fr.noise_cov, times=fr.times)
    ok = np.isfinite(c[:, 0, 0])
    # correlating adds a positive semi-definite term
    assert np.all(np.linalg.eigvalsh(c[ok] - d[ok]) > -1e-15)
    with pytest.raises(InputError):
        mapped_tree_covariances(*args, **kw, detection_covs=fr.noise_cov, pass_rho=0.5)


@pytest.mark.parametrize("cls", [TreeDbSlam, ForestrixSlam])
def test_bad_pass_options_are_config_errors(cls) -> None:
    with pytest.raises(ConfigError):
        cls(tree_cov_pass_rho=1.5)
    with pytest.raises(ConfigError):
        cls(tree_cov_pass_gap_s=-1.0)
