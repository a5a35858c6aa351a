"""Odometry front ends feeding slam/: lidar scan matching (:mod:`.lidar`), wheel + IMU sources
(:mod:`.inertial`), visual odometry from stereo / RGB-D frames (:mod:`.visual`), and their
loosely coupled EKF fusion (:mod:`.fusion`) and fusion by relative motion (:mod:`.increments`);
their drift estimate as a random walk in distance (:mod:`.drift`).

Submodules are imported on first use of a name (``from stemmap.odometry import fuse_sources``
loads only :mod:`.fusion`), so a front end's heavy dependency (KISS-ICP, OpenCV) is paid only
by the code that uses it. See docs/algorithms/odometry.md and visual-odometry.md.
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> submodule defining it (each front end adds its own lines)
_LAZY: dict[str, str] = {
    "FusedOdometry": "fusion",
    "OdometrySource": "fusion",
    "PoseSource": "fusion",
    "dead_reckon_source": "fusion",
    "fuse_odometry": "fusion",
    "fuse_sources": "fusion",
    "velocities_from_poses": "fusion",
    "distance_random_walk_variance": "drift",
    "IncrementSource": "increments",
    "fuse_increments": "increments",
    "LidarOdometry": "lidar",
    "LidarOdometryConfig": "lidar",
    "LidarOdometryResult": "lidar",
    "lidar_odometry": "lidar",
    "fuse_front_ends": "inertial",
    "lidar_inertial_odometry": "inertial",
    "gyro_source": "inertial",
    "motion_prior": "inertial",
    "wheel_source": "inertial",
    "StereoCalibration": "visual",
    "VISUAL_DRIFT_XY_PER_SQRT_M": "visual",
    "VISUAL_STEP_RATE_HZ": "visual",
    "VISUAL_STEP_SIGMA": "visual",
    "VisualFrame": "visual",
    "VisualOdometry": "visual",
    "VisualOdometryConfig": "visual",
    "VisualOdometryResult": "visual",
    "VoStatus": "visual",
    "planar_from_camera": "visual",
    "run_visual_odometry": "visual",
    "visual_velocity_sigma": "visual",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'stemmap.odometry' has no attribute {name!r}")
    return getattr(importlib.import_module(f"stemmap.odometry.{mod}"), name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
