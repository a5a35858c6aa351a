"""``stemmap map --motion``: where the mapper's motion comes from.

* ``wheel`` (default): the log's own odometry -- ``--odometry FILE`` (a ``time_s,speed,yaw_rate``
  CSV, or for a frames bundle also a ``time_s,x,y,theta`` pose CSV), the ``<stem>_odometry.csv``
  beside a scan file, or a bag's nav_msgs/Odometry topic;
* ``lidar``: KISS-ICP scan-to-map odometry on the log's own scans or 3D frames
  (:func:`stemmap.cli._odometry.lidar_front_end`, ``stemmap odometry``'s defaults), fused with
  ``--imu`` (gyro + wheel speed) when given;
* ``visual``: stereo / RGB-D visual odometry of ``--camera`` (a camera frames folder, a bag with
  Image + CameraInfo topics -- the input bag itself when it has them -- or the trajectory CSV
  ``stemmap odometry --camera ... --out vo.csv`` wrote);
* ``fused``: the visual-lidar paper's loose coupling (§2.4): the visual odometry as body-frame
  velocities in the EKF of the lidar odometry (+ ``--imu``),
  :func:`stemmap.odometry.inertial.fuse_front_ends`.

The chosen trajectory becomes the mapper's controls (body-frame velocities of each interval,
:func:`stemmap.slam.munjer.controls_from_trajectory` with its default ``lateral="drop"``: the
sideways part of each step is left out; docs/algorithms/slam.md, "Controls from a pose
trajectory"). ``--odometry lidar`` (the word), the
earlier spelling of ``--motion lidar``, still works with a deprecation warning.

Every run records ``motion`` in metrics.json and run.json: the source, what fed it, the path
length and a **drift estimate** in % of distance with the method that produced it (the
source's own noise model propagated to the end of the run: an estimate, not a measurement;
docs/algorithms/odometry.md).
"""

from __future__ import annotations

import math
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.cli._common import console
from stemmap.errors import ConfigError, InputError

__all__ = [
    "LIDAR_WORD",
    "WHEEL_SIGMA_SCALE",
    "WHEEL_SIGMA_YAW_BIAS",
    "Motion",
    "motion_trajectory",
    "resolve_motion",
    "vehicle_path",
    "visual_drift_estimate",
    "wheel_drift_estimate",
]

#: 1-sigma speed scale error of wheel odometry (fraction, 0.5 %): Victoria Park's encoder
#: against its iSAM2 path over 30-60 m windows (robust RMS 0.50-0.57 %; straight 10-30 m
#: chords 0.3-0.45 %); its GPS resolves it only over 200 m (0.25 % after its own noise).
#: docs/algorithms/odometry.md, "Wheel odometry" (benchmarks/wheel_drift_victoria_park.py).
WHEEL_SIGMA_SCALE = 0.005
#: 1-sigma constant yaw-rate bias of wheel odometry (rad/s, 0.17 deg/s): Victoria Park against
#: its GPS over 100-200 m windows (robust RMS 0.0031-0.0034 after the GPS's own noise; iSAM2
#: path 0.0023-0.0031 over 30-200 m). Same doc and benchmark.
WHEEL_SIGMA_YAW_BIAS = 0.003

#: ``--odometry lidar``: the deprecated spelling of ``--motion lidar``.
LIDAR_WORD = "lidar"


class Motion(StrEnum):
    wheel = "wheel"
    lidar = "lidar"
    visual = "visual"
    fused = "fused"


def resolve_motion(
    motion: Motion | None, odometry: Path | None, *, camera: Path | None, imu: Path | None
) -> tuple[Motion, Path | None]:
    """The motion source and the ``--odometry`` file after validating the combination.

    ``--odometry lidar`` maps to ``--motion lidar`` (warning on stderr). Raises ConfigError for
    combinations that would silently ignore an option.
    """
    if odometry is not None and str(odometry) == LIDAR_WORD and not odometry.exists():
        console.print(
            "warning: '--odometry lidar' is deprecated; use '--motion lidar' (--odometry is "
            "for odometry files).",
            markup=False,
        )
        if motion not in (None, Motion.lidar):
            raise ConfigError(
                f"--odometry lidar contradicts --motion {motion.value}; give --motion only."
            )
        motion, odometry = Motion.lidar, None
    motion = motion or Motion.wheel
    if motion != Motion.wheel and odometry is not None:
        raise ConfigError(
            f"--odometry {odometry} is the wheel motion source; --motion {motion.value} does not "
            "use it (drop it, or use --motion wheel)."
        )
    if camera is not None and motion not in (Motion.visual, Motion.fused):
        raise ConfigError(
            f"--camera feeds the visual odometry: use it with --motion visual or fused, not "
            f"{motion.value}."
        )
    if imu is not None and motion not in (Motion.lidar, Motion.fused):
        raise ConfigError(
            f"--imu is fused with the lidar odometry: use it with --motion lidar or fused, not "
            f"{motion.value}."
        )
    return motion, odometry


#: ``stemmap odometry``'s defaults, used by ``--motion lidar|fused``.
LIDAR_DEFAULTS: dict[str, Any] = {
    "topic": None,
    "imu_topic": None,
    "odom_topic": None,
    "rate": None,
    "max_range": 100.0,
    "min_range": 0.5,
    "voxel": None,
    "keep_ground": False,
}


def _camera_source(source: Path, camera: Path | None) -> Path:
    """``--camera``, else the input bag when it carries Image topics."""
    if camera is not None:
        return camera
    from stemmap.io.rosbag import is_bag, list_topics

    if is_bag(source) and any(m.endswith("/Image") for m in list_topics(source).values()):
        return source
    raise ConfigError(
        f"--motion visual/fused needs camera frames: {source} has no Image topic; pass --camera "
        "(a frames folder, a bag with Image + CameraInfo, or a trajectory CSV from `stemmap "
        "odometry --camera`)."
    )


def _visual(camera: Path, **camera_options: Any) -> tuple[Any, Any, dict[str, Any]]:
    """The visual odometry's vehicle path, its velocity source for the EKF and a summary."""
    from stemmap.odometry.fusion import velocities_from_poses
    from stemmap.odometry.visual import visual_velocity_sigma

    keep = None
    if camera.is_file() and camera.suffix.lower() == ".csv":
        from stemmap.io.trajectory import read_trajectory_csv

        traj = read_trajectory_csv(camera, frame="odom")
        info: dict[str, Any] = {
            "camera": str(camera),
            "kind": "trajectory CSV",
            "frames": len(traj),
        }
    else:
        from stemmap.cli._odometry_camera import camera_trajectory

        traj, res, summary = camera_trajectory(camera, **camera_options)
        info = {"camera": str(camera), **summary}
        keep = res.ok[1:] & res.ok[:-1]  # as visual_odometry_source: drop lost-frame steps
    if len(traj) < 2:
        raise InputError(f"the visual odometry of {camera} has {len(traj)} frame(s); need 2.")
    sv, sw = visual_velocity_sigma(float(np.median(np.diff(traj.times))))
    src = velocities_from_poses(traj, sigma_speed=sv, sigma_yaw_rate=sw, name="visual odometry")
    if keep is not None:
        if not keep.any():
            raise InputError(f"the visual odometry of {camera} lost every frame.")
        src = src.take(keep)
    return traj, src, info


def _random_walk_percent(step_var_xy: Any, distance: float) -> float | None:
    """100 * sqrt(sum of per-step xy variances) / distance (independent steps)."""
    v = np.asarray(step_var_xy, dtype=np.float64)
    v = v[np.isfinite(v)]
    if distance <= 0 or v.size == 0:
        return None
    return 100.0 * math.sqrt(float(v.sum())) / distance


def visual_drift_estimate(traj: Any) -> dict[str, Any]:
    """The visual odometry's drift estimate for its path ``traj``: a random walk in the distance
    travelled (:func:`stemmap.odometry.drift.distance_random_walk_variance` with
    :data:`stemmap.odometry.visual.VISUAL_DRIFT_XY_PER_SQRT_M`), so ``100 c / sqrt(d)`` % of
    ``d`` metres whatever the frame rate. Until Dec 4 every frame was one independent step of
    ``VISUAL_STEP_SIGMA[0]`` per axis, which grew with the square root of the frame count
    (0.79x the measured end drift at 5 Hz, 1.98x at 40 Hz; docs/algorithms/visual-odometry.md
    "Drift estimate")."""
    from stemmap.eval.trajectory import path_length
    from stemmap.odometry.drift import distance_random_walk_variance
    from stemmap.odometry.visual import VISUAL_DRIFT_XY_PER_SQRT_M

    dist = path_length(traj)
    var = distance_random_walk_variance(VISUAL_DRIFT_XY_PER_SQRT_M, dist)
    return {
        "distance_m": round(dist, 3),
        "drift_estimate_percent": _random_walk_percent([var], dist),
        "drift_method": "visual odometry random walk per distance (VISUAL_DRIFT_XY_PER_SQRT_M, "
        "measured on simulated stereo drives only); scale error not included",
    }


def vehicle_path(traj: Any, sensor_offset: tuple[float, float]) -> Any:
    """The vehicle reference point's path from the lidar's (``sensor = vehicle * offset``)."""
    a, b = sensor_offset
    if a == 0 and b == 0:
        return traj
    from stemmap.slam.motion import compose
    from stemmap.types import Trajectory

    return Trajectory(traj.times, compose(traj.poses, np.array([-a, -b, 0.0])), frame=traj.frame)


def wheel_drift_estimate(
    controls: Any,
    model: Any,
    *,
    sigma_scale: float | None = None,
    sigma_bias: float | None = None,
) -> dict[str, Any]:
    """The wheel odometry's drift estimate: the mapper's motion model propagated to the end of
    the run (first order, along the dead-reckoned path of the controls), plus an unknown but
    constant speed scale error and yaw-rate bias.

    **Random walk** (the motion model's white noise). Each control interval ``k`` (``dt_k`` s,
    held speed and yaw rate) adds independent errors of the
    :class:`~stemmap.slam.motion.UnicycleModel`: distance ``sigma_speed² dt_k`` along the
    heading, sideways ``sigma_lateral² dt_k``, and heading ``sigma_steer² dt_k``. A heading
    error made at ``p_k`` (the interval's mid point) turns the rest of the path about ``p_k``,
    so it moves the end point by ``dtheta_k * |p_end - p_k|``. The end point's xy variance is::

        V_rw = sum_k dt_k (sigma_speed² + sigma_lateral² + sigma_steer² |p_end - p_k|²)

    (the linearised covariance propagation of the EKF prediction, Thrun, Burgard & Fox,
    "Probabilistic Robotics" 2005, §5.4 and §3.3, summed in closed form). On a straight drive
    of ``T`` s at speed ``v`` the heading term is ``sigma_steer² v² T³ / 3``: the cross-track
    error grows as ``T^1.5``, faster than the speed term's ``sqrt(T)``.

    **Systematic** (the same first-order propagation, but one error for the whole run, so the
    steps add coherently, as vectors, not as variances). A speed scale error ``s`` (speed read
    ``(1 + s)`` times too large, e.g. a wrong wheel radius) moves the end point by
    ``s (p_end - p_0)``; a constant yaw-rate bias ``b`` (rad/s, a gyro or steering offset)
    adds ``b (t - t_0)`` to the heading, which moves the end point by ``b J sum_k dt_k (p_end -
    p_k)`` (``J`` the 90° rotation). With ``s ~ N(0, sigma_scale²)`` and ``b ~ N(0,
    sigma_bias²)`` independent::

        V_sys = sigma_scale² |p_end - p_0|² + sigma_bias² |sum_k dt_k (p_end - p_k)|²

    On a straight drive these are ``sigma_scale v T`` (linear in the distance) and
    ``sigma_bias v T² / 2`` (quadratic); on a closed loop the scale term vanishes at the end
    (first order). The reported estimate is ``100 sqrt(V_rw + V_sys) / distance``; the
    random-walk part alone is ``drift_random_percent``.

    ``sigma_scale`` and ``sigma_bias`` default to :data:`WHEEL_SIGMA_SCALE` and
    :data:`WHEEL_SIGMA_YAW_BIAS`, measured on real wheel odometry (Victoria Park against its GPS,
    docs/algorithms/odometry.md "Wheel odometry"); 0 leaves a term out.
    """
    sig_s = WHEEL_SIGMA_SCALE if sigma_scale is None else float(sigma_scale)
    sig_b = WHEEL_SIGMA_YAW_BIAS if sigma_bias is None else float(sigma_bias)
    if not (math.isfinite(sig_s) and sig_s >= 0 and math.isfinite(sig_b) and sig_b >= 0):
        raise ConfigError(
            f"wheel drift estimate: sigma_scale and sigma_bias must be finite and >= 0, got "
            f"{sig_s}, {sig_b}."
        )
    t = np.asarray(controls.times, dtype=np.float64)
    dt = np.diff(t)
    v = np.asarray(controls.speed, dtype=np.float64)[:-1]
    w = np.asarray(controls.steer, dtype=np.float64)[:-1]  # unicycle: yaw rate, rad/s
    dist = float(np.sum(np.abs(v) * dt))
    heading = np.concatenate(([0.0], np.cumsum(w * dt)))[:-1] + 0.5 * w * dt  # mid heading
    step = (v * dt)[:, None] * np.column_stack((np.cos(heading), np.sin(heading)))
    start = np.cumsum(step, axis=0) - step  # each interval's start, the run starting at 0
    end = start[-1] + step[-1] if dt.size else np.zeros(2)
    arm = end - (start + 0.5 * step)  # p_end - p_k
    lever2 = np.sum(arm**2, axis=1)
    sig_lat = float(getattr(model, "sigma_lateral", 0.0))
    var_along = (model.sigma_speed**2 + sig_lat**2) * dt  # (m/s)^2 per 1-s average * s -> m^2
    var_heading = model.sigma_steer**2 * dt * lever2  # rad^2 * m^2
    random = _random_walk_percent(var_along + var_heading, dist)
    var_sys = sig_s**2 * float(end @ end) + sig_b**2 * float(
        np.sum((dt[:, None] * arm).sum(0) ** 2)
    )
    total = None if random is None else math.hypot(random, 100.0 * math.sqrt(var_sys) / dist)
    return {
        "distance_m": round(dist, 3),
        "drift_estimate_percent": total,
        "drift_random_percent": random,
        "drift_method": "motion-model speed and yaw-rate noise (sigma_speed, sigma_yaw_rate, "
        "1-s averages) propagated along the dead-reckoned path, plus a constant speed scale "
        "error (sigma_scale) and yaw-rate bias (sigma_yaw_rate_bias, rad/s; defaults measured "
        "on real wheel odometry, Victoria Park)",
        "sigma_scale": sig_s,
        "sigma_yaw_rate_bias": sig_b,
    }


def motion_trajectory(
    source: Path,
    motion: Motion,
    *,
    camera: Path | None,
    imu: Path | None,
    quiet: bool = True,
    camera_options: dict[str, Any] | None = None,
    lidar_options: dict[str, Any] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """The planar path of ``motion`` (``lidar``, ``visual`` or ``fused``) for the log
    ``source`` (a scan file, a frames bundle or a bag), frame ``odom`` (the sensor at the first
    frame), and the ``motion`` record for metrics.json. ``camera_options`` go to
    :func:`stemmap.cli._odometry_camera.camera_trajectory` (topics, max_corners, baseline),
    ``lidar_options`` override :data:`LIDAR_DEFAULTS` (``stemmap odometry``'s options).

    Raises
    ------
    ConfigError
        ``visual`` / ``fused`` without camera frames; ``lidar`` / ``fused`` on a detections CSV
        (no scans to register).
    """
    from stemmap.cli._map_inputs import is_detections_csv
    from stemmap.eval.trajectory import path_length

    if motion == Motion.wheel:
        raise ConfigError("motion_trajectory: the wheel source is read by the input's reader.")
    info: dict[str, Any] = {"source": motion.value}
    if motion in (Motion.lidar, Motion.fused) and is_detections_csv(source):
        raise ConfigError(
            f"--motion {motion.value} registers the log's scans; {source} is a detections CSV "
            "(no scans): use --motion wheel or visual."
        )
    if motion in (Motion.visual, Motion.fused):
        cam = _camera_source(source, camera)
        vtraj, vsrc, vinfo = _visual(cam, **(camera_options or {}))
        info["visual"] = vinfo
    if motion == Motion.visual:
        info.update(visual_drift_estimate(vtraj))
        return vtraj, info
    from stemmap.cli._odometry import lidar_front_end

    extra = [vsrc] if motion == Motion.fused else []
    opts = {**LIDAR_DEFAULTS, **(lidar_options or {})}
    traj, lidar, fused, summary = lidar_front_end(source, imu=imu, quiet=quiet, extra=extra, **opts)
    info["lidar"] = summary
    info["imu"] = None if imu is None else str(imu)
    if motion == Motion.fused:
        t_lo, t_hi = float(vsrc.interval_start[0]), float(vsrc.times[-1])
        if t_lo > traj.times[-1] or t_hi < traj.times[0]:
            raise InputError(
                f"the camera frames span {t_lo:.3f}-{t_hi:.3f} s but the scans of {source} span "
                f"{traj.times[0]:.3f}-{traj.times[-1]:.3f} s: the time bases differ."
            )
    dist = path_length(traj)
    info["distance_m"] = round(dist, 3)
    info["drift_estimate_percent"] = _random_walk_percent([lidar.drift_xy_variance(dist)], dist)
    info["drift_method"] = (
        "lidar scan-to-map random walk per distance (drift_xy_per_sqrt_m, measured on "
        "simulated drives) plus the registration covariances above their floor"
        + ("; the fused path follows the lidar's scan-to-map poses" if fused is not None else "")
    )
    if fused is not None:
        info["ekf_final_position_std_m"] = float(
            math.sqrt(max(float(np.trace(fused.covariances[-1, :2, :2])), 0.0))
        )
    if motion == Motion.fused:
        info["visual_vs_lidar_percent"] = _disagreement_percent(vtraj, lidar.trajectory())
        from stemmap.cli._map_handedness import turn_sense_warning

        what = "the camera's visual odometry"
        warning = turn_sense_warning(lidar.trajectory(), vtraj.times, vtraj.poses[:, 2], what)
        if warning is not None:
            info["turn_sense_warning"] = warning
            console.print(f"[yellow]warning:[/yellow] {warning}")
    return traj, info


def _disagreement_percent(a: Any, b: Any, delta: float = 10.0) -> float | None:
    """Mean translational relative pose error of ``a`` against ``b`` over ``delta``-metre
    stretches of ``b``, % of ``delta``: how much two odometries disagree (a measured bound on
    the worse one's drift); None when the run is shorter than ``delta``."""
    from stemmap.eval.trajectory import rpe

    r = rpe(a, b, delta=delta, min_step=0.5)  # b's jitter must not shorten the stretches
    return 100.0 * r.trans_mean / delta if r else None
