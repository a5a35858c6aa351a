"""IMU + wheel-speed logs: the :class:`InertialLog` type, its CSV form, and bag conversion.

CSV layout (one header line, ``#`` comment lines allowed, an empty field = no value)::

    time_s,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,wheel_speed
    0.00,0.0012,-0.0004,0.0521,0.31,0.02,9.81,
    0.02,0.0010,-0.0003,0.0519,0.30,0.03,9.80,4.02

* ``time_s`` (s, strictly increasing) and ``gyro_z`` (rad/s, counter-clockwise about the
  vehicle's up axis) are required on IMU rows;
* ``gyro_x``, ``gyro_y`` (rad/s) and ``accel_x/y/z`` (m/s², specific force in the body frame,
  x forward, y left, z up: a level, resting IMU reads ``(0, 0, +g)``) are optional;
* ``wheel_speed`` (m/s, forward) is optional; a row may carry only a wheel speed (empty or
  ``nan`` gyro fields) when the encoders run at another rate than the IMU. The writer writes
  ``nan`` for a missing value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import InputError
from stemmap.io._util import PathLike, existing_file, fmt_row, parse_numeric_csv, read_text
from stemmap.io.atomic import atomic_write
from stemmap.types import FloatArray

__all__ = [
    "IMU_CSV_COLUMNS",
    "InertialLog",
    "inertial_from_bag",
    "read_imu_csv",
    "write_imu_csv",
]

IMU_CSV_COLUMNS = (
    "time_s",
    "gyro_x",
    "gyro_y",
    "gyro_z",
    "accel_x",
    "accel_y",
    "accel_z",
    "wheel_speed",
)


@dataclass(frozen=True, eq=False)
class InertialLog:
    """Gyro, accelerometer and wheel-speed samples on one time base.

    Parameters
    ----------
    times : ndarray (N,), s, strictly increasing
    gyro : ndarray (N, 3), rad/s, body frame (x forward, y left, z up); NaN rows = no IMU sample
    accel : ndarray (N, 3), m/s², specific force; NaN = not recorded
    wheel_speed : ndarray (N,), m/s; NaN = no wheel sample at this time
    """

    times: FloatArray
    gyro: FloatArray
    accel: FloatArray
    wheel_speed: FloatArray

    def __post_init__(self) -> None:
        t = np.asarray(self.times, dtype=np.float64).reshape(-1)
        n = t.shape[0]
        g = np.asarray(self.gyro, dtype=np.float64).reshape(-1, 3)
        a = np.asarray(self.accel, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(self.wheel_speed, dtype=np.float64).reshape(-1)
        if not (g.shape[0] == a.shape[0] == w.shape[0] == n):
            raise InputError(
                f"InertialLog needs one gyro, accel and wheel_speed row per time: got {n} "
                f"times, {g.shape[0]} gyro, {a.shape[0]} accel, {w.shape[0]} wheel rows."
            )
        if not np.all(np.isfinite(t)) or (n > 1 and np.any(np.diff(t) <= 0)):
            raise InputError("InertialLog times must be finite and strictly increasing.")
        for name, arr in (("times", t), ("gyro", g), ("accel", a), ("wheel_speed", w)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def has_gyro(self) -> bool:
        return bool(np.any(np.isfinite(self.gyro[:, 2])))

    @property
    def has_wheel(self) -> bool:
        return bool(np.any(np.isfinite(self.wheel_speed)))

    @classmethod
    def merge(
        cls,
        imu_times: ArrayLike,
        gyro: ArrayLike,
        accel: ArrayLike | None = None,
        wheel_times: ArrayLike | None = None,
        wheel_speed: ArrayLike | None = None,
    ) -> InertialLog:
        """Merge an IMU stream and a wheel-speed stream with their own clocks into one log
        (a wheel sample at the time of an IMU sample shares its row)."""
        ti = np.asarray(imu_times, dtype=np.float64).reshape(-1)
        g = np.asarray(gyro, dtype=np.float64).reshape(-1, 3)
        a = (
            np.full((ti.shape[0], 3), np.nan)
            if accel is None
            else np.asarray(accel, dtype=np.float64).reshape(-1, 3)
        )
        tw = np.zeros(0) if wheel_times is None else np.asarray(wheel_times, np.float64).ravel()
        ws = np.zeros(0) if wheel_speed is None else np.asarray(wheel_speed, np.float64).ravel()
        if tw.shape != ws.shape:
            raise InputError(f"{tw.shape[0]} wheel times but {ws.shape[0]} wheel speeds.")
        t = np.union1d(ti, tw)
        gi = np.full((t.shape[0], 3), np.nan)
        ai = np.full((t.shape[0], 3), np.nan)
        wi = np.full(t.shape[0], np.nan)
        ki = np.searchsorted(t, ti)
        gi[ki] = g
        ai[ki] = a
        wi[np.searchsorted(t, tw)] = ws
        return cls(t, gi, ai, wi)


def write_imu_csv(path: PathLike, log: InertialLog) -> None:
    """Write an :class:`InertialLog` as the module's CSV layout, atomically."""
    with atomic_write(path) as fh:
        fh.write(",".join(IMU_CSV_COLUMNS) + "\n")
        data = np.column_stack((log.times, log.gyro, log.accel, log.wheel_speed))
        for row in data:
            fh.write(fmt_row(row) + "\n")


def read_imu_csv(path: PathLike) -> InertialLog:
    """Read the module's CSV layout.

    Raises
    ------
    InputError
        Missing file or column, a malformed row, non-increasing times, or no row with either a
        ``gyro_z`` or a ``wheel_speed`` value.
    """
    p = existing_file(path, "IMU CSV")
    table = parse_numeric_csv(
        p, read_text(p, "IMU CSV"), ("time_s",), IMU_CSV_COLUMNS[1:], "IMU CSV"
    )
    cols = table.columns
    n = cols["time_s"].shape[0]
    if "gyro_z" not in cols and "wheel_speed" not in cols:
        raise InputError(
            f"IMU CSV file {str(p)!r} has neither a gyro_z nor a wheel_speed column; the header "
            f"must name at least one of them ({', '.join(IMU_CSV_COLUMNS)})."
        )

    def col(name: str) -> FloatArray:
        return cols.get(name, np.full(n, np.nan))

    t = cols["time_s"]
    if not np.all(np.isfinite(t)):
        k = int(np.argmax(~np.isfinite(t)))
        raise InputError(f"IMU CSV file {str(p)!r} line {table.lines[k]}: time_s is not finite.")
    if n > 1 and np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0)) + 1
        raise InputError(
            f"IMU CSV file {str(p)!r} line {table.lines[k]}: time_s {t[k]} does not increase "
            f"(previous row {t[k - 1]}); sort the file by time and drop duplicate rows."
        )
    from stemmap.io.conventions import check_times

    check_times(t, f"IMU CSV file {str(p)!r}", "time_s")
    log = InertialLog(
        t,
        np.column_stack((col("gyro_x"), col("gyro_y"), col("gyro_z"))),
        np.column_stack((col("accel_x"), col("accel_y"), col("accel_z"))),
        col("wheel_speed"),
    )
    if not (log.has_gyro or log.has_wheel):
        raise InputError(f"IMU CSV file {str(p)!r} has no gyro_z or wheel_speed value.")
    _check_gyro_turns(log, f"IMU CSV file {str(p)!r}")
    return log


def _check_gyro_turns(log: InertialLog, source: str) -> None:
    """The odometry's unit checks on the gyro's z rate (:func:`stemmap.io.conventions.
    check_turns`: half a turn between samples -- relative times in ms --, or over 1 g
    sideways at the wheel speed, held from its last sample: deg/s)."""
    from stemmap.io.conventions import check_turns

    g = np.flatnonzero(np.isfinite(log.gyro[:, 2]))
    if g.size < 2:
        return
    tg = log.times[g]
    w = np.flatnonzero(np.isfinite(log.wheel_speed))
    speed = np.zeros(g.size)
    if w.size:  # the wheel speed of the last sample at or before each gyro sample
        k = np.searchsorted(log.times[w], tg, side="right") - 1
        speed = np.where(k >= 0, log.wheel_speed[w][np.maximum(k, 0)], 0.0)
    check_turns(tg, speed, log.gyro[g, 2], source)


def inertial_from_bag(
    path: PathLike, imu_topic: str | None = None, odom_topic: str | None = None
) -> InertialLog:
    """The IMU (``sensor_msgs/Imu``) and, when ``odom_topic`` is given, the wheel odometry's
    forward speed (``nav_msgs/Odometry`` twist) of a ROS bag, merged on one time base."""
    from stemmap.io.rosbag import read_imu, read_odometry

    imu = read_imu(path, imu_topic)
    wt = ws = None
    if odom_topic is not None:
        odo = read_odometry(path, odom_topic)
        wt, ws = odo.times, odo.twists[:, 0]
        keep = np.concatenate(([True], np.diff(wt) > 0))
        wt, ws = wt[keep], ws[keep]
    keep_i = np.concatenate(([True], np.diff(imu.times) > 0))
    return InertialLog.merge(
        imu.times[keep_i],
        imu.angular_velocity[keep_i],
        imu.linear_acceleration[keep_i],
        wt,
        ws,
    )
