"""Sensor positions of the points of a cloud file, for the along-ray refinement of the stem
fits (:func:`stemmap.cloud.stems.detect_stems` ``origins=``; docs/algorithms/cloud.md step 6).

A point file rarely stores where the scanner stood. Two sources are supported:

* one **station** for every point (a single terrestrial scan, or one lidar frame in its own
  sensor frame: station 0, 0);
* a **trajectory** (timed planar poses of the machine, :class:`stemmap.types.Trajectory`: the
  stemmap trajectory CSV ``time,x,y,theta`` or a TUM file) plus each point's time stamp (LAS
  ``gps_time``, or a ``time`` / ``timestamp`` field of PLY, PCD and text files): the pose is
  interpolated at the point's time (linear in x, y; shortest arc in theta) and the sensor's
  mounting offset on the machine is applied (:func:`stemmap.slam.base.sensor_poses`).

Only the horizontal position is used: the refinement works on horizontal slices.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, Trajectory

__all__ = ["TIME_FIELDS", "SensorPositions"]

#: Per-point time fields looked for, in this order, when ``time_field`` is not given.
TIME_FIELDS = ("gps_time", "time", "timestamp")


@dataclass(frozen=True)
class SensorPositions:
    """Where the scanner was when it measured each point (exactly one of ``station`` and
    ``trajectory``).

    Parameters
    ----------
    station : (x, y) or (x, y, z), metres, optional
        One scanner position for every point (z is accepted and ignored).
    trajectory : Trajectory, optional
        Machine poses over time, in the cloud's frame and on the points' time base.
    time_field : str, optional
        Per-point time field; default the first of :data:`TIME_FIELDS` that the file has.
    time_offset : float, seconds
        Added to the point times before the trajectory is looked up (e.g. 1e9 to turn LAS
        "adjusted standard GPS time" into GPS seconds).
    sensor_offset : (a, b), metres
        Scanner position on the machine, forward and left of the trajectory's reference point
        (as ``stemmap map --sensor-offset``).
    max_gap : float, seconds, optional
        How far outside the trajectory's time span a point may lie and still get the end pose;
        default one median trajectory step (poses stamped at the start or end of a revolution
        leave up to one step uncovered). Points further out are an error: the time bases
        probably differ.
    """

    station: tuple[float, ...] | None = None
    trajectory: Trajectory | None = None
    time_field: str | None = None
    time_offset: float = 0.0
    sensor_offset: tuple[float, float] = (0.0, 0.0)
    max_gap: float | None = None

    def __post_init__(self) -> None:
        if (self.station is None) == (self.trajectory is None):
            raise ConfigError("give exactly one of a sensor station and a trajectory.")
        if self.station is not None:
            st = tuple(float(v) for v in self.station)
            if len(st) not in (2, 3) or not all(math.isfinite(v) for v in st):
                raise ConfigError(
                    f"a sensor station is 2 or 3 finite coordinates (m), got {self.station!r}."
                )
            object.__setattr__(self, "station", st)
        if self.trajectory is not None and len(self.trajectory) < 2:
            raise InputError(
                f"a trajectory for sensor positions needs at least 2 poses, got "
                f"{len(self.trajectory)}."
            )
        if not math.isfinite(self.time_offset):
            raise ConfigError(f"time_offset must be finite, got {self.time_offset}.")
        off = tuple(float(v) for v in self.sensor_offset)
        if len(off) != 2 or not all(math.isfinite(v) for v in off):
            raise ConfigError(
                f"sensor_offset must be (a, b) in metres, got {self.sensor_offset!r}."
            )
        object.__setattr__(self, "sensor_offset", off)
        if self.max_gap is not None and not self.max_gap >= 0:
            raise ConfigError(f"max_gap must be >= 0 s, got {self.max_gap}.")

    @property
    def needs_time(self) -> bool:
        """True if each point's time stamp is needed (a trajectory)."""
        return self.trajectory is not None

    def pick_time_field(self, available: Iterable[str], source: str) -> str:
        """The time field to use among ``available`` (InputError naming them if none fits)."""
        have = tuple(available)
        if self.time_field is not None:
            if self.time_field in have:
                return self.time_field
            raise InputError(
                f"{source} has no per-point time field {self.time_field!r} (its fields: "
                f"{', '.join(have) or 'none'}); pick one with --time-field."
            )
        for name in TIME_FIELDS:
            if name in have:
                return name
        raise InputError(
            f"{source} has no per-point time ({' / '.join(TIME_FIELDS)}), which a trajectory "
            f"needs to place the sensor (its fields: {', '.join(have) or 'none'}). Pass "
            "--time-field NAME, or --origin X,Y for a single station."
        )

    def origins(self, n: int, times: NDArray[Any] | None, source: str) -> FloatArray:
        """Horizontal sensor position (n, 2) of ``n`` points with time stamps ``times``."""
        if self.station is not None:
            return np.broadcast_to(np.asarray(self.station[:2], dtype=np.float64), (n, 2))
        assert self.trajectory is not None
        if times is None or np.shape(times) != (n,):
            raise InputError(
                f"{source}: sensor positions from a trajectory need one time per point."
            )
        t = np.asarray(times, dtype=np.float64) + self.time_offset
        if not np.all(np.isfinite(t)):
            raise InputError(f"{source}: {int((~np.isfinite(t)).sum())} point times are NaN/inf.")
        tr = self.trajectory
        gap = self.max_gap
        if gap is None:
            gap = float(np.median(np.diff(tr.times)))
        t0, t1 = float(tr.times[0]), float(tr.times[-1])
        out = (t < t0 - gap) | (t > t1 + gap)
        if n and out.any():
            raise InputError(
                f"{source}: {int(out.sum())} of {n} points have times outside the trajectory "
                f"(points {float(t.min()):.6f} .. {float(t.max()):.6f} s after the time offset, "
                f"trajectory {t0:.6f} .. {t1:.6f} s, allowed gap {gap:.3g} s). The time bases "
                "probably differ (GPS week seconds, adjusted standard GPS time = GPS - 1e9, "
                "Unix time): shift the points with --time-offset."
            )
        from stemmap.slam.base import sensor_poses

        poses = tr.interpolate(t)
        return sensor_poses(poses, (self.sensor_offset[0], self.sensor_offset[1]))[:, :2]
