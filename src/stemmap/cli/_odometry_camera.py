"""Camera side of ``stemmap odometry``: stereo / RGB-D visual odometry of a frames folder.

:func:`camera_odometry` is what the ``odometry`` command calls for ``--camera FRAMES``; it reads
the folder (layout: :mod:`stemmap.io.camera_frames`), runs
:func:`stemmap.odometry.visual.run_visual_odometry` and writes the vehicle's planar path as
``time_s,x,y,theta`` CSV (frame: the vehicle at the first image).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import InputError
from stemmap.types import Trajectory

__all__ = ["camera_odometry", "camera_trajectory"]

log = logging.getLogger(__name__)

#: Camera looking along the vehicle's x axis, at its origin: the mount assumed when
#: ``camera.json`` has no ``vehicle_from_camera``.
_DEFAULT_MOUNT = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def camera_odometry(
    frames_dir: Path, out: Path, **options: Any
) -> tuple[Trajectory, dict[str, Any]]:
    """Visual odometry of a frames folder or a ROS bag, written to ``out`` (CSV); ``options``
    are those of :func:`camera_trajectory` (topics, max_corners, baseline). Returns the
    trajectory and its summary (frames, mode, keyframes, lost_frames, distance_m).
    """
    from stemmap.io.trajectory import write_trajectory_csv

    traj, _, summary = camera_trajectory(frames_dir, **options)
    write_trajectory_csv(out, traj)
    return traj, summary


def camera_trajectory(
    frames_dir: Path,
    *,
    max_corners: int | None = None,
    left_topic: str | None = None,
    right_topic: str | None = None,
    depth_topic: str | None = None,
    info_topic: str | None = None,
    baseline: float | None = None,
) -> tuple[Trajectory, Any, dict[str, Any]]:
    """The planar vehicle path of the visual odometry of a frames folder or a bag (frame:
    the vehicle at the first image), the :class:`~stemmap.odometry.visual.VisualOdometryResult`
    and a summary (frames, mode, keyframes, lost_frames, distance_m).

    A bag (``.bag``, ROS2 folder, ``.db3``, ``.mcap``) is read by
    :func:`stemmap.io.camera_bag.read_camera_bag` with the given topics (guessed when None);
    a folder by :func:`stemmap.io.camera_frames.read_camera_frames`.
    """
    from dataclasses import replace

    from stemmap.eval.trajectory import path_length
    from stemmap.io.camera_bag import read_camera_bag
    from stemmap.io.camera_frames import read_camera_frames
    from stemmap.io.rosbag import is_bag
    from stemmap.odometry.visual import (
        VisualOdometryConfig,
        VoStatus,
        planar_from_camera,
        run_visual_odometry,
    )

    frames: Any
    if is_bag(frames_dir):
        frames = read_camera_bag(
            frames_dir,
            left_topic=left_topic,
            right_topic=right_topic,
            depth_topic=depth_topic,
            info_topic=info_topic,
            baseline=baseline,
        )
    elif frames_dir.is_dir():
        frames = read_camera_frames(frames_dir)
    else:
        raise InputError(
            f"{frames_dir}: not a camera frames folder or a ROS bag (.bag, ROS2 folder, .db3, "
            ".mcap)."
        )
    cfg = VisualOdometryConfig()
    if max_corners is not None:
        cfg = replace(cfg, max_corners=max_corners)
    res = run_visual_odometry(frames, frames.calibration, cfg)
    mount = frames.vehicle_from_camera
    if mount is None:
        log.info(
            "%s: no vehicle_from_camera in camera.json; camera at the vehicle origin", frames_dir
        )
        mount = _DEFAULT_MOUNT
    traj = planar_from_camera(res, mount)
    summary = {
        "frames": len(res),
        "mode": "stereo" if frames.calibration.is_stereo else "RGB-D",
        "keyframes": int(np.sum(res.status == VoStatus.KEYFRAME)),
        "lost_frames": int(np.sum(~res.ok)),
        "distance_m": path_length(traj),
    }
    if summary["lost_frames"]:
        from stemmap.cli._common import console

        # as the lidar odometry's held frames: the path there is a guess, say so once
        console.print(
            f"warning: the visual odometry lost {summary['lost_frames']} of {len(res)} camera "
            "frames (too few corners tracked or PnP failed); their poses are extrapolated at "
            "constant velocity. Many lost frames mean images too far apart for the speed (a "
            "higher frame rate) or too little texture or light.",
            markup=False,
        )
    return traj, res, summary
