"""Simulated drives: a vehicle follows a path through a stand, scanning and logging odometry.

:func:`simulate_run` is the one-call simulator used by the detection, SLAM and fusion tests:

1. The vehicle is a unicycle (speed ``v``, yaw rate ``omega``) steered along the path by a
   pure-pursuit controller at the odometry rate (default 50 Hz); controls are piecewise
   constant between odometry samples and the true path is their *exact* integration
   (:func:`integrate_unicycle`), so noise-free odometry reproduces the truth to rounding.
2. Scans are taken at the scanner rate from the sensor pose (vehicle pose composed with the
   mounting offset) and simulated by :func:`~stemmap.sim.scanner.simulate_scans`.
3. Wheel odometry is the true controls with a speed scale error, white noise, a yaw-rate bias
   and wheel-slip events (:class:`OdometryNoise`). A second, independent source ("visual
   odometry") gives noisy relative pose increments between consecutive scans
   (:class:`VisualOdometryNoise`).

Path helpers (:func:`straight_path`, :func:`loop_path`, :func:`lawnmower_path`,
:func:`clear_corridor`) and the pure-pursuit controller live in :mod:`stemmap.sim.paths` and are
re-exported here.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.forest import Stand
from stemmap.sim.paths import (
    _pure_pursuit,
    clear_corridor,
    distance_to_polyline,
    lawnmower_path,
    loop_path,
    straight_path,
)
from stemmap.sim.scanner import ScannerModel, scanner_preset, simulate_scans
from stemmap.types import FloatArray, Pose2, ScanBatch, Trajectory, wrap_angle

__all__ = [
    "ODOMETRY_PRESETS",
    "Gnss",
    "GnssNoise",
    "Odometry",
    "OdometryNoise",
    "RelativeOdometry",
    "SimRun",
    "VisualOdometryNoise",
    "clear_corridor",
    "compose_poses",
    "distance_to_polyline",
    "integrate_unicycle",
    "lawnmower_path",
    "loop_path",
    "relative_poses",
    "simulate_run",
    "straight_path",
]

RngLike = np.random.Generator | int | None


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


@dataclass(frozen=True, eq=False)
class SimRun:
    """Everything one simulated drive produces, with ground truth.

    Attributes
    ----------
    stand : Stand
        The stand that was scanned (after :func:`clear_corridor`, if requested).
    scanner : ScannerModel
    scans : ScanBatch
        Ranges in the sensor frame ("no return" = ``inf``).
    true_poses : Trajectory
        Sensor pose per scan in the world frame (x, y, theta); ``frame="world"``.
    vehicle_poses : Trajectory
        Vehicle (odometry reference point) pose per scan in the world frame.
    sensor_offset : Pose2
        Sensor pose in the vehicle frame (``sensor = vehicle * offset``).
    hit_ids : ndarray of shape (S, N), int
        Ground truth per beam: tree index, -2 clutter, -1 nothing.
    mixed : ndarray of shape (S, N), bool
        Beams whose footprint straddled an edge (mixed pixels).
    odometry : Odometry
        Noisy wheel odometry (speed, yaw rate) at ``odom_rate_hz``.
    true_odometry : Odometry
        The exact controls; ``true_odometry.integrate(true_path.poses[0])`` is ``true_path``.
    true_path : Trajectory
        Vehicle pose at every odometry time, world frame.
    slipping : ndarray of shape (M,), bool
        Odometry samples inside a wheel-slip event.
    visual_odometry : RelativeOdometry
        Noisy increments between consecutive scans (vehicle frame).
    params : dict
        Every parameter of the scenario, for benchmark JSON output.
    gnss : Gnss or None
        GNSS fixes of the vehicle position (:class:`GnssNoise`).
    """

    stand: Stand
    scanner: ScannerModel
    scans: ScanBatch
    true_poses: Trajectory
    vehicle_poses: Trajectory
    sensor_offset: Pose2
    hit_ids: NDArray[np.int64]
    mixed: NDArray[np.bool_]
    odometry: Odometry
    true_odometry: Odometry
    true_path: Trajectory
    slipping: NDArray[np.bool_]
    visual_odometry: RelativeOdometry
    params: dict[str, Any] = field(default_factory=dict)
    gnss: Gnss | None = None

    def __len__(self) -> int:
        return len(self.scans)


# --------------------------------------------------------------------------------------------
# Pose algebra and the unicycle
# --------------------------------------------------------------------------------------------


def compose_poses(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a * b`` for (..., 3) pose arrays: ``b`` given in ``a``'s frame, mapped to a's parent."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    x = pa[..., 0] + c * pb[..., 0] - s * pb[..., 1]
    y = pa[..., 1] + s * pb[..., 0] + c * pb[..., 1]
    return np.stack((x, y, wrap_angle(pa[..., 2] + pb[..., 2])), axis=-1)


def relative_poses(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a^-1 * b`` for (..., 3) pose arrays: pose ``b`` expressed in the frame of pose ``a``."""
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    c, s = np.cos(pa[..., 2]), np.sin(pa[..., 2])
    dx = pb[..., 0] - pa[..., 0]
    dy = pb[..., 1] - pa[..., 1]
    return np.stack(
        (c * dx + s * dy, -s * dx + c * dy, wrap_angle(pb[..., 2] - pa[..., 2])), axis=-1
    )


def _arc_step(theta: FloatArray, v: FloatArray, w: FloatArray, dt: FloatArray) -> FloatArray:
    """Exact displacement (dx, dy) of a unicycle over ``dt`` at constant (v, w) from ``theta``.

    Uses ``v/w (sin(th + d) - sin th) = v dt sinc(d/2) cos(th + d/2)`` (and the cosine twin)
    with ``d = w dt``: exact, and free of the cancellation of the ``v/w`` form when ``w -> 0``.
    """
    dth = w * dt
    chord = v * dt * np.sinc(dth / (2.0 * np.pi))  # np.sinc(x) = sin(pi x) / (pi x)
    mid = theta + dth / 2.0
    return np.stack((chord * np.cos(mid), chord * np.sin(mid)), axis=-1)


def integrate_unicycle(
    pose0: ArrayLike, speed: ArrayLike, yaw_rate: ArrayLike, dt: ArrayLike
) -> FloatArray:
    """Exact integration of piecewise-constant unicycle controls.

    Parameters
    ----------
    pose0 : array_like of shape (3,)
    speed, yaw_rate, dt : array_like of shape (K,)
        Controls held over intervals of length ``dt`` (s).

    Returns
    -------
    ndarray of shape (K + 1, 3)
        Poses at the interval boundaries, starting with ``pose0``.

    Notes
    -----
    Over one interval ``theta' = theta + w dt``, ``x' = x + v/w (sin theta' - sin theta)``,
    ``y' = y + v/w (cos theta - cos theta')``, evaluated in the cancellation-free chord form
    ``v dt sinc(w dt / 2) (cos, sin)(theta + w dt / 2)`` (exact; straight line when w = 0).
    Headings accumulate without wrapping before the trig, then are wrapped to (-pi, pi].
    """
    p0 = np.asarray(pose0, dtype=np.float64).reshape(3)
    v = np.asarray(speed, dtype=np.float64).reshape(-1)
    w = np.asarray(yaw_rate, dtype=np.float64).reshape(-1)
    d = np.broadcast_to(np.asarray(dt, dtype=np.float64), v.shape)
    theta = p0[2] + np.concatenate(([0.0], np.cumsum(w * d)))
    steps = _arc_step(theta[:-1], v, w, d)
    xy = p0[:2] + np.concatenate((np.zeros((1, 2)), np.cumsum(steps, axis=0)))
    return np.column_stack((xy, wrap_angle(theta)))


# --------------------------------------------------------------------------------------------
# The run
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


def _poses_at(true_path: Trajectory, odo: Odometry, tq: FloatArray) -> FloatArray:
    """Exact vehicle poses at arbitrary times inside the run (arc from the previous sample)."""
    k = np.clip(np.searchsorted(odo.times, tq, side="right") - 1, 0, len(odo) - 1)
    base = true_path.poses[k]
    dt = tq - odo.times[k]
    d = _arc_step(base[:, 2], odo.speed[k], odo.yaw_rate[k], dt)
    return np.column_stack(
        (base[:, 0] + d[:, 0], base[:, 1] + d[:, 1], wrap_angle(base[:, 2] + odo.yaw_rate[k] * dt))
    )


def _skewed_scans(
    stand: Stand,
    model: ScannerModel,
    true_path: Trajectory,
    true_odo: Odometry,
    offset: Pose2,
    t_scan: FloatArray,
    beam_dt: float,
    gen: np.random.Generator,
) -> tuple[ScanBatch, NDArray[np.int64], NDArray[np.bool_]]:
    """Scans whose beams are cast from the pose at each beam's own time (sliced fan)."""
    n_b = model.n_beams
    n_slices = min(32, n_b // 2)
    edges = np.linspace(0, n_b, n_slices + 1).round().astype(np.int64)
    gens = gen.spawn(n_slices)
    ranges = np.empty((t_scan.size, n_b))
    hit = np.empty((t_scan.size, n_b), dtype=np.int64)
    mixed = np.empty((t_scan.size, n_b), dtype=bool)
    inc = model.angle_increment
    for j in range(n_slices):
        i0, i1 = int(edges[j]), int(edges[j + 1])
        t_mid = t_scan + beam_dt * (i0 + i1 - 1) / 2.0
        sens = compose_poses(_poses_at(true_path, true_odo, t_mid), offset.as_array())
        part = replace(
            model, angle_min=model.angle_min + i0 * inc, angle_max=model.angle_min + (i1 - 1) * inc
        )
        b, h, mx = simulate_scans(stand, sens, part, times=t_scan, rng=gens[j])
        ranges[:, i0:i1], hit[:, i0:i1], mixed[:, i0:i1] = b.ranges, h, mx
    batch = ScanBatch(
        ranges, t_scan, model.angle_min, inc, model.range_min, model.range_max, "laser"
    )
    return batch, hit, mixed


def simulate_run(
    stand: Stand,
    path: ArrayLike | Trajectory,
    *,
    scanner: ScannerModel | str | None = "sick_lms",
    speed: float = 1.0,
    rate_hz: float | None = None,
    odom_rate_hz: float = 50.0,
    odometry_noise: OdometryNoise | str | None = "wheel",
    vo_noise: VisualOdometryNoise | None = None,
    gnss_noise: GnssNoise | None = None,
    sensor_offset: Pose2 | None = None,
    lookahead: float = 2.0,
    max_yaw_rate: float = 0.8,
    corridor_half_width: float | None = None,
    max_scans: int | None = None,
    motion_skew: bool = False,
    rng: RngLike = None,
) -> SimRun:
    """Simulate a drive through ``stand``: scans, true poses, wheel and visual odometry.

    Parameters
    ----------
    stand : Stand
    path : array_like of shape (K, 2) or Trajectory
        Waypoints (metres, world frame) followed by a pure-pursuit controller at ``speed``; the
        drive starts at the first waypoint heading to the second and stops at the last. Or an
        explicit vehicle :class:`~stemmap.types.Trajectory`: its controls are derived by finite
        differences at ``odom_rate_hz`` and re-integrated (so the truth stays a unicycle).
    scanner : ScannerModel or preset name (``"sick_lms"``, ``"rplidar"``)
    speed : float, m/s, > 0
    rate_hz : float, optional
        Scan rate; default the scanner's ``scan_rate_hz``.
    odom_rate_hz : float
        Wheel-odometry rate (controls are constant between samples).
    odometry_noise : OdometryNoise or preset name (see :data:`ODOMETRY_PRESETS`) or None
    vo_noise : VisualOdometryNoise, optional (default :class:`VisualOdometryNoise()`)
    gnss_noise : GnssNoise, optional (default :class:`GnssNoise()`: 1 Hz, 0.5 m white + 1 m
        slowly correlated error, no outages)
    sensor_offset : Pose2, optional
        Sensor pose in the vehicle frame (default: at the vehicle reference point).
    lookahead : float, metres
        Pure-pursuit lookahead distance.
    max_yaw_rate : float, rad/s
    corridor_half_width : float, metres, optional
        If given, trees and clutter within this distance of the path are removed first
        (:func:`clear_corridor`); ``SimRun.stand`` is the cleared stand.
    max_scans : int, optional
        Keep only the first ``max_scans`` scans (and the odometry up to the last of them).
    motion_skew : bool
        If True, beam ``i`` is measured from the pose at ``time + i * dt_beam`` with
        ``dt_beam = angle_increment / (2 pi rate)`` (a mirror turning once per scan), as a
        real scanner does while the vehicle moves; ``scans.times`` and ``true_poses`` stay the
        time and pose of the first beam (the ROS ``LaserScan`` stamp convention). Poses are
        held constant over slices of <= 1/32 of the beams. Default False: every beam from the
        scan pose.
    rng : numpy Generator or int seed
        Independent child streams are spawned for the scanner, wheel odometry, visual
        odometry and GNSS, so changing one noise model does not change the others' draws.

    Returns
    -------
    SimRun

    Raises
    ------
    ConfigError
        On bad rates/speeds, unknown presets, or a path the vehicle cannot follow.
    InputError
        On malformed waypoints.

    Examples
    --------
    >>> from stemmap.sim import loop_path, random_stand
    >>> stand = random_stand(30, (30.0, 30.0), rng=1)
    >>> run = simulate_run(stand, loop_path((15.0, 15.0), (9.0, 6.0)), rate_hz=10.0,
    ...                    corridor_half_width=1.0, rng=2)
    >>> run.scans.ranges.shape == run.hit_ids.shape == (len(run), 361)
    True
    >>> end, start = run.true_path.poses[-1, :2], run.true_path.poses[0, :2]
    >>> bool(np.hypot(*(end - start)) < 0.1)  # the loop closes
    True
    """
    model = scanner_preset(scanner)
    rate = model.scan_rate_hz if rate_hz is None else float(rate_hz)
    if not (speed > 0 and rate > 0 and odom_rate_hz > 0 and lookahead > 0 and max_yaw_rate > 0):
        raise ConfigError(
            "simulate_run needs speed, rate_hz, odom_rate_hz, lookahead and max_yaw_rate > 0."
        )
    if isinstance(odometry_noise, str):
        try:
            onoise = ODOMETRY_PRESETS[odometry_noise]
        except KeyError as exc:
            raise ConfigError(
                f"unknown odometry noise preset {odometry_noise!r}; choose one of "
                f"{sorted(ODOMETRY_PRESETS)}."
            ) from exc
    else:
        onoise = odometry_noise or OdometryNoise()
    vnoise = vo_noise or VisualOdometryNoise()
    offset = sensor_offset or Pose2(0.0, 0.0, 0.0)
    gen = np.random.default_rng(rng)
    g_scan, g_odo, g_vo, g_gnss = gen.spawn(4)
    gnoise = gnss_noise or GnssNoise()
    dt = 1.0 / odom_rate_hz

    if isinstance(path, Trajectory):
        if len(path) < 2:
            raise InputError("simulate_run needs a Trajectory with at least 2 poses.")
        tq = np.arange(path.times[0], path.times[-1] + 1e-12, dt)
        pq = path.interpolate(tq)
        rel = relative_poses(pq[:-1], pq[1:])
        v_true = rel[:, 0] / dt
        w_true = rel[:, 2] / dt
        pose0 = pq[0]
        t0 = float(tq[0])
        path_xy = path.xy
    else:
        wp = np.asarray(path, dtype=np.float64)
        if wp.ndim != 2 or wp.shape[1] != 2 or wp.shape[0] < 2 or not np.all(np.isfinite(wp)):
            raise InputError(
                f"simulate_run path must be finite waypoints of shape (K >= 2, 2), got {wp.shape}."
            )
        d0 = wp[1] - wp[0]
        pose0 = np.array([wp[0, 0], wp[0, 1], math.atan2(d0[1], d0[0])])
        v_true, w_true = _pure_pursuit(wp, pose0, speed, dt, lookahead, max_yaw_rate)
        t0 = 0.0
        path_xy = wp
    if v_true.size < 1:
        raise ConfigError("the path is shorter than one odometry step; nothing to simulate.")
    if corridor_half_width is not None:
        stand = clear_corridor(stand, path_xy, corridor_half_width)

    t_odo: FloatArray = t0 + dt * np.arange(v_true.size + 1, dtype=np.float64)
    # the last sample's controls hold for one more period; repeat the last control
    true_odo = Odometry(t_odo, np.append(v_true, v_true[-1]), np.append(w_true, w_true[-1]))
    true_path = Trajectory(t_odo, integrate_unicycle(pose0, v_true, w_true, dt), frame="world")
    beam_dt = model.angle_increment / (2.0 * math.pi * rate)
    skew = motion_skew and model.n_beams >= 4
    # with motion skew a scan needs the drive to last for its whole sweep
    sweep = beam_dt * (model.n_beams - 1) if skew else 0.0
    t_scan = t0 + np.arange(0.0, t_odo[-1] - t0 - sweep + 1e-12, 1.0 / rate)
    if max_scans is not None:
        if max_scans < 2:
            raise ConfigError(f"max_scans must be >= 2, got {max_scans}.")
        t_scan = t_scan[:max_scans]
        keep_odo = t_odo <= t_scan[-1] + sweep + dt
        true_odo = Odometry(
            true_odo.times[keep_odo], true_odo.speed[keep_odo], true_odo.yaw_rate[keep_odo]
        )
        true_path = Trajectory(true_path.times[keep_odo], true_path.poses[keep_odo], "world")
    if t_scan.size < 2:
        raise ConfigError("the drive is shorter than two scan periods; lengthen the path.")
    vehicle = _poses_at(true_path, true_odo, t_scan)
    sensor = compose_poses(vehicle, offset.as_array())
    if skew:
        scans, hit, mixed = _skewed_scans(
            stand, model, true_path, true_odo, offset, t_scan, beam_dt, g_scan
        )
    else:
        scans, hit, mixed = simulate_scans(stand, sensor, model, times=t_scan, rng=g_scan)
    odo, slipping = _noisy_odometry(true_odo, onoise, g_odo)
    vo = _visual_odometry(vehicle, t_scan, vnoise, g_vo)
    gnss = _gnss(true_path, true_odo, gnoise, g_gnss)
    params: dict[str, Any] = {
        "scanner": asdict(model),
        "speed_m_s": speed,
        "scan_rate_hz": rate,
        "odom_rate_hz": odom_rate_hz,
        "odometry_noise": asdict(onoise),
        "vo_noise": asdict(vnoise),
        "gnss_noise": asdict(gnoise),
        "sensor_offset": [offset.x, offset.y, offset.theta],
        "lookahead_m": lookahead,
        "max_yaw_rate_rad_s": max_yaw_rate,
        "corridor_half_width_m": corridor_half_width,
        "motion_skew": motion_skew,
        "beam_time_increment_s": beam_dt if skew else 0.0,
        "n_scans": int(t_scan.size),
        "n_trees": stand.n_trees,
        "n_clutter_objects": stand.n_clutter_objects,
    }
    return SimRun(
        stand=stand,
        scanner=model,
        scans=scans,
        true_poses=Trajectory(t_scan, sensor, frame="world"),
        vehicle_poses=Trajectory(t_scan, vehicle, frame="world"),
        sensor_offset=offset,
        hit_ids=hit,
        mixed=mixed,
        odometry=odo,
        true_odometry=true_odo,
        true_path=true_path,
        slipping=slipping,
        visual_odometry=vo,
        params=params,
        gnss=gnss,
    )
