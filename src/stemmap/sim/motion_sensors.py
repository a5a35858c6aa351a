"""Simulated motion sensors of a drive: wheel odometry, visual odometry and GNSS.

Each sensor has an error model (a frozen dataclass), a record of what it reports, and a function
that corrupts the truth of a drive with the model (used by
:func:`stemmap.sim.trajectory.simulate_run`):

* wheel odometry: the true controls with a speed scale error, white noise, a yaw-rate bias and
  wheel-slip events (:class:`OdometryNoise`, :data:`ODOMETRY_PRESETS`) -> :class:`Odometry`;
* visual odometry: noisy relative pose increments between consecutive scans
  (:class:`VisualOdometryNoise`) -> :class:`RelativeOdometry`;
* GNSS: position fixes with white and slowly correlated (Gauss-Markov) error and outages
  (:class:`GnssNoise`) -> :class:`Gnss`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.unicycle import _poses_at, compose_poses, integrate_unicycle, relative_poses
from stemmap.types import FloatArray, Trajectory, wrap_angle

__all__ = [
    "ODOMETRY_PRESETS",
    "Gnss",
    "GnssNoise",
    "Odometry",
    "OdometryNoise",
    "RelativeOdometry",
    "VisualOdometryNoise",
]


# --------------------------------------------------------------------------------------------
# Noise models
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel-odometry error model (applied per odometry sample).

    Parameters
    ----------
    speed_scale : float, > 0
        Multiplicative speed error (wheel radius / calibration), e.g. 1.02 = reads 2 % fast.
    speed_noise : float, m/s, >= 0
        1-sigma white noise added to each speed sample.
    yaw_rate_bias : float, rad/s
        Constant gyro / differential-wheel bias.
    yaw_rate_noise : float, rad/s, >= 0
        1-sigma white noise added to each yaw-rate sample.
    slip_rate : float, events per second, >= 0
        Wheel-slip events form a Poisson process.
    slip_duration : float, seconds, > 0
        Length of each slip event.
    slip_excess : float, >= 0
        During a slip the wheels turn faster than the vehicle moves: the measured speed is
        ``true * (1 + slip_excess)`` (times the scale error).
    """

    speed_scale: float = 1.0
    speed_noise: float = 0.0
    yaw_rate_bias: float = 0.0
    yaw_rate_noise: float = 0.0
    slip_rate: float = 0.0
    slip_duration: float = 0.5
    slip_excess: float = 0.5

    def __post_init__(self) -> None:
        if not self.speed_scale > 0:
            raise ConfigError(f"speed_scale must be > 0, got {self.speed_scale}.")
        for name in ("speed_noise", "yaw_rate_noise", "slip_rate", "slip_excess"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"OdometryNoise.{name} must be >= 0, got {getattr(self, name)}.")
        if not self.slip_duration > 0:
            raise ConfigError(f"slip_duration must be > 0 s, got {self.slip_duration}.")
        if not math.isfinite(self.yaw_rate_bias):
            raise ConfigError(f"yaw_rate_bias must be finite, got {self.yaw_rate_bias}.")


#: Named wheel-odometry error levels. ``none``: perfect. ``wheel``: a decent encoder +
#: gyro (1 % scale, 0.05 m/s, 0.2 deg/s bias, 1 deg/s noise). ``forest``: rough terrain with
#: 3 % scale, 0.5 deg/s bias and slips every ~20 s.
ODOMETRY_PRESETS: dict[str, OdometryNoise] = {
    "none": OdometryNoise(),
    "wheel": OdometryNoise(
        speed_scale=1.01,
        speed_noise=0.05,
        yaw_rate_bias=math.radians(0.2),
        yaw_rate_noise=math.radians(1.0),
    ),
    "forest": OdometryNoise(
        speed_scale=1.03,
        speed_noise=0.08,
        yaw_rate_bias=math.radians(0.5),
        yaw_rate_noise=math.radians(2.0),
        slip_rate=0.05,
        slip_duration=0.8,
        slip_excess=0.5,
    ),
}


@dataclass(frozen=True)
class VisualOdometryNoise:
    """Error model of the second odometry source: relative pose increments between scans.

    Each increment ``(dx, dy, dtheta)`` (expressed in the earlier vehicle frame) gets
    independent Gaussian noise with standard deviations
    ``sigma_xy + sigma_rel * |translation|`` (x and y) and ``sigma_theta`` (heading); an
    increment is missing (NaN) with probability ``dropout`` (lost tracking).
    """

    sigma_xy: float = 0.005
    sigma_rel: float = 0.01
    sigma_theta: float = math.radians(0.05)
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if not (self.sigma_xy >= 0 and self.sigma_rel >= 0 and self.sigma_theta >= 0):
            raise ConfigError("VisualOdometryNoise sigmas must be >= 0.")
        if not 0 <= self.dropout < 1:
            raise ConfigError(f"VisualOdometryNoise.dropout must be in [0, 1), got {self.dropout}.")


@dataclass(frozen=True)
class GnssNoise:
    """Error model of GNSS position fixes of the vehicle.

    Each fix is ``truth + e_white + e_slow``: white noise ``N(0, sigma²)`` per axis plus a
    first-order Gauss-Markov error (standard deviation ``sigma_slow``, correlation time
    ``tau`` seconds), the slowly wandering multipath error seen under canopy. Outages (no fix)
    form a Poisson process (``outage_rate`` per second) of length ``outage_duration``.
    """

    rate_hz: float = 1.0
    sigma: float = 0.5
    sigma_slow: float = 1.0
    tau: float = 30.0
    outage_rate: float = 0.0
    outage_duration: float = 20.0

    def __post_init__(self) -> None:
        if not (self.rate_hz > 0 and self.tau > 0 and self.outage_duration > 0):
            raise ConfigError("GnssNoise needs rate_hz, tau and outage_duration > 0.")
        if not (self.sigma >= 0 and self.sigma_slow >= 0 and self.outage_rate >= 0):
            raise ConfigError("GnssNoise sigmas and outage_rate must be >= 0.")


# --------------------------------------------------------------------------------------------
# Odometry records
# --------------------------------------------------------------------------------------------


def _readonly(a: ArrayLike, dtype: Any = np.float64) -> NDArray[Any]:
    arr = np.array(a, dtype=dtype, copy=True)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Odometry:
    """Timed unicycle controls of the vehicle (body frame), piecewise constant.

    ``speed[k]`` (m/s, forward) and ``yaw_rate[k]`` (rad/s, counter-clockwise) hold over
    ``[times[k], times[k + 1])``; the last sample holds for one more nominal period.
    """

    times: FloatArray
    speed: FloatArray
    yaw_rate: FloatArray

    def __post_init__(self) -> None:
        t = _readonly(self.times).reshape(-1)
        v = _readonly(self.speed).reshape(-1)
        w = _readonly(self.yaw_rate).reshape(-1)
        if not (t.shape == v.shape == w.shape):
            raise InputError(
                f"Odometry needs equal lengths, got times {t.shape}, speed {v.shape}, "
                f"yaw_rate {w.shape}."
            )
        if t.size > 1 and not np.all(np.diff(t) > 0):
            raise InputError("Odometry.times must be strictly increasing.")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "speed", v)
        object.__setattr__(self, "yaw_rate", w)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def integrate(self, pose0: ArrayLike = (0.0, 0.0, 0.0)) -> Trajectory:
        """Dead-reckoned vehicle trajectory at ``times`` (exact arc integration)."""
        dt = np.diff(self.times)
        poses = integrate_unicycle(pose0, self.speed[:-1], self.yaw_rate[:-1], dt)
        return Trajectory(self.times, poses, frame="odom")


@dataclass(frozen=True, eq=False)
class RelativeOdometry:
    """Relative pose increments between pairs of scans (a second odometry source).

    Attributes
    ----------
    index0, index1 : ndarray of shape (K,), int
        Scan indices; the increment maps the vehicle pose at ``index0`` to the one at ``index1``.
    times0, times1 : ndarray of shape (K,), seconds
    increments : ndarray of shape (K, 3)
        ``(dx, dy, dtheta)`` of pose ``index1`` expressed in the frame of pose ``index0``
        (``pose1 = pose0 * increment``); NaN rows are dropouts.
    covs : ndarray of shape (K, 3, 3)
        Covariance of each increment as simulated.
    """

    index0: NDArray[np.int64]
    index1: NDArray[np.int64]
    times0: FloatArray
    times1: FloatArray
    increments: FloatArray
    covs: FloatArray

    def __post_init__(self) -> None:
        for name in ("index0", "index1"):
            object.__setattr__(self, name, _readonly(getattr(self, name), np.int64).reshape(-1))
        for name in ("times0", "times1"):
            object.__setattr__(self, name, _readonly(getattr(self, name)).reshape(-1))
        inc = _readonly(self.increments).reshape(-1, 3)
        cov = _readonly(self.covs).reshape(-1, 3, 3)
        k = self.index0.shape[0]
        if not (self.index1.shape[0] == self.times0.shape[0] == self.times1.shape[0] == k):
            raise InputError("RelativeOdometry columns have different lengths.")
        if inc.shape[0] != k or cov.shape[0] != k:
            raise InputError("RelativeOdometry increments/covs do not match the index columns.")
        object.__setattr__(self, "increments", inc)
        object.__setattr__(self, "covs", cov)

    def __len__(self) -> int:
        return int(self.index0.shape[0])

    def integrate(self, pose0: ArrayLike = (0.0, 0.0, 0.0)) -> Trajectory:
        """Chain consecutive increments into a trajectory (dropouts are treated as no motion)."""
        inc = np.where(np.isnan(self.increments), 0.0, self.increments)
        poses = np.empty((len(self) + 1, 3))
        poses[0] = np.asarray(pose0, dtype=np.float64)
        for k in range(len(self)):  # sequential composition; K is the number of scans
            poses[k + 1] = compose_poses(poses[k], inc[k])
        times = np.concatenate((self.times0[:1], self.times1))
        return Trajectory(times, poses, frame="odom")


@dataclass(frozen=True, eq=False)
class Gnss:
    """GNSS fixes: ``times`` (K,) s, ``xy`` (K, 2) m in the world frame, ``sigma`` (K,) m
    (the simulated total 1-sigma per axis). Fixes inside outages are absent."""

    times: FloatArray
    xy: FloatArray
    sigma: FloatArray

    def __post_init__(self) -> None:
        t = _readonly(self.times).reshape(-1)
        xy = _readonly(self.xy).reshape(-1, 2)
        sg = _readonly(self.sigma).reshape(-1)
        if not (xy.shape[0] == t.shape[0] == sg.shape[0]):
            raise InputError("Gnss times, xy and sigma have different lengths.")
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "sigma", sg)

    def __len__(self) -> int:
        return int(self.times.shape[0])


# --------------------------------------------------------------------------------------------
# Corrupting the truth
# --------------------------------------------------------------------------------------------


def _noisy_odometry(
    true: Odometry, noise: OdometryNoise, gen: np.random.Generator
) -> tuple[Odometry, NDArray[np.bool_]]:
    t = true.times
    slipping = np.zeros(t.shape[0], dtype=bool)
    if noise.slip_rate > 0 and t.size:
        duration = float(t[-1] - t[0])
        n_events = gen.poisson(noise.slip_rate * duration)
        starts = gen.uniform(t[0], t[-1], n_events)
        for s0 in starts:
            slipping |= (t >= s0) & (t < s0 + noise.slip_duration)
    v = true.speed * noise.speed_scale * np.where(slipping, 1.0 + noise.slip_excess, 1.0)
    v = v + gen.normal(0.0, 1.0, t.shape) * noise.speed_noise
    w = true.yaw_rate + noise.yaw_rate_bias + gen.normal(0.0, 1.0, t.shape) * noise.yaw_rate_noise
    return Odometry(t, v, w), slipping


def _visual_odometry(
    vehicle: FloatArray, times: FloatArray, noise: VisualOdometryNoise, gen: np.random.Generator
) -> RelativeOdometry:
    k = vehicle.shape[0] - 1
    inc = relative_poses(vehicle[:-1], vehicle[1:]).reshape(-1, 3)
    dist = np.hypot(inc[:, 0], inc[:, 1])
    sxy = noise.sigma_xy + noise.sigma_rel * dist
    sig = np.column_stack((sxy, sxy, np.full(k, noise.sigma_theta)))
    noisy = inc + gen.normal(0.0, 1.0, inc.shape) * sig
    noisy[:, 2] = wrap_angle(noisy[:, 2])
    if noise.dropout > 0:
        noisy[gen.random(k) < noise.dropout] = np.nan
    covs = np.zeros((k, 3, 3))
    covs[:, [0, 1, 2], [0, 1, 2]] = sig**2
    idx = np.arange(k)
    return RelativeOdometry(idx, idx + 1, times[:-1], times[1:], noisy, covs)


def _gnss(true_path: Trajectory, odo: Odometry, noise: GnssNoise, gen: np.random.Generator) -> Gnss:
    t0, t1 = float(true_path.times[0]), float(true_path.times[-1])
    t = np.arange(t0, t1 + 1e-12, 1.0 / noise.rate_hz)
    xy = _poses_at(true_path, odo, t)[:, :2]
    # Gauss-Markov: e_k = a e_{k-1} + sqrt(1 - a^2) sigma_slow w_k, stationary start
    a = math.exp(-1.0 / (noise.rate_hz * noise.tau))
    w = gen.normal(0.0, 1.0, (t.size, 2))
    slow = np.empty((t.size, 2))
    if t.size:
        slow[0] = noise.sigma_slow * w[0]
        q = noise.sigma_slow * math.sqrt(1.0 - a * a)
        for k in range(1, t.size):  # a scalar recursion at 1-10 Hz: few thousand steps
            slow[k] = a * slow[k - 1] + q * w[k]
    fix = xy + slow + gen.normal(0.0, 1.0, xy.shape) * noise.sigma
    keep = np.ones(t.size, dtype=bool)
    if noise.outage_rate > 0:
        for s0 in gen.uniform(t0, t1, gen.poisson(noise.outage_rate * (t1 - t0))):
            keep &= ~((t >= s0) & (t < s0 + noise.outage_duration))
    total = math.hypot(noise.sigma, noise.sigma_slow)
    return Gnss(t[keep], fix[keep], np.full(int(keep.sum()), total))
