"""Kalman refinement of tree positions in the map frame (Munjer 2025 §3.6)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import observation_to_world
from stemmap.slam.refine import (
    kalman_refine_trees,
    refine_stem_map,
    world_observation_covariance,
)
from stemmap.types import StemMap, Tree


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 12), st.integers(0, 10_000))
def test_static_kalman_equals_information_weighted_mean(k, seed):
    rng = np.random.default_rng(seed)
    z = rng.normal(0, 1, (k, 2))
    A = rng.normal(0, 0.5, (k, 2, 2))
    R = A @ np.swapaxes(A, 1, 2) + 0.05 * np.eye(2)
    out = kalman_refine_trees(z, R, np.zeros(k, dtype=int))
    info = np.linalg.inv(R).sum(axis=0)
    P = np.linalg.inv(info)
    x = P @ np.einsum("kij,kj->i", np.linalg.inv(R), z)
    # sequential KF with q = 0 is algebraically the batch information fusion
    np.testing.assert_allclose(out.xy[0], x, atol=1e-9)
    np.testing.assert_allclose(out.cov[0], P, atol=1e-9)
    assert out.n_obs.tolist() == [k]


def test_many_trees_vectorised_and_unassociated_skipped(rng):
    n, per = 30, 12
    truth = rng.uniform(0, 50, (n, 2))
    idx = np.repeat(np.arange(n), per)
    rng.shuffle(idx)
    sigma = 0.2
    z = truth[idx] + rng.normal(0, sigma, (idx.size, 2))
    idx_with_junk = idx.copy()
    idx_with_junk[:5] = -1  # unassociated detections are ignored
    R = np.broadcast_to(np.eye(2) * sigma**2, (idx.size, 2, 2))
    out = kalman_refine_trees(z, R, idx_with_junk, n)
    err = np.hypot(*(out.xy - truth).T)
    # each tree averages ~12 detections: error std ~ 0.2/sqrt(12) = 0.058 m per axis;
    # 5 sigma bound on the worst of 30 trees
    assert err.max() < 5 * sigma / math.sqrt(per - 5) * math.sqrt(2)
    np.testing.assert_allclose(out.cov[:, 0, 0], sigma**2 / out.n_obs, rtol=1e-9)


def test_process_noise_tracks_a_drifting_frame():
    # tree position jumps by 1 m halfway (map-frame drift): q > 0 follows, q = 0 averages
    z = np.vstack((np.zeros((50, 2)), np.ones((50, 2))))
    R = np.broadcast_to(np.eye(2) * 0.01, (100, 2, 2))
    fixed = kalman_refine_trees(z, R, np.zeros(100, int))
    follow = kalman_refine_trees(z, R, np.zeros(100, int), process_noise=0.01)
    np.testing.assert_allclose(fixed.xy[0], [0.5, 0.5], atol=1e-9)
    assert np.all(follow.xy[0] > 0.95)


def test_world_covariance_matches_monte_carlo(rng):
    pose = np.array([2.0, -1.0, 0.7])
    Sp = np.diag([0.05**2, 0.08**2, math.radians(1.5) ** 2])
    r, b, off = 12.0, 0.4, (3.78, 0.5)
    sr, sb = 0.1, math.radians(0.5)
    C = world_observation_covariance(
        pose[None], Sp, [r], [b], sigma_range=sr, sigma_bearing=sb, sensor_offset=off
    )[0]
    n = 40_000
    P = pose + rng.multivariate_normal(np.zeros(3), Sp, n)
    pts = observation_to_world(P, r + rng.normal(0, sr, n), b + rng.normal(0, sb, n), off)
    emp = np.cov(pts.T)
    # first-order propagation vs sampling: angles are small, agree to ~3 % (sampling error
    # of a 40k-sample covariance is ~1 %)
    np.testing.assert_allclose(C, emp, rtol=0.05, atol=1e-4)


def test_refine_bad_input():
    with pytest.raises(InputError):
        kalman_refine_trees(np.zeros((2, 2)), np.zeros((3, 2, 2)), [0, 0])
    with pytest.raises(InputError, match="finite"):
        kalman_refine_trees([[np.nan, 0]], [np.eye(2)], [0])
    with pytest.raises(InputError, match="n_trees"):
        kalman_refine_trees([[0.0, 0.0]], [np.eye(2)], [3], n_trees=2)
    with pytest.raises(ConfigError):
        kalman_refine_trees([[0.0, 0.0]], [np.eye(2)], [0], process_noise=-1.0)
    with pytest.raises(InputError):
        world_observation_covariance(
            np.zeros((2, 3)), np.eye(3), [1.0], [0.0], sigma_range=0.1, sigma_bearing=0.01
        )
    empty = kalman_refine_trees([[0.0, 0.0]], [np.eye(2)], [-1], n_trees=2)
    assert np.all(np.isnan(empty.xy)) and empty.n_obs.tolist() == [0, 0]


def test_refine_stem_map_moves_trees_to_the_detections_and_shrinks_covariance(rng):
    # two trees, a vehicle passing by; the map is 0.4 m off, detections are exact + 2 cm noise
    truth = np.array([[10.0, 3.0], [14.0, -2.0]])
    smap = StemMap(
        (
            Tree(0, 10.4, 3.0, 0.3, cov=np.eye(2)),
            Tree(1, 14.0, -2.4, 0.4, cov=np.eye(2)),
            Tree(2, 40.0, 40.0, 0.2, cov=np.eye(2)),  # never detected: unchanged
        )
    )
    poses = np.column_stack((np.linspace(0, 8, 20), np.zeros(20), np.zeros(20)))
    rel = truth[None, :, :] - poses[:, None, :2]
    r = np.hypot(rel[..., 0], rel[..., 1]).reshape(-1) + rng.normal(0, 0.02, 40)
    b = np.arctan2(rel[..., 1], rel[..., 0]).reshape(-1)
    ptr = np.arange(0, 41, 2)
    out = refine_stem_map(smap, poses, ptr, r, b, sigma_range=0.02, sigma_bearing=1e-3, gate=1.0)
    # 20 detections of 2 cm noise: within 2 cm of the truth (about 4 sigma of the mean)
    np.testing.assert_allclose(out.xy[:2], truth, atol=0.02)
    assert [t.n_obs for t in out] == [20, 20, 0]
    assert out.trees[2] is smap.trees[2]
    assert np.all(np.linalg.eigvalsh(out.trees[0].cov) < 1e-3)
    assert [t.diameter for t in out] == [0.3, 0.4, 0.2]
    with pytest.raises(InputError):
        refine_stem_map(smap, poses, ptr[:-1], r, b, sigma_range=0.1, sigma_bearing=0.01)
