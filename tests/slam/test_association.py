"""Association: Mahalanobis gating, greedy nearest neighbour, JCBB."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.slam.association import (
    chi2_gate,
    individual_compatibility,
    jcbb,
    joint_nis,
    nearest_neighbour,
)


def test_individual_compatibility_matches_direct_formula(rng):
    k, c = 3, 4
    nu = rng.normal(size=(k, c, 2))
    A = rng.normal(size=(2 * c, 2 * c))
    C = A @ A.T + np.eye(2 * c)
    R = np.array([[0.2, 0.05], [0.05, 0.1]])
    extra = rng.uniform(0, 2, size=(k, c))
    d2 = individual_compatibility(nu, C, R, extra)
    for i in range(k):
        for j in range(c):
            S = C[2 * j : 2 * j + 2, 2 * j : 2 * j + 2] + R
            ref = nu[i, j] @ np.linalg.solve(S, nu[i, j]) + extra[i, j]
            assert d2[i, j] == pytest.approx(ref, rel=1e-12)


def test_nearest_neighbour_is_one_to_one_and_gated():
    d2 = np.array([[1.0, 2.0], [0.5, 8.0], [20.0, 30.0]])
    a = nearest_neighbour(d2, gate=9.21)
    # pair (1, 0) is the best, so observation 0 takes landmark 1; observation 2 is gated out
    np.testing.assert_array_equal(a, [1, 0, -1])


def _common_shift_case():
    """Two landmarks 1 m apart on x; both observations shifted +0.6 m by one pose error.

    Predicted-measurement covariance: a common pose term (sigma 1 m on x, fully correlated
    between the landmarks) plus 0.05 m independent noise.
    """
    pred = np.array([[0.0, 0.0], [1.0, 0.0]])  # landmark predictions
    z = np.array([[0.6, 0.0], [1.6, 0.0]])  # observations
    nu = z[:, None, :] - pred[None, :, :]
    common = np.zeros((4, 4))
    for a in (0, 2):
        for b in (0, 2):
            common[a, b] = 1.0
    C = common + 0.05**2 * np.eye(4)
    R = 0.05**2 * np.eye(2)
    return nu, C, R


def test_jcbb_uses_the_correlation_nn_cannot_see():
    nu, C, R = _common_shift_case()
    d2 = individual_compatibility(nu, C, R)
    nn = nearest_neighbour(d2, chi2_gate(0.99, 2))
    # greedy NN takes the closest pair first (observation 0 -> landmark 1, 0.4 m) and is left
    # with the crossed pairing; the common 0.6 m shift is invisible pair by pair
    np.testing.assert_array_equal(nn, [1, 0])
    jc = jcbb(nu, C, R, alpha=0.99)
    np.testing.assert_array_equal(jc, [0, 1])
    # the joint hypothesis is far more consistent than the crossed one
    assert joint_nis([(0, 0), (1, 1)], nu, C, np.stack([R, R])) < 1.0


def test_jcbb_diameter_cue_breaks_ties():
    nu = np.zeros((1, 2, 2))
    C = 0.1 * np.eye(4)
    R = 0.01 * np.eye(2)
    extra = np.array([[15.0, 0.1]])  # landmark 0 has a very different diameter
    np.testing.assert_array_equal(jcbb(nu, C, R, extra_d2=extra, extra_dof=1), [1])


def test_bad_inputs():
    with pytest.raises(InputError):
        individual_compatibility(np.zeros((2, 3)), np.eye(6), np.eye(2))
    with pytest.raises(InputError):
        individual_compatibility(np.zeros((2, 3, 2)), np.eye(4), np.eye(2))
    with pytest.raises(InputError):
        jcbb(np.zeros((2, 1, 2)), np.eye(2), np.zeros((3, 2, 2)))
    with pytest.raises(ConfigError):
        chi2_gate(1.5, 2)
    assert chi2_gate(0.99, 2) == pytest.approx(9.2103, abs=1e-4)


def test_joint_nis_equals_the_block_by_block_construction(rng):
    # the R blocks are added with one fancy-indexed addition per entry: same values, bit for bit,
    # as adding R_t block by block (the form before the speed-up)
    k, c = 5, 6
    nu = rng.normal(size=(k, c, 2))
    A = rng.normal(size=(2 * c, 2 * c))
    C = A @ A.T + np.eye(2 * c)
    R = rng.uniform(0.05, 0.3, size=(k, 2, 2))
    R = 0.5 * (R + R.transpose(0, 2, 1)) + np.eye(2)
    extra = rng.uniform(0, 2, size=(k, c))
    pairs = [(0, 3), (2, 0), (3, 5), (4, 1)]
    obs = np.array([p[0] for p in pairs])
    cand = np.array([p[1] for p in pairs])
    rows = np.stack((2 * cand, 2 * cand + 1), axis=1).reshape(-1)
    S = C[np.ix_(rows, rows)].copy()
    for t in range(len(pairs)):
        S[2 * t : 2 * t + 2, 2 * t : 2 * t + 2] += R[obs[t]]
    v = nu[obs, cand].reshape(-1)
    ref = float(v @ np.linalg.solve(S, v)) + float(extra[obs, cand].sum())
    assert joint_nis(pairs, nu, C, R, extra) == ref
    assert joint_nis([], nu, C, R, extra) == 0.0


def _nn_reference(D, gate):
    # the pure-Python greedy assignment the compiled kernel replaced
    assign = np.full(D.shape[0], -1, dtype=np.int64)
    ii, jj = np.nonzero(gate > D)
    used_i, used_j = set(), set()
    for t in np.argsort(D[ii, jj], kind="stable"):
        i, j = int(ii[t]), int(jj[t])
        if i not in used_i and j not in used_j:
            assign[i] = j
            used_i.add(i)
            used_j.add(j)
    return assign


def test_nearest_neighbour_equals_the_python_greedy_loop(rng):
    for _ in range(200):
        k, c = rng.integers(1, 9), rng.integers(1, 12)
        D = rng.choice([0.5, 1.0, 2.0, 7.0], size=(k, c)) if rng.random() < 0.3 else None
        if D is None:  # ties above, continuous values here
            D = rng.exponential(4.0, size=(k, c))
        D[rng.random((k, c)) < 0.1] = np.nan
        np.testing.assert_array_equal(nearest_neighbour(D, 6.0), _nn_reference(D, 6.0))
    assert nearest_neighbour(np.zeros((3, 0)), 6.0).tolist() == [-1, -1, -1]


def test_joint_nis_of_a_singular_covariance_is_infinite():
    nu = np.ones((2, 2, 2))
    C = np.zeros((4, 4))
    assert joint_nis([(0, 0), (1, 1)], nu, C, np.zeros((2, 2, 2))) == np.inf
