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
:func:`clear_corridor`) and the pure-pursuit controller live in :mod:`stemmap.sim.paths`, the
pose algebra and the exact unicycle (:func:`compose_poses`, :func:`relative_poses`,
:func:`integrate_unicycle`) in :mod:`stemmap.sim.unicycle`, and the odometry and GNSS error
models and records (:class:`OdometryNoise`, :class:`Odometry`, ...) in
:mod:`stemmap.sim.motion_sensors`; all are re-exported here.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.forest import Stand
from stemmap.sim.motion_sensors import (
    ODOMETRY_PRESETS,
    Gnss,
    GnssNoise,
    Odometry,
    OdometryNoise,
    RelativeOdometry,
    VisualOdometryNoise,
    _gnss,
    _noisy_odometry,
    _visual_odometry,
)
from stemmap.sim.paths import (
    _pure_pursuit,
    clear_corridor,
    distance_to_polyline,
    lawnmower_path,
    loop_path,
    straight_path,
)
from stemmap.sim.scanner import ScannerModel, scanner_preset, simulate_scans
from stemmap.sim.unicycle import _poses_at, compose_poses, integrate_unicycle, relative_poses
from stemmap.types import FloatArray, Pose2, ScanBatch, Trajectory

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
