"""ROS1 (``.bag``) and ROS2 (folder with ``metadata.yaml``, or a bare ``.db3`` / ``.mcap``)
bag readers, via the ``rosbags`` package (no ROS installation needed).

Supported messages and what they become:

=============================  =====================================================
``sensor_msgs/LaserScan``      :class:`stemmap.types.LaserScan` (:func:`iter_laser_scans`)
``nav_msgs/Odometry``          :class:`OdometryLog` -- times, planar poses, twists
``sensor_msgs/Imu``            :class:`ImuLog` -- roll / pitch (tilt compensation)
``sensor_msgs/NavSatFix``      :class:`GnssLog` -- latitude, longitude, altitude, status
``sensor_msgs/PointCloud2``    :class:`stemmap.types.PointCloud` (:func:`read_pointclouds`)
=============================  =====================================================

Topic choice: with ``topic=None`` the only topic of the needed type is used; if there is none
or more than one, an :class:`~stemmap.errors.InputError` lists the bag's topics.

Time stamps are the message ``header.stamp`` in seconds; a zero stamp (drivers that do not
fill it) falls back to the bag's receive time. A message that cannot be decoded is skipped,
logged, and recorded in the optional ``skipped`` list; a bag whose data end early (truncated
recording) yields the messages before the damage and records one skipped entry for the rest.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import InputError
from stemmap.io._bag import (
    BAG_SUFFIXES,
    LASERSCAN,
    POINTCLOUD2,
    POINTFIELD_DTYPES,
    TopicSummary,
    _checked,
    _iter_messages,
    _skip,
    _stamp,
    bag_summary,
    is_bag,
    list_topics,
    open_bag,
)
from stemmap.io._bag import (
    IMU as IMU,
)
from stemmap.io._bag import (
    NAVSATFIX as NAVSATFIX,
)
from stemmap.io._bag import (
    ODOMETRY as ODOMETRY,
)
from stemmap.io._bag_salvage import _records as _records
from stemmap.io._util import PathLike, SkippedFrame
from stemmap.io.bag_logs import (
    GnssLog,
    ImuLog,
    OdometryLog,
    read_imu,
    read_navsatfix,
    read_odometry,
    roll_pitch_from_acceleration,
    roll_pitch_from_quaternion,
)
from stemmap.io.bag_write import write_scans_bag
from stemmap.types import LaserScan, PointCloud

__all__ = [
    "BAG_SUFFIXES",
    "GnssLog",
    "ImuLog",
    "OdometryLog",
    "PointField",
    "TopicSummary",
    "bag_summary",
    "decode_pointcloud2",
    "indexed_laser_scans",
    "is_bag",
    "iter_laser_scans",
    "laserscan_from_msg",
    "list_topics",
    "open_bag",
    "read_imu",
    "read_navsatfix",
    "read_odometry",
    "read_pointclouds",
    "roll_pitch_from_acceleration",
    "roll_pitch_from_quaternion",
    "write_scans_bag",
]


# --------------------------------------------------------------------------------------------
# LaserScan
# --------------------------------------------------------------------------------------------


def laserscan_from_msg(msg: Any, time: float) -> LaserScan:
    """A :class:`LaserScan` from a decoded ``sensor_msgs/LaserScan`` message.

    ``intensities`` are kept when they have one value per beam, dropped otherwise (many
    drivers publish an empty array). Raises InputError on invalid geometry.
    """
    # as the message holds them (float32 views of the message): LaserScan converts them to
    # float64 in one copy (converting here first held a second float64 copy of a large scan)
    ranges = np.asarray(msg.ranges)
    inten = np.asarray(msg.intensities)
    return LaserScan(
        ranges,
        float(msg.angle_min),
        float(msg.angle_increment),
        time=time,
        range_min=max(float(msg.range_min), 0.0),
        range_max=float(msg.range_max) if float(msg.range_max) > 0 else math.inf,
        intensities=inten if inten.shape == ranges.shape else None,
        frame=str(msg.header.frame_id) or "laser",
    )


def iter_laser_scans(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> Iterator[LaserScan]:
    """Lazily yield the ``sensor_msgs/LaserScan`` messages of a bag as :class:`LaserScan`.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only LaserScan topic in the bag.
    skipped : list, optional
        Receives a :class:`SkippedFrame` for every message that could not be used.

    Raises
    ------
    InputError
        If the bag cannot be opened or the topic is missing / ambiguous.
    """
    for _, scan in indexed_laser_scans(path, topic, skipped=skipped):
        yield scan


def indexed_laser_scans(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> Iterator[tuple[int, LaserScan]]:
    """Like :func:`iter_laser_scans`, yielding ``(message index in the topic, scan)``."""
    for m in _checked(_iter_messages(path, LASERSCAN, topic), path, skipped):
        try:
            scan = laserscan_from_msg(m.msg, _stamp(m.msg.header, m.bag_time))
        except (InputError, AttributeError, TypeError, ValueError) as exc:
            _skip(skipped, path, m, f"LaserScan message {m.seq} is invalid: {exc}")
        else:
            yield m.seq, scan


# --------------------------------------------------------------------------------------------
# PointCloud2
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PointField:
    """Layout of one field of a PointCloud2 point (mirrors ``sensor_msgs/PointField``)."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def decode_pointcloud2(
    data: bytes | NDArray[np.uint8],
    fields: Sequence[PointField | tuple[str, int, int, int]],
    *,
    point_step: int,
    width: int,
    height: int = 1,
    row_step: int | None = None,
    is_bigendian: bool = False,
    skip_nans: bool = True,
    time: float = 0.0,
    frame: str = "lidar",
) -> PointCloud:
    """Decode the byte buffer of a ``sensor_msgs/PointCloud2`` into a :class:`PointCloud`.

    Vectorised: the point layout (any offsets, any ``point_step`` with padding, any row
    padding via ``row_step``, little- or big-endian) becomes one numpy structured dtype that
    views the buffer without a per-point loop.

    Parameters
    ----------
    data : bytes or ndarray of uint8
        ``msg.data``: at least ``(height - 1) * row_step + width * point_step`` bytes.
    fields : sequence of PointField or (name, offset, datatype, count)
        Must contain ``x``, ``y`` and ``z``. Datatype codes as sensor_msgs/PointField
        (1 INT8 ... 8 FLOAT64). Fields with an empty name (padding) are ignored.
    point_step, width, height, row_step : int
        Bytes per point, points per row, rows, bytes per row (default ``width * point_step``).
    is_bigendian : bool
    skip_nans : bool
        Drop points whose x, y or z is NaN/inf (organised clouds mark missing returns so).
    time, frame
        Passed to the :class:`PointCloud`.

    Returns
    -------
    PointCloud
        ``xyz`` as float64; every other named field in ``fields`` (native byte order, shape
        (N,) or (N, count)).

    Examples
    --------
    >>> import numpy as np
    >>> pts = np.array([(1.0, 2.0, 3.0, 7), (np.nan, 0.0, 0.0, 8)],
    ...                dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("ring", ">u2")])
    >>> fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("ring", 12, 4, 1)]
    >>> c = decode_pointcloud2(pts.tobytes(), fields, point_step=14, width=2, is_bigendian=True)
    >>> c.xyz.tolist(), c.fields["ring"].tolist()
    ([[1.0, 2.0, 3.0]], [7])

    Raises
    ------
    InputError
        Unknown datatype, a field outside ``point_step``, missing x/y/z, duplicate field names,
        or a buffer too short for the declared layout.
    """
    if point_step <= 0 or width < 0 or height < 0:
        raise InputError(
            f"PointCloud2 layout is invalid: point_step={point_step}, width={width}, "
            f"height={height}."
        )
    row_step = width * point_step if row_step is None else int(row_step)
    if row_step < width * point_step:
        raise InputError(
            f"PointCloud2 row_step {row_step} is smaller than width * point_step = "
            f"{width * point_step}."
        )
    endian = ">" if is_bigendian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for f in fields:
        if isinstance(f, PointField):
            name, offset, datatype, count = f.name, f.offset, int(f.datatype), int(f.count)
        else:
            name, offset, datatype, count = str(f[0]), int(f[1]), int(f[2]), int(f[3])
        if not name:
            continue
        if datatype not in POINTFIELD_DTYPES:
            raise InputError(
                f"PointCloud2 field {name!r} has unknown datatype {datatype}; "
                "expected 1..8 (INT8 ... FLOAT64)."
            )
        if name in names:
            raise InputError(f"PointCloud2 field {name!r} appears twice in the layout.")
        base = np.dtype(endian + POINTFIELD_DTYPES[datatype])
        count = max(count, 1)
        if offset < 0 or offset + base.itemsize * count > point_step:
            raise InputError(
                f"PointCloud2 field {name!r} (offset {offset}, {count} x {base.itemsize} bytes) "
                f"does not fit in point_step {point_step}."
            )
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    missing = [c for c in ("x", "y", "z") if c not in names]
    if missing:
        raise InputError(
            f"PointCloud2 has no {', '.join(missing)} field(s); its fields are "
            f"{', '.join(names) or 'none'}."
        )
    dtype = np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    buf = np.ascontiguousarray(buf, dtype=np.uint8).reshape(-1)
    n = width * height
    need = 0 if n == 0 else (height - 1) * row_step + width * point_step
    if buf.size < need:
        raise InputError(
            f"PointCloud2 data has {buf.size} bytes but the layout ({height} rows x {width} "
            f"points, point_step {point_step}, row_step {row_step}) needs {need}."
        )
    if n == 0:
        recs = np.zeros(0, dtype=dtype)
    elif row_step == width * point_step:
        recs = buf[: n * point_step].view(dtype)
    else:
        rows = np.lib.stride_tricks.as_strided(
            buf, shape=(height, width * point_step), strides=(row_step, 1), writeable=False
        )
        recs = np.ascontiguousarray(rows).reshape(-1).view(dtype)
    # one float64 array filled column by column (not three converted columns, then their
    # stack), and no copy of it when every point is kept: a large cloud is ~2x lighter
    xyz = np.empty((n, 3), dtype=np.float64)
    for j, c in enumerate(("x", "y", "z")):
        if recs[c].ndim != 1:
            raise InputError(
                f"PointCloud2 field {c!r} has {recs[c].shape[1]} values a point; x, y and z "
                "have one."
            )
        xyz[:, j] = recs[c]
    keep = np.all(np.isfinite(xyz), axis=1) if skip_nans else np.ones(n, dtype=bool)
    extra = {}
    for c in names:
        if c in ("x", "y", "z"):
            continue
        col = recs[c]
        extra[c] = col[keep].astype(col.dtype.newbyteorder("="))
    return PointCloud(xyz if keep.all() else xyz[keep], time=time, frame=frame, fields=extra)


def read_pointclouds(
    path: PathLike,
    topic: str | None = None,
    *,
    skip_nans: bool = True,
    skipped: list[SkippedFrame] | None = None,
) -> Iterator[PointCloud]:
    """Lazily yield the ``sensor_msgs/PointCloud2`` messages of a bag as :class:`PointCloud`.

    Each cloud stays in its sensor frame (``header.frame_id``); see
    :func:`decode_pointcloud2` for the decoding. Bad messages are skipped and recorded.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skip_nans : bool
        Drop points with a NaN/inf coordinate (default True).
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Yields
    ------
    PointCloud
        One per message, ``xyz`` float64 in ``header.frame_id``, other fields in ``fields``.

    Raises
    ------
    InputError
        If the bag cannot be opened or the topic is missing / ambiguous.
    """
    for m in _checked(_iter_messages(path, POINTCLOUD2, topic), path, skipped):
        msg = m.msg
        try:
            cloud = decode_pointcloud2(
                np.asarray(msg.data, dtype=np.uint8),
                [PointField(f.name, f.offset, f.datatype, f.count) for f in msg.fields],
                point_step=int(msg.point_step),
                width=int(msg.width),
                height=int(msg.height),
                row_step=int(msg.row_step),
                is_bigendian=bool(msg.is_bigendian),
                skip_nans=skip_nans,
                time=_stamp(msg.header, m.bag_time),
                frame=str(msg.header.frame_id) or "lidar",
            )
        except (InputError, AttributeError, TypeError, ValueError) as exc:
            _skip(skipped, path, m, f"PointCloud2 message {m.seq} is invalid: {exc}")
        else:
            yield cloud
