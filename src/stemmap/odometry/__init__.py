"""Odometry front ends: visual odometry from stereo / RGB-D frames (:mod:`.visual`)."""

from stemmap.odometry.visual import (
    StereoCalibration,
    VisualFrame,
    VisualOdometry,
    VisualOdometryConfig,
    VisualOdometryResult,
    VoStatus,
    planar_from_camera,
    run_visual_odometry,
)

__all__ = [
    "StereoCalibration",
    "VisualFrame",
    "VisualOdometry",
    "VisualOdometryConfig",
    "VisualOdometryResult",
    "VoStatus",
    "planar_from_camera",
    "run_visual_odometry",
]
