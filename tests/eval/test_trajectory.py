"""Trajectory metrics: SE(2) alignment, GPS screening, ATE, loop-closure error."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.eval.trajectory import align_se2, ate, loop_closure_error, rpe, screen_gps
from stemmap.types import Trajectory


@settings(max_examples=50, deadline=None)
@given(
    theta=st.floats(-math.pi, math.pi),
    tx=st.floats(-1e3, 1e3),
    ty=st.floats(-1e3, 1e3),
    seed=st.integers(0, 2**31),
)
def test_align_recovers_a_rigid_transform(theta, tx, ty, seed):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-50, 50, size=(30, 2))
    R = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    dst = src @ R.T + [tx, ty]
    al = align_se2(src, dst)
    np.testing.assert_allclose(al.apply(src), dst, atol=1e-8)


def test_align_is_least_squares_under_noise(rng):
    src = rng.uniform(-20, 20, size=(200, 2))
    dst = src + np.array([5.0, -3.0]) + rng.normal(scale=0.5, size=src.shape)
    al = align_se2(src, dst)
    res = np.sum((al.apply(src) - dst) ** 2)
    from stemmap.eval.trajectory import Se2Alignment

    for dth, dt in ((1e-3, (0, 0)), (0, (1e-3, 0)), (0, (0, -1e-3))):
        other = Se2Alignment(al.theta + dth, (al.t[0] + dt[0], al.t[1] + dt[1]))
        assert np.sum((other.apply(src) - dst) ** 2) > res  # any perturbation is worse
    with pytest.raises(InputError):
        align_se2(src[:1], dst[:1])
    with pytest.raises(InputError):
        align_se2(src, dst[:-1])


def _circle(n=400, r=20.0, T=100.0):
    t = np.linspace(0, T, n)
    a = 2 * math.pi * t / T
    poses = np.column_stack((r * np.sin(a), r - r * np.cos(a), a))
    return Trajectory(t, poses)


def test_ate_is_zero_for_a_rigidly_moved_copy_and_scores_every_fix(rng):
    tr = _circle()
    gt = tr.times[::4]
    ref = tr.xy[::4] @ np.array([[0, -1], [1, 0]]).T + [100, 50]
    r = ate(tr, gt, ref)
    assert r and r.rmse < 1e-9 and r.n == gt.size
    # one bad stretch cannot be trimmed away: 10 fixes 5 m off raise the max to ~5 m
    bad = ref.copy()
    bad[10:20] += [5.0, 0.0]
    r2 = ate(tr, gt, bad)
    assert r2.n == gt.size and r2.max > 4.0
    assert r2.rmse == pytest.approx(math.sqrt(np.mean(r2.errors**2)))
    # no overlap -> falsy result with a reason
    r3 = ate(tr, gt + 1000, ref)
    assert not r3 and "overlap" in r3.reason


def test_screen_gps_rejects_jumps_and_keeps_a_consistent_track(rng):
    t = np.arange(0, 60, 0.2)
    xy = np.column_stack((3 * t, np.zeros_like(t)))  # 3 m/s straight
    dist = 3 * t
    gps = xy + rng.normal(scale=0.05, size=xy.shape)
    gps[50] += [8.0, 0]  # a single spike
    gps[100:110] += [0, 6.0]  # a 2-second offset jump
    s = screen_gps(t, gps, xy, dist)
    assert not s.keep[50] and not np.any(s.keep[100:110])
    assert s.keep[51] and s.keep[110]  # comes back once the GPS agrees again
    assert s.n_kept == t.size - 11
    with pytest.raises(InputError):
        screen_gps(t, gps[:-1], xy, dist)


def test_screen_gps_accepts_a_turn_across_an_outage():
    # quarter circle of radius 10 m driven in 10 s with the GPS out in between
    a = np.linspace(0, math.pi / 2, 51)
    xy = np.column_stack((10 * np.sin(a), 10 - 10 * np.cos(a)))
    dist = 10 * a
    t = np.linspace(0, 10, 51)
    idx = np.array([0, 1, 49, 50])
    s = screen_gps(t[idx], xy[idx], xy[idx], dist[idx])
    assert s.keep.all()  # chord 14.1 m < arc 15.7 m: displacement matches the odometry


def test_loop_closure_error():
    tr = _circle()
    assert loop_closure_error(tr) < 1e-9
    poses = tr.poses.copy()
    poses[-1, :2] += [0.3, 0.4]
    assert loop_closure_error(Trajectory(tr.times, poses)) == pytest.approx(0.5)
    # with a known displacement expressed in the start pose's frame
    line = Trajectory([0.0, 1.0], [[0, 0, math.pi / 2], [0, 5, math.pi / 2]])
    assert loop_closure_error(line, (5.0, 0.0)) == pytest.approx(0.0, abs=1e-12)


def _line(t, x, theta):
    return Trajectory(np.asarray(t, float), np.column_stack((x, np.zeros_like(t), theta)))


def test_rpe_scale_drift_hand_computed():
    # reference: 1 m/s along x; estimate runs 10 % long. Stretches of 5 m: pairs (0,5), (5,10);
    # each estimated stretch is 5.5 m straight ahead, so E = (0.5, 0, 0) for both.
    t = np.arange(11.0)
    ref = _line(t, t, np.zeros(11))
    est = _line(t, 1.1 * t, np.zeros(11))
    r = rpe(est, ref, delta=5.0)
    assert r.n == 2
    np.testing.assert_allclose(r.trans_errors, [0.5, 0.5], atol=1e-12)
    np.testing.assert_allclose(r.rot_errors_deg, [0.0, 0.0], atol=1e-12)
    assert r.trans_rmse == pytest.approx(0.5)
    d = r.as_dict()
    assert d["rpe_trans_rmse_m"] == pytest.approx(0.5) and d["rpe_delta_unit"] == "m"


def test_rpe_heading_drift_hand_computed():
    # same positions, heading drifts 0.02 rad/s. Pair (0,5): P_0^-1 P_5 = (5, 0, 0.1) against
    # (5, 0, 0): translation error 0, rotation 0.1 rad. Pair (5,10): seen from P_5 (heading
    # 0.1) the 5 m step is (5 cos 0.1, -5 sin 0.1): |(5 cos 0.1 - 5, -5 sin 0.1)| = 10 sin 0.05.
    t = np.arange(11.0)
    ref = _line(t, t, np.zeros(11))
    est = _line(t, t, 0.02 * t)
    r = rpe(est, ref, delta=5.0)
    np.testing.assert_allclose(r.trans_errors, [0.0, 10 * math.sin(0.05)], atol=1e-12)
    np.testing.assert_allclose(r.rot_errors_deg, [math.degrees(0.1)] * 2, atol=1e-10)
    # time stretches of 2 s: pairs (0,2), (2,4), ... (8,10)
    rt = rpe(est, ref, delta=2.0, delta_unit="s")
    assert rt.n == 5
    np.testing.assert_allclose(rt.rot_errors_deg, [math.degrees(0.04)] * 5, atol=1e-10)


def test_rpe_identical_is_zero_and_bad_input():
    t = np.linspace(0, 20, 41)
    ref = Trajectory(t, np.column_stack((np.cos(t / 5) * 10, np.sin(t / 5) * 10, t / 5 + 1.5)))
    r = rpe(ref, ref, delta=3.0)
    assert r.n > 3 and r.trans_max < 1e-9 and r.rot_max_deg < 1e-9
    short = rpe(ref, ref, delta=1e4)
    assert not short and "shorter" in short.reason
    with pytest.raises(ConfigError):
        rpe(ref, ref, delta=0.0)
    with pytest.raises(ConfigError):
        rpe(ref, ref, delta_unit="frames")
