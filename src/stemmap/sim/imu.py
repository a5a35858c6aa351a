"""IMU and wheel-speed simulation from a true drive (the inputs of Munjer 2025's odometry EKF).

Munjer et al. (2025, §2) carry an XSens IMU and wheel encoders on a differential-drive robot;
the paper gives no sensor error figures, so the presets below take theirs from data sheets
and from the wheel-odometry presets of :mod:`stemmap.sim.motion_sensors`:

* gyro ``z``: ``ω + b(t) + n``, a turn-on bias ``b0`` plus a random walk (bias instability),
  white noise per sample;
* accelerometer (specific force, body frame, x forward, y left, z up): forward acceleration
  ``dv/dt``, centripetal ``v ω``, gravity ``+g``, each with a constant bias and white noise
  (planar drive: no roll or pitch);
* wheel speed at its own rate: ``v * scale * (1 + slip_excess during slips) + n``, slips a
  Poisson process as in :class:`stemmap.sim.motion_sensors.OdometryNoise`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError
from stemmap.io.imu import InertialLog
from stemmap.sim.motion_sensors import Odometry

__all__ = ["IMU_PRESETS", "ImuNoise", "ImuSim", "simulate_imu"]

GRAVITY = 9.81


@dataclass(frozen=True)
class ImuNoise:
    """IMU + wheel-speed error model.

    Parameters
    ----------
    gyro_bias : float, rad/s
        Turn-on yaw-rate bias (uncalibrated).
    gyro_bias_walk : float, rad/s/√s
        Random-walk density of the bias (bias instability).
    gyro_noise : float, rad/s
        1-sigma white noise per gyro sample.
    accel_bias : float, m/s²
        Constant bias on each accelerometer axis.
    accel_noise : float, m/s²
        1-sigma white noise per accelerometer sample and axis.
    wheel_scale : float, > 0
        Multiplicative wheel-speed error (tyre radius, sinkage): 1.02 reads 2 % fast.
    wheel_noise : float, m/s
        1-sigma white noise per wheel sample.
    slip_rate : float, events/s
    slip_duration : float, s
    slip_excess : float
        During a slip the wheel reads ``(1 + slip_excess)`` times the true speed.
    """

    gyro_bias: float = math.radians(0.2)
    gyro_bias_walk: float = math.radians(0.005)
    gyro_noise: float = math.radians(0.1)
    accel_bias: float = 0.02
    accel_noise: float = 0.02
    wheel_scale: float = 1.02
    wheel_noise: float = 0.05
    slip_rate: float = 0.05
    slip_duration: float = 0.8
    slip_excess: float = 0.3

    def __post_init__(self) -> None:
        for name in (
            "gyro_bias_walk",
            "gyro_noise",
            "accel_noise",
            "wheel_noise",
            "slip_rate",
            "slip_excess",
        ):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"ImuNoise.{name} must be >= 0, got {getattr(self, name)}.")
        if not (self.wheel_scale > 0 and self.slip_duration > 0):
            raise ConfigError("ImuNoise needs wheel_scale > 0 and slip_duration > 0.")
        if not (math.isfinite(self.gyro_bias) and math.isfinite(self.accel_bias)):
            raise ConfigError("ImuNoise biases must be finite.")


#: Named error levels. ``none``: perfect sensors. ``xsens``: an MTi-class MEMS IMU (the
#: Munjer robot's XSens; data-sheet gyro noise 0.007 deg/s/√Hz -> 0.07 deg/s at 100 Hz,
#: rounded up, 0.2 deg/s uncalibrated turn-on bias) with wheels on rough ground (2 % scale,
#: slips every ~20 s). ``mems``: a consumer IMU (1 deg/s bias, 0.5 deg/s noise) and worse
#: wheels (4 % scale, slips every ~10 s).
IMU_PRESETS: dict[str, ImuNoise] = {
    "none": ImuNoise(0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.8, 0.0),
    "xsens": ImuNoise(),
    "mems": ImuNoise(
        gyro_bias=math.radians(1.0),
        gyro_bias_walk=math.radians(0.02),
        gyro_noise=math.radians(0.5),
        accel_bias=0.1,
        accel_noise=0.05,
        wheel_scale=1.04,
        wheel_noise=0.08,
        slip_rate=0.1,
        slip_duration=0.8,
        slip_excess=0.5,
    ),
}


@dataclass(frozen=True, eq=False)
class ImuSim:
    """Output of :func:`simulate_imu`.

    Attributes
    ----------
    log : InertialLog
        The simulated measurements (IMU and wheel rows merged on one time base).
    gyro_bias : ndarray (M,), rad/s
        True bias at each IMU sample time.
    slipping : ndarray (W,), bool
        Wheel samples inside a slip.
    params : dict
    """

    log: InertialLog
    gyro_bias: NDArray[np.float64]
    slipping: NDArray[np.bool_]
    params: dict[str, Any] = field(default_factory=dict)


def simulate_imu(
    truth: Odometry,
    *,
    noise: ImuNoise | str = "xsens",
    wheel_rate_hz: float = 50.0,
    rng: np.random.Generator | int | None = None,
) -> ImuSim:
    """Simulate an IMU at the rate of ``truth`` and wheel speed at ``wheel_rate_hz``.

    Parameters
    ----------
    truth : Odometry
        The exact piecewise-constant controls of the drive (``SimRun.true_odometry``); the IMU
        samples at its times (run :func:`~stemmap.sim.trajectory.simulate_run` with
        ``odom_rate_hz=100`` for a 100 Hz IMU).
    noise : ImuNoise or preset name (:data:`IMU_PRESETS`)
    wheel_rate_hz : float, > 0
    rng : Generator or seed

    Returns
    -------
    ImuSim
    """
    if isinstance(noise, str):
        if noise not in IMU_PRESETS:
            raise ConfigError(
                f"unknown IMU noise preset {noise!r}; choose one of {', '.join(IMU_PRESETS)}."
            )
        noise = IMU_PRESETS[noise]
    if not wheel_rate_hz > 0:
        raise ConfigError(f"wheel_rate_hz must be > 0, got {wheel_rate_hz}.")
    if len(truth) < 2:
        raise ConfigError("simulate_imu needs a drive of at least 2 control samples.")
    gen = np.random.default_rng(rng)
    g_gyro, g_acc, g_wheel, g_slip = gen.spawn(4)
    t = truth.times
    v, w = truth.speed, truth.yaw_rate
    n = t.shape[0]
    dt = np.diff(t)
    # gyro: turn-on bias + random walk + white noise
    steps = g_gyro.normal(0.0, 1.0, n - 1) * noise.gyro_bias_walk * np.sqrt(dt)
    bias = noise.gyro_bias + np.concatenate(([0.0], np.cumsum(steps)))
    gz = w + bias + g_gyro.normal(0.0, noise.gyro_noise, n)
    gxy = g_gyro.normal(0.0, noise.gyro_noise, (n, 2))
    # accelerometer: dv/dt of the piecewise-constant speed (at the change), v ω, gravity
    ax = np.concatenate((np.diff(v) / dt, [0.0]))
    acc = np.column_stack((ax, v * w, np.full(n, GRAVITY)))
    acc = acc + noise.accel_bias + g_acc.normal(0.0, noise.accel_noise, (n, 3))
    # wheel speed at its own rate, holding the true control in force at each sample
    tw = np.arange(t[0], t[-1] + 1e-9, 1.0 / wheel_rate_hz)
    k = np.clip(np.searchsorted(t, tw, side="right") - 1, 0, n - 1)
    slipping = np.zeros(tw.shape[0], dtype=bool)
    if noise.slip_rate > 0:
        n_ev = g_slip.poisson(noise.slip_rate * (t[-1] - t[0]))
        for s0 in g_slip.uniform(t[0], t[-1], n_ev):
            slipping |= (tw >= s0) & (tw < s0 + noise.slip_duration)
    ws = v[k] * noise.wheel_scale * np.where(slipping, 1.0 + noise.slip_excess, 1.0)
    ws = ws + g_wheel.normal(0.0, noise.wheel_noise, tw.shape[0])
    log = InertialLog.merge(t, np.column_stack((gxy, gz)), acc, tw, ws)
    params = {"imu_rate_hz": float(1.0 / np.median(dt)), "wheel_rate_hz": wheel_rate_hz}
    params.update(asdict(noise))
    return ImuSim(log, bias, slipping, params)
