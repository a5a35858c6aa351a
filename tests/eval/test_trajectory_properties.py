"""Properties of the trajectory metrics that the first tests left open (found by mutation
testing, docs/reliability.md "Mutation testing"): RPE against a homogeneous-matrix reference
on turning paths, lever-arm offsets, the GPS screen's inclusive limits and start rule, the
ATE keep mask and time span, the failure results, and the messages."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from stemmap.errors import ConfigError, InputError
from stemmap.eval.trajectory import (
    AteResult,
    RpeResult,
    Se2Alignment,
    align_se2,
    ate,
    loop_closure_error,
    point_track,
    rpe,
    screen_gps,
)
from stemmap.types import Trajectory


def _hom(p):
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]])


def _wiggly(n=60, seed=0, t0=100.0, dt=0.5):
    rng = np.random.default_rng(seed)
    t = t0 + dt * np.arange(n)
    th = np.cumsum(rng.normal(0.0, 0.15, n)) + 0.7
    step = 0.8 + 0.4 * rng.random(n)
    xy = np.cumsum(step[:, None] * np.column_stack((np.cos(th), np.sin(th))), axis=0)
    return Trajectory(t, np.column_stack((xy + np.array([30.0, -12.0]), th)))


def test_rpe_equals_the_matrix_definition_on_turning_paths():
    ref = _wiggly(seed=1)
    rng = np.random.default_rng(2)
    noisy = ref.poses + rng.normal(0.0, [0.05, 0.05, 0.02], ref.poses.shape)
    est = Trajectory(ref.times, noisy)
    for delta, unit in ((7.0, "m"), (4.0, "s")):
        r = rpe(est, ref, delta=delta, delta_unit=unit)
        # the pairs by the documented rule: j = first pose >= delta past i along the reference
        q = ref.poses
        if unit == "m":
            along = np.r_[0.0, np.cumsum(np.hypot(*np.diff(q[:, :2], axis=0).T))]
        else:
            along = ref.times - ref.times[0]
        ids = [0]
        while True:
            k = int(np.searchsorted(along, along[ids[-1]] + delta - 1e-12))
            if k >= len(along):
                break
            ids.append(k)
        et, er = [], []
        for i, j in itertools.pairwise(ids):
            dq = np.linalg.inv(_hom(q[i])) @ _hom(q[j])
            dp = np.linalg.inv(_hom(noisy[i])) @ _hom(noisy[j])
            E = np.linalg.inv(dq) @ dp
            et.append(math.hypot(E[0, 2], E[1, 2]))
            er.append(abs(math.degrees(math.atan2(E[1, 0], E[0, 0]))))
        et_a, er_a = np.array(et), np.array(er)
        assert r.n == len(et) >= 3
        np.testing.assert_allclose(r.trans_errors, et_a, atol=1e-9)
        np.testing.assert_allclose(r.rot_errors_deg, er_a, atol=1e-7)
        assert r.trans_rmse == pytest.approx(math.sqrt(np.mean(et_a**2)))
        assert r.trans_mean == pytest.approx(et_a.mean())
        assert r.trans_max == pytest.approx(et_a.max())
        assert r.rot_rmse_deg == pytest.approx(math.sqrt(np.mean(er_a**2)))
        assert r.rot_max_deg == pytest.approx(er_a.max())
        assert r.delta == delta and r.delta_unit == unit
        d = r.as_dict("x_")
        assert d["x_rot_rmse_deg"] == r.rot_rmse_deg and d["x_delta"] == delta


def test_rpe_path_and_time_stretches_differ_when_speed_is_not_one():
    t = np.arange(11.0)
    ref = Trajectory(t, np.column_stack((2.0 * t, np.zeros(11), np.zeros(11))))  # 2 m/s
    assert rpe(ref, ref, delta=4.0, delta_unit="m").n == 5  # every 2 s
    assert rpe(ref, ref, delta=4.0, delta_unit="s").n == 2  # every 4 s: (0,4), (4,8)


def test_rpe_default_stretch_uses_only_the_overlap_and_one_pair_is_a_result():
    t = np.arange(21.0)
    ref = Trajectory(t, np.column_stack((t, np.zeros(21), np.zeros(21))))
    assert rpe(ref, ref).n == 2  # default 10 m: (0, 10), (10, 20)
    assert rpe(ref, ref, delta=0.5).n == 20
    # the estimate covers 5..15 s: only the reference poses inside count
    est = Trajectory(t[5:16], ref.poses[5:16])
    one = rpe(est, ref)
    assert one and one.n == 1 and one.trans_max < 1e-12
    # exactly two poses overlap: one pair
    two = rpe(Trajectory([3.0, 4.0], ref.poses[3:5]), ref, delta=1.0)
    assert two.n == 1 and bool(two)
    none = rpe(Trajectory([3.0, 3.5], ref.poses[3:5]), ref, delta=1.0)
    assert not none and none.reason == "only 1 reference poses overlap the trajectory (need 2)."
    for v in (none.trans_rmse, none.trans_mean, none.trans_max, none.rot_rmse_deg):
        assert math.isnan(v)
    assert math.isnan(none.rot_max_deg) and none.n == 0
    assert none.trans_errors.shape == (0,) and none.rot_errors_deg.shape == (0,)
    assert none.delta == 1.0 and none.delta_unit == "m"
    with pytest.raises(ConfigError, match=r"^rpe: delta must be > 0, got -1"):
        rpe(ref, ref, delta=-1.0)
    with pytest.raises(ConfigError, match=r"^rpe: delta_unit must be 'm'"):
        rpe(ref, ref, delta_unit="km")


def test_rpe_result_truth_value():
    z = np.zeros(1)
    assert RpeResult(0.0, 0.0, 0.0, 0.0, 0.0, 1, 1.0, "m", z, z)
    assert not RpeResult(0.0, 0.0, 0.0, 0.0, 0.0, 0, 1.0, "m", z[:0], z[:0])


def test_point_track_places_the_lever_arm_in_the_vehicle_frame():
    tr = Trajectory([0.0, 1.0], [[1.0, 2.0, math.pi / 2], [1.0, 4.0, math.pi / 2]])
    # heading +y: forward 1 m is +y, left 0.5 m is -x
    np.testing.assert_allclose(point_track(tr, [0.0, 1.0], (1.0, 0.5)), [[0.5, 3.0], [0.5, 5.0]])
    tr2 = Trajectory([0.0, 1.0], [[0.0, 0.0, math.pi / 6], [0.0, 0.0, math.pi / 6]])
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    np.testing.assert_allclose(
        point_track(tr2, [0.5], (2.0, 3.0)), [[2 * c - 3 * s, 2 * s + 3 * c]], atol=1e-12
    )


def test_apply_poses_moves_positions_and_wraps_headings():
    al = Se2Alignment(math.pi / 2, (1.0, -2.0))
    out = al.apply_poses([[1.0, 0.0, 0.0], [0.0, 2.0, 3.0]])
    np.testing.assert_allclose(out[:, :2], [[1.0, -1.0], [-1.0, -2.0]], atol=1e-12)
    np.testing.assert_allclose(out[:, 2], [math.pi / 2, 3.0 + math.pi / 2 - 2 * math.pi])
    assert np.all((out[:, 2] > -math.pi) & (out[:, 2] <= math.pi))
    assert al.apply_poses([0.0, 0.0, math.pi / 2])[0, 2] == pytest.approx(math.pi)


def test_align_se2_two_points_weights_and_messages():
    src = np.array([[0.0, 0.0], [1.0, 0.0]])
    dst = np.array([[5.0, 5.0], [5.0, 6.0]])
    al = align_se2(src, dst)
    assert al.theta == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(al.apply(src), dst, atol=1e-12)
    # weights: a zero-weight outlier does not move the fit
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (8, 2))
    b = Se2Alignment(0.4, (2.0, -1.0)).apply(a)
    b[0] += [30.0, 0.0]
    w = np.r_[0.0, np.ones(7)]
    aw = align_se2(a, b, weights=w)
    assert aw.theta == pytest.approx(0.4) and aw.t == pytest.approx((2.0, -1.0))
    assert align_se2(a, b).theta != pytest.approx(0.4, abs=1e-3)
    with pytest.raises(InputError, match=r"^align_se2: src has 3 points but dst has 4\.$"):
        align_se2(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(InputError, match=r"^align_se2 needs at least 2 point pairs, got 1\.$"):
        align_se2(np.zeros((1, 2)), np.zeros((1, 2)))


def test_screen_gps_limits_are_inclusive_and_scale_with_distance():
    t = np.array([0.0, 1.0])
    o = np.array([[0.0, 0.0], [10.0, 0.0]])  # straight: chord = arc = 10 m
    dist = np.array([0.0, 10.0])
    # tol = 0.5 + 0.1 * 10 = 1.5: 11.5 and 8.5 m are both on the limit
    for d in (11.5, 8.5):
        s = screen_gps(t, [[0.0, 0.0], [d, 0.0]], o, dist)
        assert s.keep.tolist() == [True, True], d
    for d in (11.6, 8.4, 12.4):
        s = screen_gps(t, [[0.0, 0.0], [d, 0.0]], o, dist)
        assert s.keep.tolist() == [False, False], d
    assert s.n_total == 2 and s.n_kept == 0 and s.keep.dtype == bool
    assert s.rule == "displacement vs odometry within 0.5 m + 10% of distance driven"
    # a long leg: the relative part dominates (tol = 0.5 + 10 = 10.5 m on 100 m)
    big = screen_gps(t, [[0.0, 0.0], [110.0, 0.0]], o * 10, dist * 10)
    assert big.keep.all()


def test_screen_gps_starts_at_the_first_fix_agreeing_with_its_successor():
    # stationary vehicle; fix 1 is a spike. Fix 0 agrees with fix 2 but not with fix 1, so
    # the screen starts at fix 2 (the rule never looks back)
    t = np.arange(4.0)
    g = np.array([[0.0, 0.0], [5.0, 0.0], [0.2, 0.0], [0.2, 0.0]])
    s = screen_gps(t, g, np.zeros((4, 2)), np.zeros(4))
    assert s.keep.tolist() == [False, False, True, True]
    # only the last two fixes agree
    g2 = np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0], [10.1, 0.0]])
    assert screen_gps(t, g2, np.zeros((4, 2)), np.zeros(4)).keep.tolist() == [F, F, T, T]
    # nothing agrees
    g3 = np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0]])
    none = screen_gps(t[:3], g3, np.zeros((3, 2)), np.zeros(3))
    assert not none.keep.any() and none.n_kept == 0
    with pytest.raises(InputError, match=r"^screen_gps: 4 times, 3 fixes, 4 odometry positions"):
        screen_gps(t, g3, np.zeros((4, 2)), np.zeros(4))


F, T = False, True


def _line(n=11):
    t = np.arange(float(n))
    return Trajectory(t, np.column_stack((t, np.zeros(n), np.zeros(n))))


def test_ate_keep_mask_span_and_minimum():
    tr = _line()
    ref_t = tr.times.copy()
    ref = tr.xy.copy()
    ref[4] += [0.0, 9.0]  # one bad reference, masked out
    keep = np.ones(11, dtype=bool)
    keep[4] = False
    r = ate(tr, ref_t, ref, keep=keep)
    assert r.n == 10 and r.max < 1e-9
    # the last reference time (exactly the trajectory's end) and one between the last two
    # poses are inside the span
    r2 = ate(tr, [0.0, 5.0, 9.5, 10.0], [[0, 0], [5, 0], [9.5, 0], [10, 0]])
    assert r2.n == 4
    # exactly three references are enough
    r3 = ate(tr, [0.0, 5.0, 10.0], [[0, 0], [5, 0], [10, 0]])
    assert r3 and r3.n == 3
    fail = ate(tr, [0.0, 5.0], [[0, 0], [5, 0]])
    assert not fail and fail.n == 0 and fail.alignment is None
    for v in (fail.rmse, fail.p95, fail.max, fail.mean):
        assert math.isnan(v)
    assert fail.errors.shape == (0,)
    assert fail.reason == "only 2 reference positions overlap the trajectory (need 3)."
    with pytest.raises(InputError, match=r"^ate: 3 reference times but 4 positions\.$"):
        ate(tr, [0.0, 1.0, 2.0], [[0, 0], [1, 0], [2, 0], [3, 0]])
    # a keep mask of 0/1 integers is a mask, not a list of indices
    r_int = ate(tr, ref_t, ref, keep=keep.astype(int))
    assert r_int.n == 10 and r_int.max < 1e-9
    with pytest.raises(InputError, match=r"^ate: keep mask has shape \(2,\), need \(3,\)\.$"):
        ate(tr, [0.0, 1.0, 2.0], [[0, 0], [1, 0], [2, 0]], keep=[True, True])


def test_ate_statistics_offset_and_unaligned_scoring():
    tr = _line()
    rng = np.random.default_rng(5)
    ref = tr.xy + np.array([0.0, 1.0]) + rng.normal(0.0, 0.3, (11, 2))
    r = ate(tr, tr.times, ref, align=False)
    err = np.hypot(*(tr.xy - ref).T)
    np.testing.assert_allclose(r.errors, err)
    assert r.alignment == Se2Alignment(0.0, (0.0, 0.0))
    assert r.rmse == pytest.approx(math.sqrt(np.mean(err**2)))
    assert r.p95 == pytest.approx(float(np.percentile(err, 95)))
    assert r.mean == pytest.approx(err.mean()) and r.max == pytest.approx(err.max())
    d = r.as_dict()
    assert d == {
        "ate_rmse_m": r.rmse,
        "ate_p95_m": r.p95,
        "ate_max_m": r.max,
        "ate_mean_m": r.mean,
        "ate_n": 11,
    }
    # a GPS antenna 1 m left of the reference point: the offset removes the error exactly
    left = ate(tr, tr.times, tr.xy + np.array([0.0, 1.0]), offset=(0.0, 1.0), align=False)
    assert left.max < 1e-12


def test_ate_result_truth_value():
    al = Se2Alignment(0.0, (0.0, 0.0))
    z = np.zeros(1)
    assert AteResult(0.0, 0.0, 0.0, 0.0, 1, z, al)
    assert not AteResult(0.0, 0.0, 0.0, 0.0, 0, z[:0], al)
    assert not AteResult(0.0, 0.0, 0.0, 0.0, 1, z, None)


def test_loop_closure_error_in_the_start_frame_with_an_offset():
    # start at (5, 5) heading 90 deg, end at (3, 9) heading 0: the world displacement (-2, 4)
    # is (4, 2) in the start frame (4 m forward, 2 m to the left)
    tr = Trajectory([0.0, 1.0], [[5.0, 5.0, math.pi / 2], [3.0, 9.0, 0.0]])
    assert loop_closure_error(tr, (4.0, 2.0)) == pytest.approx(0.0, abs=1e-12)
    assert loop_closure_error(tr) == pytest.approx(math.hypot(4.0, 2.0))
    # a point 1 m ahead: start (5, 6), end (4, 9) -> world (-1, 3) -> body (3, 1)
    assert loop_closure_error(tr, (3.0, 1.0), offset=(1.0, 0.0)) == pytest.approx(0.0, abs=1e-12)
    # a start heading off the axes: every term of the rotation into the start frame counts
    th = math.pi / 6
    c, s = math.cos(th), math.sin(th)
    body = np.array([3.0, -1.5])
    end = np.array([2.0, 1.0]) + np.array([c * body[0] - s * body[1], s * body[0] + c * body[1]])
    tr6 = Trajectory([0.0, 1.0], [[2.0, 1.0, th], [end[0], end[1], 1.0]])
    assert loop_closure_error(tr6, body) == pytest.approx(0.0, abs=1e-12)
    assert loop_closure_error(tr6, (0.0, 0.0)) == pytest.approx(math.hypot(3.0, -1.5))
    with pytest.raises(InputError, match=r"^loop_closure_error needs a trajectory with at least"):
        loop_closure_error(Trajectory([0.0], [[0.0, 0.0, 0.0]]))
