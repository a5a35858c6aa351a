"""Loop closure and trajectory relaxation (Öhman 2007 §2.1-2.2; relaxation, loop_closure)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.slam.loop_closure import LoopCloser, LoopConfig, close_duplicates, find_loop_closure
from stemmap.slam.motion import between, compose
from stemmap.slam.relaxation import (
    LoopClosure,
    RelaxNoise,
    fit_rigid_robust,
    loop_constraint,
    relax_trajectory,
    relaxed_pose_covariances,
    remap_trees,
)


def _rigid(xy, dth, t):
    c, s = math.cos(dth), math.sin(dth)
    return np.asarray(xy) @ np.array([[c, s], [-s, c]]) + np.asarray(t)


def _circle(n=200, radius=20.0):
    """True poses around a circle (one lap) and a drifted copy (a heading bias per step)."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    truth = np.column_stack(
        (radius * np.cos(ang), radius * np.sin(ang), ang + np.pi / 2)
    )  # heading tangent
    inc = between(truth[:-1], truth[1:])
    bias = np.array([0.0, 0.0, math.radians(0.05)])  # 10 deg over the lap
    drift = [truth[0]]
    for d in inc:
        drift.append(compose(drift[-1], d + bias))
    return truth, np.array(drift)


def test_relaxation_closes_a_drifted_loop_and_spreads_the_error():
    truth, drift = _circle()
    n = truth.shape[0]
    kf = np.arange(0, n, 4)
    # the revisit measures the last pose relative to the first exactly (as a true closure does)
    lc = LoopClosure(0, n - 1, tuple(between(truth[0], truth[-1])))
    out = relax_trajectory(drift, kf, [lc])
    err_before = np.hypot(*(drift[:, :2] - truth[:, :2]).T)
    err_after = np.hypot(*(out[:, :2] - truth[:, :2]).T)
    # drift at the end 3.4 m; after relaxation the end is within the loop sigma (0.3 m) ...
    assert err_before[-1] > 3.0
    assert err_after[-1] < 0.3
    # ... and the error is spread, not dumped at the closing edge: the whole lap improves
    assert np.sqrt(np.mean(err_after**2)) < 0.25 * np.sqrt(np.mean(err_before**2))
    # the closure holds in the relaxed trajectory
    got = between(out[0], out[-1])
    np.testing.assert_allclose(got[:2], lc.delta[:2], atol=0.3)
    # no loops: unchanged; input untouched
    np.testing.assert_array_equal(relax_trajectory(drift, kf, []), drift)
    assert not np.shares_memory(out, drift)


def test_relaxation_puts_the_error_where_the_map_did_not_correct():
    truth, _ = _circle()
    n = truth.shape[0]
    inc = between(truth[:-1], truth[1:])
    # scan-matched everywhere except frames 100-130 (dead reckoning with a heading bias there)
    drift = [truth[0]]
    for k, d in enumerate(inc):
        bad = 100 <= k + 1 <= 130
        drift.append(compose(drift[-1], d + (np.array([0, 0, math.radians(0.4)]) if bad else 0)))
    drift = np.array(drift)
    cov = np.zeros((n, 3, 3))
    cov[100:131] = np.diag([0.05**2, 0.05**2, math.radians(0.5) ** 2])
    kf = np.arange(0, n, 4)
    lc = [LoopClosure(0, n - 1, tuple(between(truth[0], truth[-1])))]
    even = relax_trajectory(drift, kf, lc)
    aware = relax_trajectory(drift, kf, lc, odometry_cov=cov)
    e_even = np.hypot(*(even[:, :2] - truth[:, :2]).T)
    e_aware = np.hypot(*(aware[:, :2] - truth[:, :2]).T)
    # the part before the blind stretch was right: spreading the error evenly bends it more
    # (measured: max error there 0.62 m evenly, 0.37 m with the covariance)
    assert e_aware[:100].max() < 0.7 * e_even[:100].max()
    assert np.sqrt(np.mean(e_aware**2)) < np.sqrt(np.mean(e_even**2))


def test_a_wrong_closure_is_down_weighted_by_the_robust_kernel():
    truth, drift = _circle()
    n = truth.shape[0]
    kf = np.arange(0, n, 4)
    good = LoopClosure(0, n - 1, tuple(between(truth[0], truth[-1])))
    wrong = LoopClosure(50, 150, (0.0, 0.0, 0.0))  # claims two far-apart poses coincide
    out = relax_trajectory(drift, kf, [good, wrong])
    err = np.hypot(*(out[:, :2] - truth[:, :2]).T)
    # with a quadratic cost the wrong closure would pull poses 50 and 150 (40 m apart) together
    assert np.hypot(*(out[50, :2] - out[150, :2])) > 30.0
    assert err[-1] < 1.0


def test_relaxation_bad_input():
    with pytest.raises(InputError):
        relax_trajectory(np.zeros((5, 3)), [1, 2], [LoopClosure(0, 4, (0, 0, 0))])
    with pytest.raises(InputError):
        relax_trajectory(np.zeros((5, 3)), [0, 2], [LoopClosure(0, 9, (0, 0, 0))])
    with pytest.raises(ConfigError):
        RelaxNoise(xy_base=0.0)


def test_fit_rigid_robust_ignores_wrong_pairs(rng):
    src = rng.uniform(-20, 20, (12, 2))
    dst = _rigid(src, math.radians(4.0), (3.0, -2.0)) + rng.normal(0, 0.05, (12, 2))
    dst[[2, 7]] += [5.0, -4.0]  # two wrong correspondences
    fit = fit_rigid_robust(src, dst)
    assert fit and fit.inliers is not None
    assert set(fit.inliers.tolist()) == set(range(12)) - {2, 7}
    assert abs(math.degrees(fit.dtheta) - 4.0) < 0.3
    assert fit.rms < 0.1
    assert not fit_rigid_robust(src[:4], dst[:4])  # too few pairs
    noisy = fit_rigid_robust(src, dst + rng.normal(0, 0.6, dst.shape), max_rms=0.2)
    assert not noisy and "rms" in noisy.reason


def test_loop_constraint_is_the_pose_the_fit_implies():
    old, new = np.array([1.0, 2.0, 0.3]), np.array([5.0, 1.0, 1.2])
    fit = fit_rigid_robust(
        np.array([[0, 0], [3, 0], [0, 4], [2, 2], [5, 1]], float),
        _rigid(np.array([[0, 0], [3, 0], [0, 4], [2, 2], [5, 1]], float), 0.1, (1.0, 0.5)),
    )
    d = loop_constraint(old, new, fit)
    np.testing.assert_allclose(compose(old, np.asarray(d)), fit.apply_pose(new), atol=1e-12)


def _revisit(rng, n_old=120, size=60.0, radius=12.0, dth=3.0, shift=(6.0, -2.0)):
    """An old map, and the trees of one area of it mapped again with a drift (rotation about
    the area's centre + shift) and 5 cm noise, plus 3 new trees."""
    old = rng.uniform(0, size, (n_old, 2))
    c = np.array([size / 2, size / 2])
    seen = np.flatnonzero(np.hypot(*(old - c).T) <= radius)
    recent = _rigid(old[seen] - c, math.radians(dth), shift) + c
    recent = recent + rng.normal(0, 0.05, recent.shape)
    recent = np.vstack((recent, c + rng.uniform(-radius, radius, (3, 2))))
    return old, seen, recent


def test_find_loop_closure_recognises_a_drifted_revisit(rng):
    # 6.3 m and 3 deg off: beyond the 2 m scan-to-map search, within the loop search
    old, seen, recent = _revisit(rng)
    lm = find_loop_closure(recent, old, search_radius=10.0)
    assert lm
    pairs = dict(zip(lm.recent.tolist(), lm.old.tolist(), strict=True))
    assert len(pairs) >= 0.7 * seen.size
    assert all(pairs[k] == seen[k] for k in pairs if k < seen.size)
    assert abs(math.degrees(lm.fit.dtheta) + 3.0) < 0.5
    # an unrelated stand of the same density is not a revisit
    c = np.array([30.0, 30.0])
    other = c + rng.uniform(-12, 12, (recent.shape[0], 2))
    assert not find_loop_closure(other, old, search_radius=10.0)
    # a drift beyond the search radius is not recognised (the radius bounds it)
    assert not find_loop_closure(recent + np.array([15.0, 0.0]), old, search_radius=5.0)


def test_loop_closer_records_a_constraint_and_returns_the_pairs(rng):
    old_xy, seen, recent_xy = _revisit(rng, dth=2.0, shift=(3.0, 1.0))
    recent_xy = recent_xy[: seen.size]
    n_old, n_new = old_xy.shape[0], seen.size
    xy = np.vstack((old_xy, recent_xy))
    n = xy.shape[0]
    first = np.r_[np.zeros(n_old), np.full(n_new, 95.0)]
    last = np.r_[np.zeros(n_old), np.full(n_new, 99.0)]
    count = np.full(n, 6)
    times = np.arange(0.0, 100.2, 0.2)
    poses = np.zeros((times.size, 3))
    poses[:, 0] = np.linspace(0, 50, times.size)
    lc = LoopCloser(LoopConfig(search_radius=8.0), times)
    f = times.size - 1
    assert lc.due(times[f]) and not lc.due(times[f])  # at most every every_s
    found = lc.detect(f, poses, np.array([30.0, 30.0]), xy, first, last, count, np.ones(n, bool))
    assert found is not None
    src, dst = found
    assert src.size >= 0.7 * n_new
    np.testing.assert_array_equal(dst, seen[src - n_old])
    assert len(lc.loops) == 1 and lc.loops[0].i == f and lc.loops[0].j == 0
    assert lc.keyframes[-1] == f
    # old trees seen fewer than old_min_count times take no part
    lc2 = LoopCloser(LoopConfig(search_radius=8.0), times)
    assert lc2.detect(f, poses, np.array([30.0, 30.0]), xy, first, last, count,
                      np.ones(n, bool), old_min_count=7) is None  # fmt: skip


def test_close_duplicates_and_remap():
    xy = np.array([[0.0, 0.0], [0.3, 0.0], [5.0, 5.0], [5.2, 5.0]])
    src, dst = close_duplicates(xy, np.array([0.3, 0.32, 0.3, 0.9]), [5, 9, 3, 3],
                                np.ones(4, bool), 1.0, 0.42)  # fmt: skip
    # 0 and 1 are one tree (kept: the more-seen 1); 2 and 3 differ in diameter but overlap
    assert dict(zip(src.tolist(), dst.tolist(), strict=True)) in ({0: 1, 3: 2}, {0: 1, 2: 3})
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    out, cnt = remap_trees(poses, [0, 1, 1], [2.0, 1.0, 3.0], [0.0, 0.0, 0.0], [0, 0, 1], 3)
    np.testing.assert_allclose(out[0], [2.0, 0.0])
    np.testing.assert_allclose(out[1], [4.0, 0.0])
    assert np.isnan(out[2]).all() and cnt.tolist() == [2, 1, 0]


def test_relaxed_pose_covariances_propagate_the_chain_and_shrink_at_a_loop():
    """Issue 14, tree DB / Forestrix pose covariance: the marginals of the relaxation's pose
    graph. Straight drive along x, keyframes 2 m apart, a frame halfway between: without
    loops the along-track variance is the prior plus the chain's sigma² per edge
    ((0.05 + 0.02 * 2)² m²), the frame between carries its keyframe's plus the partial edge
    ((0.05 + 0.02 * 1)²); the cross-track variance grows faster (heading lever arm). A loop
    constraint from the last keyframe back to the first pulls the end's covariance down to
    about the constraint's own (0.3 m, 1 deg). ``chain_variance_factor`` scales the chain
    alone: a dead-reckoned frame's odometry covariance (0.5 m² along track, frame 3) is
    added unscaled."""
    nk = 15
    xs = np.arange(0.0, 2.0 * nk - 1.0, 1.0)  # frames every 1 m, keyframes every 2 m
    poses = np.column_stack((xs, np.zeros_like(xs), np.zeros_like(xs)))
    kf = np.arange(0, xs.size, 2)
    cov = relaxed_pose_covariances(poses, kf, [])
    assert np.isfinite(cov).all() and np.all(np.linalg.eigvalsh(cov) > 0)
    edge = (0.05 + 0.02 * 2.0) ** 2
    for k, f in enumerate(kf):
        assert cov[f, 0, 0] == pytest.approx(1e-8 + k * edge, rel=1e-6)
        if f + 1 < xs.size:
            assert cov[f + 1, 0, 0] == pytest.approx(1e-8 + k * edge + 0.07**2, rel=1e-6)
    assert np.all(np.diff(cov[kf, 1, 1]) > 0) and cov[kf[-1], 1, 1] > cov[kf[-1], 0, 0]
    loop = LoopClosure(0, int(kf[-1]), tuple(between(poses[0], poses[kf[-1]])))
    closed = relaxed_pose_covariances(poses, kf, [loop])
    end = int(kf[-1])
    assert closed[end, 1, 1] < 0.2 * cov[end, 1, 1]
    assert closed[end, 0, 0] < 0.3**2 and closed[end, 1, 1] < 2 * 0.3**2
    assert np.all(closed[kf, 0, 0] <= cov[kf, 0, 0] + 1e-12)
    # the factor scales the chain's variances only, not the dead-reckoned odometry's
    odo = np.zeros((xs.size, 3, 3))
    odo[3, 0, 0] = 0.5
    c4 = relaxed_pose_covariances(poses, kf, [], odometry_cov=odo, chain_variance_factor=4.0)
    assert c4[kf[-1], 0, 0] == pytest.approx(1e-8 + 4 * (nk - 1) * edge + 0.5, rel=1e-6)
    assert c4[kf[1], 0, 0] == pytest.approx(1e-8 + 4 * edge, rel=1e-6)  # before frame 3
    assert c4[kf[2], 0, 0] == pytest.approx(1e-8 + 8 * edge + 0.5, rel=1e-6)
