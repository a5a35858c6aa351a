"""Trajectory files: stemmap CSV (``time,x,y,theta``) and the TUM RGB-D format.

The CSV optionally carries each pose's 3x3 covariance as six columns
(:data:`TRAJECTORY_COV_COLUMNS`; docs/outputs.md "trajectory.csv"): written when the back-end
gives one (``SlamResult.pose_covs``), an empty-valued ``nan`` on rows without one, absent
altogether otherwise; :func:`read_trajectory_csv_with_covariance` reads them back.

Both are written atomically. The TUM format (Sturm et al. 2012, used by evo and most SLAM
benchmarks) stores one pose per line as ``t x y z qx qy qz qw``; stemmap's planar poses are
written with ``z = 0`` and a yaw-only quaternion, and read back by taking the yaw of the
quaternion (roll and pitch are dropped, with a warning when they exceed 5 degrees).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from stemmap.errors import InputError
from stemmap.io._util import (
    PathLike,
    existing_file,
    fmt_row,
    parse_numeric_csv,
    read_text,
    require_finite,
)
from stemmap.io.atomic import atomic_write
from stemmap.types import FloatArray, Trajectory, wrap_angle

__all__ = [
    "TRAJECTORY_COV_COLUMNS",
    "TRAJECTORY_CSV_COLUMNS",
    "read_trajectory_csv",
    "read_trajectory_csv_with_covariance",
    "read_trajectory_tum",
    "write_trajectory_csv",
    "write_trajectory_tum",
    "yaw_from_quaternion",
    "yaw_to_quaternion",
]

log = logging.getLogger(__name__)

#: Columns of the stemmap trajectory CSV, in order.
TRAJECTORY_CSV_COLUMNS = ("time_s", "x", "y", "theta")

#: Optional covariance columns of the trajectory CSV, in order: the (x, y, theta) covariance's
#: entries xx, xy, yy (m²), x-theta, y-theta (m·rad), theta-theta (rad²).
TRAJECTORY_COV_COLUMNS = (
    "cov_xx_m2",
    "cov_xy_m2",
    "cov_yy_m2",
    "cov_xt_m_rad",
    "cov_yt_m_rad",
    "cov_tt_rad2",
)
# (row, col) of each covariance column in the 3x3 matrix
_COV_IJ = ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2))

_TILT_WARN_RAD = math.radians(5.0)


def wrap_if_needed(angle: FloatArray) -> FloatArray:
    """Wrap to (-pi, pi] only the angles outside it, leaving the others bit-identical."""
    a = np.asarray(angle, dtype=np.float64)
    inside = (a > -math.pi) & (a <= math.pi)
    return np.where(inside, a, np.asarray(wrap_angle(a)))


def yaw_to_quaternion(yaw: FloatArray) -> FloatArray:
    """Quaternions ``(qx, qy, qz, qw)`` of rotations by ``yaw`` (rad) about +z, shape (N, 4)."""
    h = 0.5 * np.asarray(yaw, dtype=np.float64).reshape(-1)
    z = np.zeros_like(h)
    return np.column_stack((z, z, np.sin(h), np.cos(h)))


def yaw_from_quaternion(q: FloatArray) -> FloatArray:
    """Yaw (rad, in (-pi, pi]) of quaternions ``(qx, qy, qz, qw)``, shape (N, 4) -> (N,).

    Uses the z-y-x (yaw-pitch-roll) Euler convention of ROS ``tf``: yaw =
    atan2(2 (w z + x y), 1 - 2 (y^2 + z^2)). Quaternions need not be normalised.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / n
    x, y, z, w = q.T
    return wrap_if_needed(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def write_trajectory_csv(
    path: PathLike, trajectory: Trajectory, *, covs: FloatArray | None = None
) -> None:
    """Write ``time_s,x,y,theta`` rows (s, m, m, rad), atomically; with ``covs`` also the
    pose covariance columns :data:`TRAJECTORY_COV_COLUMNS`.

    Parameters
    ----------
    path : str or PathLike
        Output file; parent folders are created.
    trajectory : Trajectory
        Poses in any frame (the frame name is not stored; keep it in the file name).
    covs : ndarray (N, 3, 3), optional
        Covariance of each pose (x, y, theta); rows that have none are NaN (written ``nan``).
        Columns are written only when at least one row has a finite covariance.

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib
    >>> from stemmap.types import Trajectory
    >>> tr = Trajectory(np.array([0.0, 0.1]), np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.05]]))
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "path.csv"
    >>> write_trajectory_csv(p, tr)
    >>> p.read_text().splitlines()[1]
    '0.0,0.0,0.0,0.0'
    """
    cols = list(TRAJECTORY_CSV_COLUMNS)
    table = np.column_stack((trajectory.times, trajectory.poses))
    if covs is not None:
        c = np.asarray(covs, dtype=np.float64)
        if c.shape != (len(trajectory), 3, 3):
            raise InputError(
                f"pose covariances must have shape ({len(trajectory)}, 3, 3), got {c.shape}."
            )
        entries = np.column_stack([c[:, i, j] for i, j in _COV_IJ])
        if np.isfinite(entries).any():
            cols += TRAJECTORY_COV_COLUMNS
            table = np.column_stack((table, entries))
    with atomic_write(path) as fh:
        fh.write(",".join(cols) + "\n")
        for row in table:
            fh.write(fmt_row(row) + "\n")


def read_trajectory_csv(path: PathLike, *, frame: str = "map") -> Trajectory:
    """Read a ``time_s,x,y,theta`` CSV (extra columns are ignored; ``#`` lines are comments;
    a bare ``time`` header, as stemmap < 0.2 wrote, is accepted).

    Parameters
    ----------
    path : str or PathLike
    frame : str
        Frame name given to the returned trajectory.

    Returns
    -------
    Trajectory
        Headings wrapped to (-pi, pi].

    Raises
    ------
    InputError
        If the file is missing or empty, lacks a column, has a malformed row, a non-finite
        value, or times that do not strictly increase.
    """
    return read_trajectory_csv_with_covariance(path, frame=frame)[0]


def read_trajectory_csv_with_covariance(
    path: PathLike, *, frame: str = "map"
) -> tuple[Trajectory, FloatArray | None]:
    """:func:`read_trajectory_csv` plus the pose covariances (N, 3, 3) of the
    :data:`TRAJECTORY_COV_COLUMNS` (NaN on rows without one), or None when the file has none
    of those columns (all six or none: a partial set is an InputError).
    """
    p = existing_file(path, "trajectory CSV")
    table = parse_numeric_csv(
        p,
        read_text(p, "trajectory CSV"),
        TRAJECTORY_CSV_COLUMNS,
        TRAJECTORY_COV_COLUMNS,
        "trajectory CSV",
    )
    for c in TRAJECTORY_CSV_COLUMNS:
        require_finite(p, "trajectory CSV", table, c)
    cols = table.columns
    poses = np.column_stack((cols["x"], cols["y"], wrap_if_needed(cols["theta"])))
    traj = _trajectory(p, cols["time_s"], poses, frame, table.lines)
    have = [c for c in TRAJECTORY_COV_COLUMNS if c in cols]
    if not have:
        return traj, None
    if len(have) != len(TRAJECTORY_COV_COLUMNS):
        missing = [c for c in TRAJECTORY_COV_COLUMNS if c not in cols]
        raise InputError(
            f"trajectory CSV file {str(p)!r} has covariance column(s) {', '.join(have)} but "
            f"lacks {', '.join(missing)}; write all six or none."
        )
    covs = np.empty((len(traj), 3, 3))
    for name, (i, j) in zip(TRAJECTORY_COV_COLUMNS, _COV_IJ, strict=True):
        covs[:, i, j] = covs[:, j, i] = cols[name]
    return traj, covs


def _trajectory(
    path: PathLike, times: FloatArray, poses: FloatArray, frame: str, lines: np.ndarray
) -> Trajectory:
    d = np.diff(times)
    if d.size and not np.all(d > 0):
        k = int(np.argmax(~(d > 0)))
        raise InputError(
            f"trajectory file {str(path)!r} line {lines[k + 1]}: time {times[k + 1]} does not "
            f"increase after {times[k]} (line {lines[k]}); times must strictly increase."
        )
    return Trajectory(times, poses.reshape(-1, 3), frame=frame)


def write_trajectory_tum(path: PathLike, trajectory: Trajectory, *, z: float = 0.0) -> None:
    """Write the TUM format ``t x y z qx qy qz qw`` (space separated, ``#`` header), atomically.

    Planar poses become ``z`` (default 0 m) and a yaw-only quaternion (rotation about +z).
    """
    q = yaw_to_quaternion(trajectory.poses[:, 2])
    with atomic_write(path) as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, (x, y, _), qi in zip(trajectory.times, trajectory.poses, q, strict=True):
            fh.write(fmt_row((t, x, y, z, *qi)).replace(",", " ") + "\n")


def read_trajectory_tum(path: PathLike, *, frame: str = "map") -> Trajectory:
    """Read a TUM trajectory ``t x y z qx qy qz qw`` into planar poses (x, y, yaw).

    Fields may be separated by spaces, tabs or commas; ``#`` lines are comments. ``z``, roll and
    pitch are dropped; a warning is logged when any pose is tilted more than 5 degrees (the
    file is then not a planar trajectory and the projection loses information).

    Raises
    ------
    InputError
        Missing/empty file, a line without 8 numbers, a non-finite value, a zero quaternion, or
        times that do not strictly increase.
    """
    p = existing_file(path, "TUM trajectory")
    rows: list[list[float]] = []
    lines: list[int] = []
    for n, ln in enumerate(read_text(p, "TUM trajectory").splitlines(), start=1):
        s = ln.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(
                f"TUM trajectory {str(p)!r} line {n} has {len(parts)} fields; "
                "expected 8: t x y z qx qy qz qw."
            )
        try:
            vals = [float(v) for v in parts]
        except ValueError as exc:
            raise InputError(f"TUM trajectory {str(p)!r} line {n}: {exc}.") from None
        if not all(math.isfinite(v) for v in vals):
            raise InputError(f"TUM trajectory {str(p)!r} line {n} contains NaN or inf: {s!r}.")
        rows.append(vals)
        lines.append(n)
    if not rows:
        raise InputError(f"TUM trajectory {str(p)!r} holds no poses.")
    a = np.array(rows)
    qn = np.linalg.norm(a[:, 4:8], axis=1)
    if np.any(qn < 1e-9):
        k = int(np.argmax(qn < 1e-9))
        raise InputError(f"TUM trajectory {str(p)!r} line {lines[k]} has a zero quaternion.")
    q = a[:, 4:8] / qn[:, None]
    # tilt = angle between the rotated z axis and the world z axis
    cos_tilt = 1.0 - 2.0 * (q[:, 0] ** 2 + q[:, 1] ** 2)
    tilt = np.arccos(np.clip(cos_tilt, -1.0, 1.0))
    if np.any(tilt > _TILT_WARN_RAD):
        log.warning(
            "TUM trajectory %s: poses tilt up to %.1f deg; roll and pitch are dropped.",
            p,
            math.degrees(float(tilt.max())),
        )
    poses = np.column_stack((a[:, 1], a[:, 2], yaw_from_quaternion(q)))
    return _trajectory(p, a[:, 0], poses, frame, np.array(lines))
