"""Log inputs of ``stemmap map``: scans (NPZ / CSV, e.g. from ``stemmap sim scans``) or a
detections CSV (``stemmap detect``), each with a wheel-odometry CSV, and ROS bags (LaserScan +
Odometry); or any of them with a trajectory from ``--motion lidar|visual|fused``."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import InputError
from stemmap.io.clouds import CLOUD_EXTENSIONS

__all__ = [
    "bag_problem",
    "file_problem",
    "is_detections_csv",
    "odometry_path",
    "read_odometry_csv",
]

#: Columns of the odometry CSV (``stemmap sim scans`` and ``stemmap sim munjer`` write them;
#: an older header's ``time`` is read as ``time_s``).
ODOMETRY_CSV_COLUMNS = ("time_s", "speed", "yaw_rate")


#: Point-cloud file types that are nothing else (.txt and .csv are also scans or detections).
_CLOUD_ONLY = frozenset(CLOUD_EXTENSIONS) - {".txt", ".csv"}

#: Bounds of a wheel-odometry row (the user walk, Dec 4: one row of 1e5 m/s ended every
#: back-end in a traceback -- GTSAM's indeterminant system, a k-d tree overflow, a NaN
#: matrix); far beyond any vehicle, so they refuse corrupt rows and unit errors only.
MAX_ODOMETRY_SPEED = 1000.0
MAX_YAW_RATE = 100.0
#: Largest 99th percentile of |yaw_rate| (rad/s) an odometry in rad/s can have: half a turn
#: per second, for 1 % of the drive. A yaw rate in deg/s turning at 10-30 deg/s reads 10-30
#: "rad/s"; a slow turn in deg/s (under 3.1 deg/s) is caught only by the lateral
#: acceleration it implies (:func:`stemmap.io.conventions.check_turns`, docs/reliability.md).
MAX_SUSTAINED_YAW_RATE = math.pi


def read_odometry_csv(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``time_s,speed,yaw_rate`` (s, m/s, rad/s; each row held until the next) -> arrays.

    Raises
    ------
    InputError
        Missing file or column, non-finite values, fewer than 2 rows, times not increasing.
    """
    from stemmap.io._util import existing_file, parse_numeric_csv, read_text, require_finite

    what = "odometry CSV"
    p = existing_file(path, what)
    table = parse_numeric_csv(p, read_text(p, what), ODOMETRY_CSV_COLUMNS, (), what)
    for c in ODOMETRY_CSV_COLUMNS:
        require_finite(p, what, table, c)
    t = table.columns["time_s"]
    if t.shape[0] < 2:
        raise InputError(f"{what} {str(p)!r} has {t.shape[0]} rows; dead reckoning needs >= 2.")
    if np.any(np.diff(t) < 0):
        k = int(np.argmax(np.diff(t) < 0))
        raise InputError(
            f"{what} {str(p)!r} line {table.lines[k + 1]}: time {t[k + 1]} goes backwards."
        )
    for c, limit, unit in (
        ("speed", MAX_ODOMETRY_SPEED, "m/s"),
        ("yaw_rate", MAX_YAW_RATE, "rad/s"),
    ):
        v = table.columns[c]
        if np.any(np.abs(v) > limit):
            k = int(np.argmax(np.abs(v) > limit))
            raise InputError(
                f"{what} {str(p)!r} line {table.lines[k]}: {c} {v[k]:g} {unit} is beyond "
                f"+-{limit:g} {unit}, no vehicle's: a corrupt row or another unit?"
            )
    from stemmap.io.conventions import check_times, check_turns

    check_times(t, f"{what} {str(p)!r}", "time_s")
    w = np.abs(table.columns["yaw_rate"])
    if float(np.percentile(w, 99)) > MAX_SUSTAINED_YAW_RATE:
        raise InputError(
            f"{what} {str(p)!r}: 1 % of the yaw rates exceed {np.percentile(w, 99):.3g} rad/s "
            f"(over half a turn per second, {MAX_SUSTAINED_YAW_RATE:.3g} rad/s): is yaw_rate in "
            "degrees per second? stemmap reads rad/s: multiply it by pi/180."
        )
    keep = np.concatenate(([True], np.diff(t) > 0))
    t, speed, yaw = t[keep], table.columns["speed"][keep], table.columns["yaw_rate"][keep]
    check_turns(t, speed, yaw, f"{what} {str(p)!r}")  # ms times, slow turns in deg/s
    return t, speed, yaw


def is_detections_csv(path: Path) -> bool:
    """A ``stemmap detect`` CSV (header with ``scan_index``) rather than a scans CSV."""
    if path.suffix.lower() not in (".csv", ".txt") or not path.is_file():
        return False
    with path.open(encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.strip() and not line.lstrip().startswith("#"):
                return "scan_index" in [h.strip() for h in line.split(",")]
    return False


def odometry_path(source: Path, odometry: Path | None) -> Path:
    """``--odometry`` or the ``<stem>_odometry.csv`` that ``stemmap sim scans`` writes beside
    ``<stem>.npz``; InputError naming both options when neither exists."""
    if not source.exists():
        raise InputError(f"input {str(source)!r} does not exist.")
    if source.suffix.lower() in _CLOUD_ONLY:
        raise InputError(
            f"{source} is a point cloud; `stemmap map` maps 2D scans (.npz, .csv), a detections "
            "CSV, a ROS bag or a frames bundle (.npz). The stems of a point cloud: `stemmap "
            f"stems {source.name}`."
        )
    if odometry is not None:
        return odometry
    guess = source.with_name(f"{source.stem}_odometry.csv")
    if guess.is_file():
        return guess
    raise InputError(
        f"{source} has no odometry: pass --odometry FILE (CSV time_s,speed,yaw_rate in s, m/s, "
        f"rad/s), or put it beside the input as {guess.name}."
    )


def file_problem(
    source: Path,
    odometry: Path | None,
    sensor_offset: tuple[float, float],
    *,
    motion: Any = None,
    motion_sigma: tuple[float, float] | None = None,
    before_compute: Callable[[], None] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """A :class:`~stemmap.slam.base.SlamProblem` from scans or detections plus a motion source.

    Scans are run through the default :class:`~stemmap.scan.detect.ScanTrunkDetector`. The map
    frame starts at the vehicle pose (0, 0, 0) of the first frame. Motion: the wheel odometry
    CSV ``odometry`` (default ``<stem>_odometry.csv``), or ``motion``, a vehicle trajectory
    (``stemmap map --motion lidar|visual|fused``) differenced into body-frame velocities. The
    motion noise is ``motion_sigma`` (speed m/s, yaw rate rad/s, 1-s averages), default the
    :class:`~stemmap.slam.motion.UnicycleModel` default. ``before_compute`` is called once
    every input is read and checked, before the first detection (the first-run compile
    notice).
    """
    from dataclasses import replace

    from stemmap.io.maps import read_observations_csv
    from stemmap.io.scans import read_scans
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.slam.base import Controls, SlamProblem, TreeFrames
    from stemmap.slam.motion import UnicycleModel

    if motion is None:
        odo_file: Path | str = odometry_path(source, odometry)
        t_odo, speed, yaw_rate = read_odometry_csv(Path(odo_file))
        model = (
            UnicycleModel()
            if motion_sigma is None
            else UnicycleModel(sigma_speed=motion_sigma[0], sigma_steer=motion_sigma[1])
        )
        controls = Controls(t_odo, speed, yaw_rate, "unicycle")
    else:
        from stemmap.slam.munjer import controls_from_trajectory

        sig = motion_sigma or (UnicycleModel().sigma_speed, UnicycleModel().sigma_steer)
        controls, model = controls_from_trajectory(
            motion, sigma_speed=sig[0], sigma_yaw_rate=sig[1]
        )
        odo_file = "the motion source"
        t_odo = np.asarray(motion.times)
    max_range = math.inf
    batch = None
    if is_detections_csv(source):
        obs = read_observations_csv(source)
        if len(obs) == 0:
            raise InputError(f"detections CSV {source} has no rows.")
        scans, first = np.unique(obs.index, return_index=True)
        times = obs.times[first]
        if np.any(np.diff(times) < 0):
            raise InputError(f"detections CSV {source}: scan times must increase with scan_index.")
        obs = replace(obs, index=np.searchsorted(scans, obs.index))
        kind = "detections"
    else:
        batch = read_scans(source)
        times = batch.times
        _check_time_bases(source, "scans", times, odo_file, t_odo)
        if before_compute is not None:
            before_compute()
        obs = ScanTrunkDetector().detect_batch(batch)
        max_range = float(batch.range_max)
        kind = "scans"
    frames = TreeFrames.from_observations(obs, times)
    _check_time_bases(source, kind, times, odo_file, t_odo)
    if before_compute is not None:
        before_compute()
    problem = SlamProblem(
        controls,
        frames,
        model,
        sensor_offset=sensor_offset,
        initial_pose=(0.0, 0.0, 0.0),
        name=str(source),
        max_range=max_range,
    )
    ctx: dict[str, Any] = {"kind": kind, "odometry": str(odo_file)}
    if batch is not None:
        ctx["scans"] = batch  # raw scans, one per frame: ray-cast false-tree removal
    return problem, ctx


def _check_time_bases(
    source: Path, kind: str, times: Any, odo_file: Path | str, t_odo: Any
) -> None:
    if times[0] < t_odo[0] or times[-1] > t_odo[-1] + 1.0:
        raise InputError(
            f"the {kind} of {source} span {times[0]:.3f}-{times[-1]:.3f} s but the odometry "
            f"{odo_file} spans {t_odo[0]:.3f}-{t_odo[-1]:.3f} s: the time bases differ."
        )


def bag_problem(
    path: Path,
    sensor_offset: tuple[float, float],
    *,
    motion: Any = None,
    motion_sigma: tuple[float, float] | None = None,
    before_compute: Callable[[], None] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """A problem from a bag's LaserScan topic; motion from its Odometry topic, or ``motion``
    (a vehicle trajectory from ``--motion lidar|visual|fused``). ``before_compute`` is called
    once both are read, before the first detection."""
    from stemmap.io.rosbag import iter_laser_scans, read_odometry
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.slam.base import Controls, SlamProblem, TreeFrames
    from stemmap.slam.motion import UnicycleModel
    from stemmap.types import ScanBatch

    scans = list(iter_laser_scans(path))
    if not scans:
        raise InputError(f"bag {path} has no usable LaserScan messages.")
    batch = ScanBatch.from_scans(scans)
    sig = motion_sigma or (UnicycleModel().sigma_speed, UnicycleModel().sigma_steer)
    model = UnicycleModel(sigma_speed=sig[0], sigma_steer=sig[1])
    ctx: dict[str, Any] = {"kind": "bag", "scans": batch}
    if motion is None:
        try:
            odo = read_odometry(path)
        except InputError as exc:
            raise InputError(
                f"{exc} Without wheel odometry, take the motion from the scans: --motion lidar."
            ) from exc
        if len(odo) < 2:
            raise InputError(
                f"bag {path} has fewer than 2 Odometry messages; cannot dead-reckon (or use "
                "--motion lidar)."
            )
        keep = np.concatenate(([True], np.diff(odo.times) > 0))
        controls = Controls(odo.times[keep], odo.twists[keep, 0], odo.twists[keep, 2], "unicycle")
        p0 = odo.trajectory().interpolate([float(batch.times[0])])[0]
        ctx["odometry"] = odo
    else:
        from stemmap.slam.munjer import controls_from_trajectory

        controls, model = controls_from_trajectory(
            motion, sigma_speed=sig[0], sigma_yaw_rate=sig[1]
        )
        p0 = motion.interpolate([float(batch.times[0])])[0]
    if before_compute is not None:
        before_compute()
    obs = ScanTrunkDetector().detect_batch(batch)
    frames = TreeFrames.from_observations(obs, batch.times)
    problem = SlamProblem(
        controls,
        frames,
        model,
        sensor_offset=sensor_offset,
        initial_pose=(float(p0[0]), float(p0[1]), float(p0[2])),
        name=str(path),
        max_range=float(batch.range_max),
    )
    return problem, ctx
