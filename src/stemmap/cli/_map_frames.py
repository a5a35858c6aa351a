"""``stemmap map FRAMES.npz --frontend ...``: the Munjer et al. (2025) pipeline from a frames
bundle (:mod:`stemmap.io.frames`) and a motion source.

Motion source, pluggable (``--motion``, :mod:`stemmap.cli._map_motion`):

* ``wheel`` with ``--odometry``: a velocity CSV ``time_s,speed,yaw_rate`` (wheel odometry,
  ``stemmap sim munjer`` writes one) or a pose CSV ``time_s,x,y,theta`` (any pose-output
  odometry: ``stemmap odometry --out traj.csv``, a SLAM front end), differenced into body-frame
  velocities (:func:`stemmap.slam.munjer.controls_from_trajectory`);
* ``lidar`` / ``visual`` / ``fused``: the trajectory of
  :func:`stemmap.cli._map_motion.motion_trajectory` (the paper's ICP + IMU EKF odometry on the
  bundle's own lidar frames with ``lidar``), then as a pose CSV.

Front ends: ``eb-lidar`` (EB-LiDAR on every lidar frame), ``daim`` (a detector's boxes + aligned
depth; ``--model`` an ONNX detector, default the segmentation detector; never truth boxes),
``ours`` (stemmap's own cloud detector on every lidar frame).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path
from typing import Any

from stemmap.errors import ConfigError, InputError

__all__ = ["Frontend", "frames_problem", "odometry_controls"]


class Frontend(StrEnum):
    eb_lidar = "eb-lidar"
    daim = "daim"
    ours = "ours"


def _header(path: Path) -> list[str]:
    with path.open(encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.strip() and not line.lstrip().startswith("#"):
                return [h.strip() for h in line.split(",")]
    raise InputError(f"odometry file {str(path)!r} is empty.")


def trajectory_controls(
    traj: Any, *, sigma_speed: float, sigma_yaw_rate: float
) -> tuple[Any, Any, str, Any]:
    """:func:`odometry_controls` of a pose trajectory already in memory."""
    from stemmap.slam.munjer import controls_from_trajectory

    c, m = controls_from_trajectory(traj, sigma_speed=sigma_speed, sigma_yaw_rate=sigma_yaw_rate)
    return c, m, "poses", traj


def odometry_controls(
    path: Path, *, sigma_speed: float, sigma_yaw_rate: float
) -> tuple[Any, Any, str, Any]:
    """Controls, motion model, kind ("velocities" / "poses") and the pose trajectory (None for
    velocities) from an odometry CSV.

    ``sigma_speed`` (m/s) and ``sigma_yaw_rate`` (rad/s), one-second averages, are the motion
    source's error: the FastSLAM motion noise.
    """
    from stemmap.cli._map_inputs import read_odometry_csv
    from stemmap.io.trajectory import read_trajectory_csv
    from stemmap.slam.base import Controls
    from stemmap.slam.motion import UnicycleModel

    if not path.is_file():
        raise InputError(f"odometry file {str(path)!r} does not exist.")
    cols = _header(path)
    if {"x", "y", "theta"} <= set(cols):
        traj = read_trajectory_csv(path, frame="odom")
        return trajectory_controls(traj, sigma_speed=sigma_speed, sigma_yaw_rate=sigma_yaw_rate)
    t, v, w = read_odometry_csv(path)
    model = UnicycleModel(sigma_speed=sigma_speed, sigma_steer=sigma_yaw_rate)
    return Controls(t, v, w, "unicycle"), model, "velocities", None


def motion_poses(controls: Any, motion_model: Any, traj: Any, times: Any) -> Any:
    """(F, 3) poses of the motion source at ``times``: the pose trajectory interpolated, or the
    velocities dead-reckoned from the origin (:func:`stemmap.slam.motion.rollout`); only poses
    relative to each other are used by :func:`stemmap.slam.munjer.accumulate_frames`."""
    from stemmap.slam.motion import rollout

    if traj is not None:
        return traj.interpolate(times)
    return rollout(motion_model, controls, times)


def frames_problem(
    source: Path,
    odometry: Path | None,
    frontend: Frontend,
    *,
    model: Path | None,
    sigma_speed: float,
    sigma_yaw_rate: float,
    motion: tuple[Any, dict[str, Any]] | None = None,
    eb_window: int = 1,
    before_compute: Callable[[], None] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """A SLAM problem from a frames bundle: motion source + per-frame detections.

    ``motion`` is a (trajectory, record) from :func:`stemmap.cli._map_motion.motion_trajectory`;
    None = ``odometry``, a velocity or pose CSV (None = the ``<stem>_odometry.csv`` beside
    ``source``). ``eb_window`` is :attr:`stemmap.cloud.munjer.MunjerConfig.window` of the
    EB-LiDAR front end (1 = per frame, as published; K > 1 clusters each frame with the K - 1
    before it, moved with the motion source's own poses: docs/algorithms/cloud.md,
    "Accumulated frames"). ``before_compute`` is called once the bundle and the motion
    source are read and checked, before the front end runs (the first-run compile notice).
    """
    from stemmap.cli._map_inputs import odometry_path
    from stemmap.cloud.munjer import MunjerConfig
    from stemmap.io.frames import read_frames_npz
    from stemmap.slam.munjer import (
        daim_observations,
        eb_lidar_observations,
        munjer_problem,
        ours_lidar_observations,
    )

    eb_cfg = MunjerConfig(window=eb_window)  # ConfigError for a window < 1
    if eb_window != 1 and frontend != Frontend.eb_lidar:
        raise ConfigError(
            "--eb-window is the EB-LiDAR frame window; use it with --frontend eb-lidar."
        )
    bundle = read_frames_npz(source)
    sig = {"sigma_speed": sigma_speed, "sigma_yaw_rate": sigma_yaw_rate}
    if motion is not None:
        if bundle.lidar is None and motion[1]["source"] != "visual":
            raise ConfigError(
                f"--motion {motion[1]['source']} needs lidar frames; {source} has none."
            )
        controls, motion_model, _, traj = trajectory_controls(motion[0], **sig)
        odo: Path | str = motion[1]["source"]
        kind = odo
    else:
        odo = odometry_path(source, odometry)
        controls, motion_model, kind, traj = odometry_controls(odo, **sig)
    t = bundle.times
    if t[0] < controls.times[0] - 1e-6 or t[-1] > controls.times[-1] + 1.0:
        raise InputError(
            f"the frames of {source} span {t[0]:.3f}-{t[-1]:.3f} s but the odometry {odo} spans "
            f"{controls.times[0]:.3f}-{controls.times[-1]:.3f} s: the time bases differ."
        )
    if frontend == Frontend.daim and bundle.images is None:
        raise ConfigError(f"--frontend daim needs RGB-D frames; {source} has none.")
    if frontend != Frontend.daim:
        if model is not None:
            raise ConfigError("--model is the DAIM trunk detector; use it with --frontend daim.")
        if bundle.lidar is None:
            raise ConfigError(f"--frontend {frontend.value} needs lidar frames; {source} has none.")
    if before_compute is not None:
        before_compute()
    if frontend == Frontend.daim:
        from stemmap.vision.detector import OnnxDetector, SegmentationDetector

        detector = OnnxDetector(model) if model is not None else SegmentationDetector()
        assert (
            bundle.images is not None
            and bundle.depths is not None
            and bundle.image_frames is not None
        )
        obs = daim_observations(
            list(bundle.images),
            list(bundle.depths),
            bundle.image_frames,
            t,
            bundle.rig(),
            detector,
        )
        max_range = 12.0
    else:
        assert bundle.lidar is not None
        if frontend == Frontend.eb_lidar:
            poses = None
            if eb_window > 1:  # the motion source's own poses at the frames (never the truth)
                poses = motion_poses(controls, motion_model, traj, t)
            obs = eb_lidar_observations(bundle.lidar, t, eb_cfg, poses=poses)
            max_range = 10.0  # the pass-through box
        else:
            obs = ours_lidar_observations(bundle.lidar, t)
            max_range = math.inf
    if len(obs) == 0:
        raise InputError(f"the {frontend.value} front end found no trunk in any frame of {source}.")
    # the map frame: the pose odometry's own frame, else the vehicle pose at the first frame
    p0 = (0.0, 0.0, 0.0) if traj is None else tuple(float(v) for v in traj.interpolate([t[0]])[0])
    problem = munjer_problem(
        obs,
        t,
        controls,
        motion_model,
        initial_pose=p0,  # type: ignore[arg-type]
        max_range=max_range,
        name=f"{source} ({frontend.value})",
    )
    ctx: dict[str, Any] = {"kind": "frames", "odometry": str(odo), "motion_source": kind}
    ctx["front_end"] = {"name": frontend.value}
    if frontend == Frontend.eb_lidar:
        ctx["front_end"]["eb_window"] = eb_window
    return problem, ctx
