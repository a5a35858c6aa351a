"""2D logs whose times count milliseconds from the log's start, or whose yaw rates are in
deg/s with slow turns, are refused or warned about (`io.conventions.check_turns`,
`check_scan_period`). Before (main at 88c3073) only absolute Unix times in ms/us/ns and yaw
rates with a 99th percentile above pi "rad/s" were caught: Victoria Park's own raw dead
reckoning (aa3_dr.mat, time in milliseconds from the log's start) was read as seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stemmap.cli._map_inputs import read_odometry_csv
from stemmap.errors import InputError
from stemmap.io.conventions import (
    check_scan_period,
    check_turns,
)

#: Victoria Park's wheelbase (m), as in stemmap.datasets.victoria_park's Ackermann model
_WHEELBASE = 2.83


def _vp_odometry(datasets_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time in the raw file's milliseconds, speed m/s, yaw rate rad/s) of Victoria Park's
    raw dead reckoning (the yaw rate from the steering angle, kinematic bicycle model)."""
    from scipy.io import loadmat

    d = loadmat(str(datasets_dir / "victoria_park" / "aa3_dr.mat"))
    t = d["time"].ravel().astype(np.float64)
    v = d["speed"].ravel()
    w = v * np.tan(d["steering"].ravel()) / _WHEELBASE
    return t, v, w


def _write(path: Path, t: np.ndarray, v: np.ndarray, w: np.ndarray) -> Path:
    np.savetxt(path, np.column_stack((t, v, w)), delimiter=",", header="time_s,speed,yaw_rate",
               comments="", fmt="%.9g")  # fmt: skip
    return path


def test_victoria_park_raw_milliseconds_refused(datasets_dir: Path, tmp_path: Path) -> None:
    t, v, w = _vp_odometry(datasets_dir)
    assert t[0] < 1e5 and np.median(np.diff(t)) == 25.0  # relative ms: main's checks pass
    with pytest.raises(InputError, match="milliseconds"):
        read_odometry_csv(_write(tmp_path / "ms.csv", t, v, w))
    got = read_odometry_csv(_write(tmp_path / "s.csv", t / 1e3, v, w))  # seconds: read
    assert got[0].size == t.size


def test_slow_turns_in_deg_per_s_at_speed_refused() -> None:
    """A drive at 4 m/s turning at up to 3 deg/s (under main's pi 'rad/s' bound): as rad/s
    it would pull 12 m/s^2 sideways, beyond 1 g. In rad/s: 0.2 m/s^2, read."""
    t = np.arange(0.0, 120.0, 0.05)
    v = np.full(t.size, 4.0)
    w_deg = 3.0 * np.sin(2 * np.pi * t / 60.0)
    check_turns(t, v, np.radians(w_deg), "odometry")
    with pytest.raises(InputError, match="degrees per second"):
        check_turns(t, v, w_deg, "odometry")


def test_victoria_park_real_odometry_passes(datasets_dir: Path) -> None:
    """The real log in seconds and rad/s: 0.012 rad per row, 1.27 m/s^2 (99th percentiles)."""
    t, v, w = _vp_odometry(datasets_dir)
    check_turns(t / 1e3, v, w, "odometry")


def test_scan_times_in_milliseconds_warned(datasets_dir: Path) -> None:
    """Victoria Park's laser frames (a median 0.214 s apart) stamped in ms step by 214."""
    t = np.loadtxt(datasets_dir / "victoria_park" / "measurements.dat", usecols=0)
    t = np.unique(t)
    assert check_scan_period(t, "scans") is None
    msg = check_scan_period(t * 1e3, "scans")
    assert msg is not None and "milliseconds" in msg and "divide them by 1e3" in msg


def test_imu_gyro_in_milliseconds_refused(tmp_path: Path) -> None:
    """A 100 Hz gyro turning at up to 0.5 rad/s, stamped in ms from the start: 5 rad between
    samples read as seconds. In seconds it is read."""
    from stemmap.io.imu import read_imu_csv

    t = np.arange(0.0, 60.0, 0.01)
    gz = 0.5 * np.sin(2 * np.pi * t / 20.0)
    rows = np.column_stack((t, gz))
    path = tmp_path / "imu_s.csv"
    np.savetxt(path, rows, delimiter=",", header="time_s,gyro_z", comments="", fmt="%.9g")
    assert read_imu_csv(path).times.size == t.size
    rows[:, 0] *= 1e3
    np.savetxt(path, rows, delimiter=",", header="time_s,gyro_z", comments="", fmt="%.9g")
    with pytest.raises(InputError, match="milliseconds"):
        read_imu_csv(path)
