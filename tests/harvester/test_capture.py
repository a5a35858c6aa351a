import math

import numpy as np
import pytest

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
    assert plan.max_velocity_ratio <= 1.02
    assert plan.max_acceleration_ratio <= 1.02
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
    assert second.max_acceleration_ratio <= 1.02


def test_unreachable_plan_and_bad_config():
    q0 = CRANE.inverse([3.0, 0.0, 1.5])
    with pytest.raises(UnreachableError):
        plan_capture(CRANE, q0, [15.0, 0.0, 0.7])
    with pytest.raises(ConfigError):
        PlannerConfig(k_min=5)
    with pytest.raises(ConfigError):
        PlannerConfig(execute=0)
