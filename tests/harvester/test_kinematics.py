import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError
from stemmap.harvester.kinematics import (
    DHChain,
    DHJoint,
    ForestryCrane,
    UnreachableError,
    dh_transform,
    invert_transform,
    make_transform,
    rot_z,
)

CRANE = ForestryCrane()


def test_dh_transform_matches_textbook_product():
    th, d, a, al = 0.3, 0.5, 1.2, -0.7
    Rx = np.eye(4)
    Rx[1:3, 1:3] = [[math.cos(al), -math.sin(al)], [math.sin(al), math.cos(al)]]
    expected = make_transform(rot_z(th)) @ make_transform(None, (0, 0, d))
    expected = expected @ make_transform(None, (a, 0, 0)) @ Rx
    np.testing.assert_allclose(dh_transform(th, d, a, al), expected, atol=1e-15)
    # broadcasting: K angles give K transforms
    assert dh_transform(np.zeros(7), d, a, al).shape == (7, 4, 4)


def test_invert_transform_is_exact_inverse(rng):
    T = make_transform(rot_z(1.1), rng.normal(size=3))
    np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-14)


def test_dh_chain_agrees_with_closed_form_crane(rng):
    """The D-H model (to the stick tip) and the closed-form geometry are the same crane."""
    chain = CRANE.chain()
    q = rng.uniform(CRANE.lower, CRANE.upper, size=(50, 5))
    tips_dh = chain.forward(q[:, :4])[:, :3, 3]
    np.testing.assert_allclose(tips_dh, CRANE.tip_position(q), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(
    r=st.floats(3.0, 9.0),
    bearing=st.floats(-2.3, 2.3),
    z=st.floats(0.3, 2.5),
    yaw=st.floats(-math.pi, math.pi),
)
def test_closed_form_inverse_round_trip(r, bearing, z, yaw):
    """FK(IK(p)) == p for every reachable head target; rotator realises the requested yaw."""
    p = np.array([r * math.cos(bearing), r * math.sin(bearing), z])
    q = CRANE.inverse(p, yaw)
    T = CRANE.head_pose(q)
    np.testing.assert_allclose(T[:3, 3], p, atol=1e-9)
    assert math.remainder(math.atan2(T[1, 0], T[0, 0]) - yaw, 2 * math.pi) == pytest.approx(
        0, abs=1e-9
    )
    assert np.all(q >= np.asarray(CRANE.lower) - 1e-9)
    assert np.all(q <= np.asarray(CRANE.upper) + 1e-9)


def test_inverse_is_vectorised_and_equals_scalar(rng):
    P = np.column_stack((rng.uniform(3, 8, 20), rng.uniform(-3, 3, 20), np.full(20, 0.7)))
    Q = CRANE.inverse(P)
    for k in range(20):
        np.testing.assert_allclose(Q[k], CRANE.inverse(P[k]), atol=1e-12)


@pytest.mark.parametrize(
    ("target", "message"),
    [
        ([14.0, 0.0, 0.7], "out of reach"),
        ([-5.0, 0.1, 0.7], "slew"),  # behind the machine: outside the slew range
    ],
)
def test_unreachable_targets_raise_clear_error(target, message):
    with pytest.raises(UnreachableError, match=message):
        CRANE.inverse(target)
    assert not CRANE.reachable(np.array([target]))[0]


def test_numerical_inverse_of_generic_chain_round_trips(rng):
    chain = CRANE.chain()
    q_true = np.array([0.4, 0.5, -1.2, 0.8])
    p = chain.forward(q_true)[:3, 3]
    q = chain.inverse_position(p, q0=np.array([0.0, 0.3, -1.0, 0.2]))
    np.testing.assert_allclose(chain.forward(q)[:3, 3], p, atol=1e-6)
    assert chain.within_limits(q)
    with pytest.raises(UnreachableError, match="closest the chain gets"):
        chain.inverse_position([30.0, 0.0, 0.0], q0=np.array([0.0, 0.3, -1.0, 0.2]))


def test_bad_joint_config():
    with pytest.raises(ConfigError, match="revolute"):
        DHJoint("spherical")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="lower limit"):
        DHJoint("revolute", lower=1.0, upper=0.0)
    with pytest.raises(ConfigError, match="expected 1 joint"):
        DHChain((DHJoint("revolute"),)).forward([0.0, 1.0])
    with pytest.raises(ConfigError, match="5 values"):
        ForestryCrane(lower=(0.0,))
