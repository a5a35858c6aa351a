"""Helpers for tests/cloud and benchmarks/stems_sensor_positions.py: a simulated mobile scan
written the way a mobile-mapping system delivers it -- a LAS file whose points carry
``gps_time``, and the machine's trajectory as a separate file."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np

from stemmap.io.trajectory import write_trajectory_csv, write_trajectory_tum
from stemmap.sim.lidar import MobileScan
from stemmap.types import Trajectory

T0 = 1_000_000.0  # s, time of the first revolution
PERIOD = 0.1  # s, one revolution (10 Hz)


def write_las(path: Path, xyz: np.ndarray, gps_time: np.ndarray | None = None) -> None:
    """LAS 1.2, 1 mm scale; point format 1 (with gps_time) when times are given, else 0."""
    header = laspy.LasHeader(point_format=0 if gps_time is None else 1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.floor(xyz.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if gps_time is not None:
        las.gps_time = gps_time
    las.write(path)


def write_ply(path: Path, xyz: np.ndarray, time: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with double x, y, z (and a double ``time`` property)."""
    names = ["x", "y", "z"] + ([] if time is None else ["time"])
    rec = np.empty(len(xyz), dtype=[(n, "<f8") for n in names])
    rec["x"], rec["y"], rec["z"] = xyz.T
    if time is not None:
        rec["time"] = time
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n"
        + "".join(f"property double {n}\n" for n in names)
        + "end_header\n"
    )
    path.write_bytes(head.encode() + rec.tobytes())


def point_times(mob: MobileScan) -> np.ndarray:
    """Each point's time: the time of its revolution (the simulator scans each revolution
    from one pose, so every point of it has that pose)."""
    return T0 + PERIOD * np.asarray(mob.cloud.fields["frame_index"], dtype=np.float64)


def vehicle_trajectory(
    mob: MobileScan, lever: tuple[float, float] = (0.0, 0.0), every: int = 2
) -> Trajectory:
    """The machine's path: the pose of every ``every``-th revolution (and the last), of a
    reference point ``lever`` (forward, left) behind the scanner -- so that the reader must
    both interpolate between poses and apply the mounting offset."""
    p = mob.poses
    keep = np.unique(np.append(np.arange(0, len(p), every), len(p) - 1))
    yaw = p[keep, 3]
    c, s = np.cos(yaw), np.sin(yaw)
    a, b = lever
    x = p[keep, 0] - (a * c - b * s)
    y = p[keep, 1] - (a * s + b * c)
    return Trajectory(T0 + PERIOD * keep, np.column_stack((x, y, yaw)))


def write_trajectory(path: Path, traj: Trajectory) -> None:
    """stemmap CSV for ``.csv``, TUM otherwise."""
    if path.suffix == ".csv":
        write_trajectory_csv(path, traj)
    else:
        write_trajectory_tum(path, traj)
