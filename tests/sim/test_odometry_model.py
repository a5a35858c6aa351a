"""The analytic odometry-error moments against Monte Carlo from the simulator's own generator."""

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.sim.motion_sensors import (
    ODOMETRY_PRESETS,
    Odometry,
    OdometryNoise,
    _noisy_odometry,
)
from stemmap.sim.odometry_model import (
    dead_reckoning_horizon,
    increment_error_moments,
    white_equivalent_sigmas,
)

RATE = 50.0
SPEED, YAW = 1.2, 0.1


def _window_errors(noise: OdometryNoise, duration: float, seed: int) -> tuple[np.ndarray, ...]:
    """Integrated (distance, heading) errors of consecutive ``duration`` windows of one long
    drive at constant speed and yaw rate, through the generator ``simulate_run`` uses."""
    n_win, n = 6000, round(duration * RATE)
    t = np.arange(n_win * n) / RATE
    true = Odometry(t, np.full(t.size, SPEED), np.full(t.size, YAW))
    odo, _ = _noisy_odometry(true, noise, np.random.default_rng(seed))
    dv = ((odo.speed - SPEED) / RATE).reshape(n_win, n).sum(axis=1)
    dw = ((odo.yaw_rate - YAW) / RATE).reshape(n_win, n).sum(axis=1)
    return dv, dw


def _agrees(x: np.ndarray, mean: float, var: float) -> None:
    """Sample mean and variance within 4.5 standard errors of the analytic ones (the standard
    errors from the sample's own moments: sd / sqrt(n) and sqrt((m4 - var²) / n); windows
    share slips only across their boundaries, a small correlation at 2 s and more)."""
    n = x.size
    se_mean = math.sqrt(var / n) + 1e-15
    m4 = float(np.mean((x - x.mean()) ** 4))
    se_var = math.sqrt(max(m4 - x.var() ** 2, 0.0) / n) + 1e-15
    assert abs(x.mean() - mean) < 4.5 * se_mean, (x.mean(), mean, se_mean)
    assert abs(x.var(ddof=1) - var) < 4.5 * se_var, (x.var(ddof=1), var, se_var)


@pytest.mark.parametrize("preset", ["wheel", "forest"])
@pytest.mark.parametrize("duration", [0.2, 2.0, 6.0])
def test_moments_match_the_generator(preset: str, duration: float) -> None:
    noise = ODOMETRY_PRESETS[preset]
    dv, dw = _window_errors(noise, duration, seed=11)
    m = increment_error_moments(noise, duration=duration, rate_hz=RATE, speed=SPEED)
    assert m.duration == pytest.approx(duration)
    _agrees(dv, m.distance_mean, m.distance_var)
    _agrees(dw, m.heading_mean, m.heading_var)


def test_slips_dominate_the_forest_distance_variance() -> None:
    """The slip term is the one that is not a textbook formula: without it the forest preset's
    distance variance would be off by far more than the Monte Carlo tolerance."""
    noise = ODOMETRY_PRESETS["forest"]
    m = increment_error_moments(noise, duration=2.0, rate_hz=RATE, speed=SPEED)
    white = 100 * noise.speed_noise**2 / RATE**2
    assert m.distance_var > 10 * white
    dv, _ = _window_errors(noise, 2.0, seed=3)
    assert dv.var() > 5 * white


def test_white_equivalent_of_white_noise_is_horizon_free() -> None:
    noise = OdometryNoise(speed_noise=0.05, yaw_rate_noise=math.radians(1.0))
    for horizon in (0.2, 5.0, 60.0):
        sv, sw = white_equivalent_sigmas(noise, rate_hz=RATE, speed=SPEED, horizon=horizon)
        assert sv == pytest.approx(0.05 / math.sqrt(RATE))
        assert sw == pytest.approx(math.radians(1.0) / math.sqrt(RATE))


def test_white_equivalent_matches_the_mean_square_error_at_the_horizon() -> None:
    noise = ODOMETRY_PRESETS["wheel"]
    horizon = 9.0
    sv, sw = white_equivalent_sigmas(noise, rate_hz=RATE, speed=1.0, horizon=horizon)
    # bias and scale grow as T: (b T)² + T sigma² / r = sigma_eq² T
    b, s = noise.yaw_rate_bias, noise.speed_scale - 1.0
    white_w, white_v = noise.yaw_rate_noise**2 / RATE, noise.speed_noise**2 / RATE
    assert sw**2 * horizon == pytest.approx((b * horizon) ** 2 + horizon * white_w)
    assert sv**2 * horizon == pytest.approx((s * horizon) ** 2 + horizon * white_v)
    # longer horizons: larger equivalents (the constant errors)
    sv2, sw2 = white_equivalent_sigmas(noise, rate_hz=RATE, speed=1.0, horizon=4 * horizon)
    assert sv2 > sv and sw2 > sw


def test_bad_arguments() -> None:
    noise = ODOMETRY_PRESETS["wheel"]
    with pytest.raises(ConfigError, match="duration"):
        increment_error_moments(noise, duration=0.0, rate_hz=RATE, speed=1.0)
    with pytest.raises(ConfigError, match="speed"):
        increment_error_moments(noise, duration=1.0, rate_hz=RATE, speed=-1.0)
    with pytest.raises(ConfigError, match="positive speed"):
        dead_reckoning_horizon(np.array([5.0]), 0.0)
    assert dead_reckoning_horizon(np.array([2.0, 4.0, np.nan]), 2.0, quantile=1.0) == 2.0
