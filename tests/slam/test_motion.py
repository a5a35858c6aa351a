"""Motion models: Jacobians vs finite differences, closed-form arcs, covariance vs Monte Carlo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import Controls
from stemmap.slam.motion import (
    AckermannModel,
    MotionModel,
    OdometryIncrementModel,
    UnicycleModel,
    between,
    compose,
    preintegrate,
    rollout,
)
from stemmap.types import wrap_angle


def _numeric_jacobians(model, x, u, dt, eps=1e-6):
    x = np.asarray(x, float)
    u = np.asarray(u, float)
    Fx = np.zeros((3, 3))
    Fu = np.zeros((3, u.size))
    for i in range(3):
        e = np.zeros(3)
        e[i] = eps
        d = model.predict(x + e, u, dt) - model.predict(x - e, u, dt)
        d[2] = wrap_angle(d[2])
        Fx[:, i] = d / (2 * eps)
    for i in range(u.size):
        e = np.zeros(u.size)
        e[i] = eps
        d = model.predict(x, u + e, dt) - model.predict(x, u - e, dt)
        d[2] = wrap_angle(d[2])
        Fu[:, i] = d / (2 * eps)
    return Fx, Fu


@pytest.mark.parametrize(
    ("model", "u", "dt"),
    [
        (AckermannModel(), (3.0, 0.3), 0.025),
        (AckermannModel(), (2.0, -0.5), 0.2),
        (UnicycleModel(), (1.5, 0.4), 0.1),
        (OdometryIncrementModel(), (0.5, 0.1, 0.2), 0.0),
    ],
)
def test_jacobians_match_finite_differences(model, u, dt):
    x = np.array([1.0, -2.0, 2.5])
    Fx, Fu = model.jacobians(x, u, dt)
    nFx, nFu = _numeric_jacobians(model, x, u, dt)
    # central differences with eps=1e-6 are accurate to ~1e-9 on these smooth functions
    np.testing.assert_allclose(Fx, nFx, atol=1e-7)
    np.testing.assert_allclose(Fu, nFu, atol=1e-7)
    assert isinstance(model, MotionModel)


def test_ackermann_constant_steer_drives_a_circle_of_radius_l_over_tan():
    m = AckermannModel(H=0.0)
    alpha = 0.2
    R = m.L / math.tan(alpha)
    v = 2.0
    T = 2 * math.pi * R / v  # one lap
    t = np.linspace(0, T, 4001)
    c = Controls(t, np.full_like(t, v), np.full_like(t, alpha), "ackermann")
    poses = rollout(m, c, t[::100])
    centre = np.array([0.0, R])
    d = np.hypot(*(poses[:, :2] - centre).T)
    # mid-point chord of length ds (not the true chord 2R sin(dtheta/2)) overshoots by
    # ds * dtheta^2 / 24 per step: ~1e-8 m per step here, ~1e-5 m over the 4000-step lap
    np.testing.assert_allclose(d, R, atol=2e-5)
    np.testing.assert_allclose(poses[-1], [0, 0, 0], atol=5e-5)


def test_ackermann_encoder_on_left_wheel_speed_correction():
    m = AckermannModel()
    # turning left, the left (encoder) wheel is the inner one and runs slower than the centre
    vc = m.centre_speed(1.0, 0.3)
    assert vc > 1.0
    np.testing.assert_allclose(vc * (1 - math.tan(0.3) * m.H / m.L), 1.0)
    assert m.centre_speed(1.0, -0.3) < 1.0


def test_predict_is_vectorised_over_states_and_controls():
    m = AckermannModel()
    X = np.random.default_rng(0).normal(size=(5, 3))
    U = np.column_stack((np.linspace(0, 3, 5), np.linspace(-0.3, 0.3, 5)))
    out = m.predict(X, U, 0.1)
    for i in range(5):
        np.testing.assert_allclose(out[i], m.predict(X[i], U[i], 0.1))


def test_preintegrated_covariance_matches_monte_carlo():
    rng = np.random.default_rng(7)
    m = AckermannModel(sigma_speed=0.2, sigma_steer=0.01)
    t = np.arange(0, 2.0001, 0.025)
    speed = 3.0 + 0.5 * np.sin(t)
    steer = 0.2 * np.cos(2 * t)
    c = Controls(t, speed, steer, "ackermann")
    pre = preintegrate(m, c, [0.0, 2.0])
    # Monte Carlo: per-step control noise with the model's control covariance
    n = 4000
    x = np.zeros((n, 3))
    for k in range(t.size - 1):
        dt = t[k + 1] - t[k]
        C = m.control_cov((speed[k], steer[k]), dt)
        u = np.array([speed[k], steer[k]]) + rng.normal(size=(n, 2)) * np.sqrt(np.diag(C))
        x = m.predict(x, u, dt)
    emp = np.cov(x.T)
    # the noise-free increment is the mean up to a second-order bias: with per-step steering
    # noise s (0.063 rad here), E[dtheta] gains v dt (H/L) s^2 / L per step (~0.1 std after 2 s);
    # the standard error of the mean is only 0.016 std, so 0.2 std checks the first-order model
    np.testing.assert_array_less(np.abs(pre.deltas[0] - x.mean(axis=0)), 0.2 * x.std(axis=0))
    # 4000 samples: sample variances within ~2*sqrt(2/n) = 4.5 % (1-sigma 2.2 %); allow 12 %
    np.testing.assert_allclose(np.diag(pre.covs[0]), np.diag(emp), rtol=0.12)
    corr_pre = pre.covs[0][0, 2] / math.sqrt(pre.covs[0][0, 0] * pre.covs[0][2, 2])
    corr_emp = emp[0, 2] / math.sqrt(emp[0, 0] * emp[2, 2])
    assert abs(corr_pre - corr_emp) < 0.06


def test_preintegrate_splits_at_frame_times_and_composes():
    m = AckermannModel()
    t = np.arange(0, 10, 0.025)
    rng = np.random.default_rng(1)
    c = Controls(t, 2 + rng.normal(size=t.size), 0.2 * rng.normal(size=t.size), "ackermann")
    frames = np.array([0.3, 1.01, 1.01, 4.567, 9.9])
    pre = preintegrate(m, c, frames, (1.0, 2.0, 0.5))
    np.testing.assert_allclose(pre.poses[0], [1.0, 2.0, 0.5])
    # composing the increments reproduces the dead-reckoned poses
    p = pre.poses[0]
    for k in range(len(frames) - 1):
        p = compose(p, pre.deltas[k])
        np.testing.assert_allclose(p, pre.poses[k + 1], atol=1e-9)
    # duplicated frame time -> zero increment with zero covariance
    np.testing.assert_allclose(pre.deltas[1], 0, atol=1e-12)
    np.testing.assert_allclose(pre.covs[1], 0, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(pre.covs[[0, 2, 3]]) > 0)
    # one long interval == the sum of its parts in distance
    whole = preintegrate(m, c, frames[[0, -1]])
    np.testing.assert_allclose(whole.distance.sum(), pre.distance.sum())


def test_rollout_rejects_wrong_control_kind_and_backwards_times():
    t = np.arange(5.0)
    c = Controls(t, np.ones(5), np.zeros(5), "unicycle")
    with pytest.raises(InputError, match="kind"):
        rollout(AckermannModel(), c, t)
    with pytest.raises(InputError, match="backwards"):
        rollout(UnicycleModel(), c, [0.0, 2.0, 1.0])


def test_bad_config_is_config_error():
    with pytest.raises(ConfigError):
        AckermannModel(L=0.0)
    with pytest.raises(ConfigError):
        UnicycleModel(sigma_speed=-1.0)
    with pytest.raises(ConfigError):
        OdometryIncrementModel(k_xy=float("nan"))


def test_noise_scales_linearly_with_time():
    m = UnicycleModel(sigma_speed=0.1, sigma_steer=0.01)
    q1 = m.noise((1.0, 0.0), 0.1)
    q2 = m.noise((1.0, 0.0), 0.2)
    # continuous white noise: variance over dt is sigma^2 * (1 s) * dt
    np.testing.assert_allclose(q2[0, 0], 2 * q1[0, 0])
    np.testing.assert_allclose(q1[0, 0], 0.1**2 * 0.1)


poses = st.tuples(st.floats(-100, 100), st.floats(-100, 100), st.floats(-math.pi, math.pi)).map(
    np.array
)


@settings(max_examples=60, deadline=None)
@given(a=poses, b=poses)
def test_between_inverts_compose(a, b):
    d = between(a, b)
    back = compose(a, d)
    np.testing.assert_allclose(back[:2], b[:2], atol=1e-9)
    assert abs(wrap_angle(back[2] - b[2])) < 1e-9


def test_steer_offset_is_added_to_the_measured_angle():
    m0 = AckermannModel()
    m1 = AckermannModel(steer_offset=0.01)
    x = np.array([1.0, 2.0, 0.3])
    np.testing.assert_allclose(m1.predict(x, (3.0, 0.2), 0.1), m0.predict(x, (3.0, 0.21), 0.1))
    _, Fu = m1.jacobians(x, (3.0, 0.2), 0.1)
    _, nFu = _numeric_jacobians(m1, x, (3.0, 0.2), 0.1)
    np.testing.assert_allclose(Fu, nFu, atol=1e-7)
    with pytest.raises(ConfigError):
        AckermannModel(steer_offset=1.0)


def test_unicycle_lateral_noise_is_a_sideways_random_walk() -> None:
    """``sigma_lateral``: a straight drive of T seconds at heading 0.7 rad gains ``σ² T`` of
    variance across its heading and none along it or in heading (speed and yaw noise off);
    the default (0) leaves the wheeled model unchanged."""
    t = np.linspace(0.0, 10.0, 51)
    c = Controls(t, np.ones(51), np.zeros(51), "unicycle")
    lat = UnicycleModel(sigma_speed=0.0, sigma_steer=0.0, sigma_lateral=0.05)
    cov = preintegrate(lat, c, [0.0, 10.0], (3.0, -1.0, 0.7)).covs[0]  # start pose's body frame
    np.testing.assert_allclose(cov, np.diag([0.0, 0.05**2 * 10.0, 0.0]), atol=1e-15)
    q = lat.noise([1.0, 0.0], 0.2, [0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(q, np.diag([0.05**2 * 0.2, 0.0, 0.0]), atol=1e-15)
    plain = UnicycleModel()
    with_zero = UnicycleModel(sigma_lateral=0.0)
    np.testing.assert_array_equal(
        preintegrate(plain, c, t, (0, 0, 0.7)).covs, preintegrate(with_zero, c, t, (0, 0, 0.7)).covs
    )
    with pytest.raises(ConfigError):
        UnicycleModel(sigma_lateral=-0.1)
