import math

import numpy as np
import pytest

import stemmap.harvester.capture as capture_mod
from stemmap.errors import ConfigError, StemmapError
from stemmap.harvester.capture import (
    PlannerConfig,
    ScannerMount,
    choose_target,
    plan_capture,
    scanner_pose,
    trunk_in_head_frame,
    trunks_to_base,
)
from stemmap.harvester.kinematics import ForestryCrane, UnreachableError
from stemmap.types import FloatArray

CRANE = ForestryCrane()


def test_eq11_trunk_relative_to_head_matches_direct_geometry():
    """Zheng eq. (11): composing scanner->trunk with head->scanner gives the trunk in the head
    frame; check against positions computed directly in the base frame."""
    q = CRANE.inverse([5.0, 1.0, 1.0], 0.4)
    T_B_S = scanner_pose(CRANE, q, ScannerMount(along=1.2, yaw=0.1))
    T_B_H = CRANE.head_pose(q)
    c_s = np.array([2.5, -0.4])
    T_H_T = trunk_in_head_frame(c_s, T_B_S, T_B_H)
    trunk_base = np.append(trunks_to_base(c_s, T_B_S)[0], T_B_S[2, 3])
    np.testing.assert_allclose(T_B_H @ T_H_T[:, 3], np.append(trunk_base, 1.0), atol=1e-12)


def test_choose_target_modes():
    xy = np.array([[4.0, 0.0], [3.0, 2.0], [20.0, 0.0], [0.0, 5.0]])
    d = np.array([0.3, 0.9, 0.3, 0.25])  # trunk 1 too thick to grip, trunk 2 out of reach
    assert choose_target(xy, d, CRANE, grip_height=0.7) == 0
    assert choose_target(xy, d, CRANE, grip_height=0.7, mode="bearing", bearing=math.pi / 2) == 3
    assert choose_target(xy, d, CRANE, grip_height=0.7, mode="index", index=3) == 3
    with pytest.raises(StemmapError, match="cannot be reached or gripped"):
        choose_target(xy, d, CRANE, grip_height=0.7, mode="index", index=2)
    with pytest.raises(ConfigError, match="not one of"):
        choose_target(xy, d, CRANE, grip_height=0.7, mode="index", index=9)
    with pytest.raises(StemmapError, match="no trunk"):
        choose_target(np.zeros((0, 2)), [], CRANE, grip_height=0.7)


@pytest.mark.parametrize("dist_target", [(6.5, 3.0), (4.0, -3.5), (8.5, 0.5)])
def test_plan_is_straight_and_respects_limits(dist_target):
    q0 = CRANE.inverse([3.0, -2.0, 1.5])
    target = np.array([*dist_target, 0.7])
    plan = plan_capture(CRANE, q0, target)
    # k from the distance, within the paper's 10 < k < 100
    assert 10 < plan.k < 100
    # set-points lie on the straight segment, and the IK reproduces them
    p0, p1 = plan.setpoints[0], plan.setpoints[-1]
    np.testing.assert_allclose(p1, target)
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    off_line = (plan.setpoints - p0) - np.outer((plan.setpoints - p0) @ u, u)
    assert np.max(np.abs(off_line)) < 1e-12
    np.testing.assert_allclose(CRANE.head_pose(plan.q)[:, :3, 3], plan.setpoints, atol=1e-9)
    # joint limits: finite-difference utilisation within 2 % (discretisation of the profile)
    assert plan.max_velocity_ratio <= 1.0
    assert plan.max_acceleration_ratio <= 1.0
    assert np.all(np.diff(plan.times) > 0)
    assert np.allclose(plan.qdot[-1], 0.0)


def test_replanning_from_motion_starts_at_current_speed():
    q0 = CRANE.inverse([3.0, -2.0, 1.5])
    first = plan_capture(CRANE, q0, [6.5, 3.0, 0.7])
    second = plan_capture(CRANE, first.q[10], [6.55, 3.02, 0.7], qdot_now=first.qdot[10])
    assert second.meta["sdot0"] > 0
    # the new plan's first joint velocity continues the old one (same direction, similar size)
    a, b = first.qdot[10], second.qdot[0]
    cos = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    assert cos > 0.99
    assert second.max_acceleration_ratio <= 1.0


def test_unreachable_plan_and_bad_config():
    q0 = CRANE.inverse([3.0, 0.0, 1.5])
    with pytest.raises(UnreachableError):
        plan_capture(CRANE, q0, [15.0, 0.0, 0.7])
    with pytest.raises(ConfigError):
        PlannerConfig(k_min=5)
    with pytest.raises(ConfigError):
        PlannerConfig(execute=0)


# ---- reference: the straightforward numpy/Python time scaling the compiled kernel replaced
def _time_scale_reference(
    q: FloatArray, s: FloatArray, sdot0: float, vmax: FloatArray, amax: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Path-speed profile sdot(s_i) within joint velocity and acceleration limits, starting at
    ``sdot0`` and ending at rest. Returns (times, sdot).

    A forward-backward pass bounds the path speed by each joint's velocity limit and the path
    acceleration by its acceleration limit (through dq/ds); the curvature term q'' sdot^2 and the
    discretisation are then handled by capping the speed where the finite-difference check of
    the timed path still exceeds a limit, and repeating (converges in a few passes).
    """
    ds = np.diff(s)
    dq_ds = np.abs(np.gradient(q, s, axis=0))
    v_cap = np.min(vmax / np.maximum(dq_ds, 1e-12), axis=1)  # (k,)
    a_lim = np.min(amax / np.maximum(dq_ds, 1e-12), axis=1)
    k = s.shape[0]
    for _ in range(30):
        sd = v_cap.copy()
        sd[0] = min(sdot0, v_cap[0])
        for i in range(k - 1):  # forward: accelerate no faster than allowed
            sd[i + 1] = min(sd[i + 1], math.sqrt(sd[i] ** 2 + 2.0 * a_lim[i] * ds[i]))
        sd[-1] = 0.0
        for i in range(k - 2, -1, -1):  # backward: leave room to stop
            sd[i] = min(sd[i], math.sqrt(sd[i + 1] ** 2 + 2.0 * a_lim[i] * ds[i]))
        mean = 0.5 * (sd[:-1] + sd[1:])
        times = np.concatenate(([0.0], np.cumsum(ds / np.maximum(mean, 1e-9))))
        v_ratio, a_ratio = capture_mod._limit_ratios(q, times, vmax, amax)
        if v_ratio.max(initial=0.0) <= 1.0 + 1e-3 and a_ratio.max(initial=0.0) <= 1.0 + 1e-3:
            break
        scale = np.ones(k)
        over_v = np.maximum(v_ratio, 1.0)
        scale[:-1] = np.minimum(scale[:-1], 1.0 / over_v)
        scale[1:] = np.minimum(scale[1:], 1.0 / over_v)
        over_a = 1.0 / np.sqrt(np.maximum(a_ratio, 1.0))
        for shift in (0, 1, 2):  # acceleration at point i involves points i-1, i, i+1
            scale[shift : shift + over_a.shape[0]] = np.minimum(
                scale[shift : shift + over_a.shape[0]], over_a
            )
        v_cap = np.minimum(v_cap, sd * scale * 0.999 + (sd == 0) * v_cap)
        a_lim = a_lim * np.where(scale < 1.0, scale**2, 1.0)
    return times, sd


def test_compiled_time_scaling_equals_the_python_reference() -> None:
    """The numba kernel runs the same passes as the plain implementation: same timing to
    round-off on random plans (at rest and already moving, short and long lines)."""
    rng = np.random.default_rng(11)
    lo, hi = np.asarray(CRANE.lower), np.asarray(CRANE.upper)
    vmax, amax = np.asarray(CRANE.max_velocity), np.asarray(CRANE.max_acceleration)
    n = 0
    while n < 40:
        q0 = lo + (hi - lo) * rng.uniform(0.2, 0.8, 5)
        target = np.array([rng.uniform(-9.0, 9.0), rng.uniform(-9.0, 9.0), 0.7])
        try:
            plan = plan_capture(CRANE, q0, target)
        except UnreachableError:
            continue
        n += 1
        s = np.linspace(0.0, 1.0, plan.k)
        sdot0 = float(rng.uniform(0.0, 0.5))
        t_ref, sd_ref = _time_scale_reference(plan.q, s, sdot0, vmax, amax)
        t_new, sd_new = capture_mod._time_scale(plan.q, s, sdot0, vmax, amax)
        np.testing.assert_allclose(t_new, t_ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sd_new, sd_ref, rtol=1e-12, atol=1e-12)
