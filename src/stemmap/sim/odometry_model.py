"""The simulator's wheel-odometry error, as the motion noise a SLAM back-end models (ours).

:func:`stemmap.sim.trajectory.simulate_run` corrupts every odometry sample (rate ``r``, each
held ``1/r`` s) with the :class:`~stemmap.sim.motion_sensors.OdometryNoise` model::

    v_k = v s (1 + eps I_k) + sigma_v n_k,        w_k = w + b + sigma_w m_k,

``s`` the speed scale, ``eps`` the slip excess, ``I_k`` = 1 while a wheel slip lasts (slips
start as a Poisson process of rate ``lambda``, each ``D`` s long), ``b`` the yaw-rate bias and
``n_k, m_k`` independent standard normal draws per sample. The generator has no random walk:
scale and bias are constant over a run.

A back-end's :class:`~stemmap.slam.motion.UnicycleModel` instead treats the speed and yaw-rate
errors as white with a one-second-average sigma (``control_cov``: the error of the controls
integrated over ``dt`` has variance ``sigma² dt``). This module gives

* :func:`increment_error_moments`: the exact mean and variance of the integrated speed and
  yaw-rate errors (the distance and heading errors of dead reckoning) over an interval of
  ``T`` s, derived from the generator above;
* :func:`white_equivalent_sigmas`: the white sigmas whose modelled variance ``sigma² T``
  equals the generator's mean square error ``mean² + var`` over a horizon ``T``. The white
  part of the generator is matched at every horizon; the constant scale and bias grow as
  ``T²`` and can only be matched at one horizon, so the horizon is an explicit argument (the
  time over which the back-end's pose rests on the odometry alone, see
  :func:`dead_reckoning_horizon`).

References
----------
S. Thrun, W. Burgard, D. Fox, "Probabilistic Robotics", MIT Press 2005, §5.4 (odometry
motion model: the control error as zero-mean noise) and §3.3 (EKF consistency needs the
modelled noise to match the actual one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stemmap.errors import ConfigError

if TYPE_CHECKING:
    from stemmap.sim.motion_sensors import OdometryNoise

__all__ = [
    "IncrementErrorMoments",
    "dead_reckoning_horizon",
    "increment_error_moments",
    "white_equivalent_sigmas",
]


@dataclass(frozen=True)
class IncrementErrorMoments:
    """Moments of the odometry error integrated over one interval.

    Attributes
    ----------
    duration : float, s
        Interval length (a whole number of odometry samples).
    distance_mean, distance_var : float, m and m²
        Mean and variance of ``sum_k (v_k - v) / r`` (integrated speed error).
    heading_mean, heading_var : float, rad and rad²
        Mean and variance of ``sum_k (w_k - w) / r`` (integrated yaw-rate error).
    """

    duration: float
    distance_mean: float
    distance_var: float
    heading_mean: float
    heading_var: float

    @property
    def distance_mse(self) -> float:
        """Mean square distance error, m² (``mean² + var``)."""
        return self.distance_mean**2 + self.distance_var

    @property
    def heading_mse(self) -> float:
        """Mean square heading error, rad² (``mean² + var``)."""
        return self.heading_mean**2 + self.heading_var


def _slip_sum_moments(
    n: int, rate_hz: float, slip_rate: float, slip_duration: float
) -> tuple[float, float]:
    """Mean and variance of ``sum_k I_k`` over ``n`` consecutive samples (stationary process).

    ``I(t) = 1`` iff a slip started in ``(t - D, t]``: ``P(I = 1) = 1 - a`` with
    ``a = exp(-lambda D)``. Two samples ``tau`` apart are both 0 iff no slip started in the
    union of their windows (length ``D + min(tau, D)``), so
    ``Cov(I(t), I(t + tau)) = a (exp(-lambda min(tau, D)) - a)``, zero from ``tau >= D``.
    """
    if slip_rate <= 0 or n <= 0:
        return 0.0, 0.0
    a = math.exp(-slip_rate * slip_duration)
    lag = np.arange(n) / rate_hz
    cov = a * (np.exp(-slip_rate * np.minimum(lag, slip_duration)) - a)
    weights = np.where(np.arange(n) == 0, n, 2.0 * (n - np.arange(n)))
    return n * (1.0 - a), float(np.sum(weights * cov))


def increment_error_moments(
    noise: OdometryNoise, *, duration: float, rate_hz: float, speed: float
) -> IncrementErrorMoments:
    """Mean and variance of the integrated odometry error over ``duration`` s (module doc).

    Parameters
    ----------
    noise : OdometryNoise
        The generator's error model (:data:`stemmap.sim.motion_sensors.ODOMETRY_PRESETS`).
    duration : float, s, > 0
        Interval length; rounded to a whole number (>= 1) of odometry samples.
    rate_hz : float, Hz, > 0
        Odometry sample rate (``simulate_run(odom_rate_hz=...)``).
    speed : float, m/s, >= 0
        True speed over the interval (the scale and slip errors are proportional to it).

    Returns
    -------
    IncrementErrorMoments

    Notes
    -----
    With ``N`` samples each held ``1/r`` s, ``p = 1 - exp(-lambda D)`` the share of time in a
    slip and ``S_I`` the sum of the slip indicators (:func:`_slip_sum_moments`)::

        E[dist] = N/r v (s - 1 + s eps p)     Var[dist] = N sigma_v² / r² + (v s eps / r)² Var S_I
        E[head] = N/r b                       Var[head] = N sigma_w² / r²

    Slips are taken as stationary (the first ``D`` s of a run, when fewer slips can have
    started, are left out).

    Examples
    --------
    >>> from stemmap.sim.motion_sensors import ODOMETRY_PRESETS
    >>> m = increment_error_moments(ODOMETRY_PRESETS["wheel"], duration=1.0, rate_hz=50.0,
    ...                             speed=1.0)
    >>> round(m.distance_mean, 4), round(math.sqrt(m.heading_var), 5)
    (0.01, 0.00247)
    """
    for name, val, lo in (("duration", duration, 0.0), ("rate_hz", rate_hz, 0.0)):
        if not (math.isfinite(val) and val > lo):
            raise ConfigError(f"increment_error_moments: {name} must be > 0, got {val}.")
    if not (math.isfinite(speed) and speed >= 0):
        raise ConfigError(f"increment_error_moments: speed must be >= 0 m/s, got {speed}.")
    n = max(1, round(duration * rate_hz))
    h = n / rate_hz
    s_mean, s_var = _slip_sum_moments(n, rate_hz, noise.slip_rate, noise.slip_duration)
    slip = speed * noise.speed_scale * noise.slip_excess / rate_hz
    return IncrementErrorMoments(
        duration=h,
        distance_mean=h * speed * (noise.speed_scale - 1.0) + slip * s_mean,
        distance_var=n * noise.speed_noise**2 / rate_hz**2 + slip**2 * s_var,
        heading_mean=h * noise.yaw_rate_bias,
        heading_var=n * noise.yaw_rate_noise**2 / rate_hz**2,
    )


def white_equivalent_sigmas(
    noise: OdometryNoise, *, rate_hz: float, speed: float, horizon: float
) -> tuple[float, float]:
    """One-second white-noise sigmas (speed m/s, yaw rate rad/s) matching the generator.

    The :class:`~stemmap.slam.motion.UnicycleModel` models the integrated error over ``T`` as
    zero-mean with variance ``sigma² T``; this returns ``sigma = sqrt(MSE(T) / T)`` with
    ``MSE`` the generator's mean square error over ``T = horizon``
    (:func:`increment_error_moments`). The white part alone gives ``sigma_v / sqrt(r)``
    whatever the horizon; the scale, bias and slips add ``~ |error rate| sqrt(T)``.

    Examples
    --------
    >>> from stemmap.sim.motion_sensors import ODOMETRY_PRESETS
    >>> sv, sw = white_equivalent_sigmas(ODOMETRY_PRESETS["wheel"], rate_hz=50.0, speed=1.0,
    ...                                  horizon=9.0)
    >>> round(sv, 4), round(math.degrees(sw), 3)
    (0.0308, 0.616)
    """
    m = increment_error_moments(noise, duration=horizon, rate_hz=rate_hz, speed=speed)
    return math.sqrt(m.distance_mse / m.duration), math.sqrt(m.heading_mse / m.duration)


def dead_reckoning_horizon(ranges: np.ndarray, speed: float, *, quantile: float = 0.9) -> float:
    """Time (s) the vehicle needs to drive past what its detector sees.

    ``quantile(ranges) / speed``: a tree first detected at the far end of the detection
    ranges is passed (leaves a forward-looking sensor's view) after this long, so a pose rests
    on the odometry alone -- relative to the trees that anchor it -- over about this horizon.
    ``ranges`` are the detections' ranges (m; no ground truth needed).
    """
    r = np.asarray(ranges, dtype=np.float64)
    r = r[np.isfinite(r)]
    if r.size == 0 or not (math.isfinite(speed) and speed > 0):
        raise ConfigError(
            "dead_reckoning_horizon needs detections and a positive speed, got "
            f"{r.size} ranges and speed {speed}."
        )
    return float(np.quantile(r, quantile)) / speed
