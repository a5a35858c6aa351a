"""Sequences of lidar frames for odometry: a folder of per-frame clouds, a 2D scan file, a frames
bundle NPZ (:mod:`stemmap.io.frames`, ``stemmap sim munjer``), or the PointCloud2 / LaserScan
topic of a ROS bag, each yielded lazily as ``(time, frame)``.

Folder of clouds
----------------
Every file with a point-cloud extension (``.pcd``, ``.ply``, ``.las``, ``.laz``, ``.xyz``,
``.txt``, ``.pts``, ``.csv``) is one frame, in the SENSOR frame (x forward, z up). Time stamps,
first rule that applies:

1. a sidecar ``times.csv`` in the folder with header ``file,time_s`` and one row per frame
   file (other files are ignored; frames are taken in time order);
2. every file stem is a number of seconds (``1690000000.123456.pcd``, ``12.3.ply``);
3. ``rate_hz`` given: files in name order at ``k / rate_hz`` seconds.

Anything else is an InputError that lists these three options.
"""

from __future__ import annotations

import csv
import itertools
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stemmap.errors import InputError
from stemmap.io._util import PathLike, check_npz_sizes
from stemmap.io.clouds import CLOUD_EXTENSIONS, read_cloud
from stemmap.types import LaserScan, PointCloud

log = logging.getLogger(__name__)

__all__ = ["TIMES_SIDECAR", "FrameSequence", "open_frames"]

TIMES_SIDECAR = "times.csv"


@dataclass(frozen=True)
class FrameSequence:
    """Where frames come from, and how to iterate them (:meth:`__iter__` is lazy).

    Attributes
    ----------
    path : Path
    kind : str
        ``"folder"``, ``"scans"`` (2D scan file), ``"bundle"`` (frames bundle NPZ) or ``"bag"``.
    files : tuple of (float, Path)
        For a folder: each frame file with its time.
    topic : str or None
        For a bag: the PointCloud2 or LaserScan topic to read.
    msgtype : str
        For a bag: ``"pointcloud2"`` or ``"laserscan"``.
    """

    path: Path
    kind: str
    files: tuple[tuple[float, Path], ...] = ()
    topic: str | None = None
    msgtype: str = ""
    n_frames: int = 0

    def __len__(self) -> int:
        return len(self.files) or self.n_frames

    def __iter__(self) -> Iterator[tuple[float, PointCloud | LaserScan]]:
        if self.kind == "folder":
            for t, f in self.files:
                yield t, read_cloud(f)
        elif self.kind == "bundle":
            from stemmap.io.frames import read_frames_npz

            b = read_frames_npz(self.path)
            assert b.lidar is not None
            for t, xyz in zip(b.times.tolist(), b.lidar, strict=True):
                yield t, PointCloud(xyz, time=t, frame="lidar")
        elif self.kind == "scans" or self.msgtype == "laserscan":
            from stemmap.io.scans import check_scan_conventions

            for k, scan in enumerate(self._laser_scans()):
                if k == 0:  # the units and angles `read_scans` checks on a whole batch
                    check_scan_conventions(scan.angle_min, scan.ranges, str(self.path))
                yield scan.time, scan
        else:
            from stemmap.io.rosbag import read_pointclouds

            for cloud in read_pointclouds(self.path, self.topic):
                yield cloud.time, cloud

    def _laser_scans(self) -> Iterator[LaserScan]:
        if self.kind == "scans":
            from stemmap.io.scans import iter_scans

            return iter_scans(self.path)
        from stemmap.io.rosbag import iter_laser_scans

        return iter_laser_scans(self.path, self.topic)


def _sidecar_times(folder: Path, sidecar: Path) -> list[tuple[float, Path]]:
    out: list[tuple[float, Path]] = []
    try:
        with sidecar.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the frame times {str(sidecar)!r}: {exc}") from exc
    body = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if not body or [c.strip() for c in body[0][:2]] != ["file", "time_s"]:
        raise InputError(
            f"{str(sidecar)!r} must start with the header 'file,time_s' (one row per frame file)."
        )
    for k, r in enumerate(body[1:], start=2):
        if len(r) < 2:
            raise InputError(f"{str(sidecar)!r} row {k} needs a file name and a time.")
        f = folder / r[0].strip()
        try:
            t = float(r[1])
        except ValueError:
            raise InputError(f"{str(sidecar)!r} row {k}: time {r[1]!r} is not a number.") from None
        if not math.isfinite(t):
            raise InputError(f"{str(sidecar)!r} row {k}: time {r[1]!r} is not finite.")
        if not f.is_file():
            raise InputError(
                f"{str(sidecar)!r} row {k} names {r[0]!r}, which is not in the folder."
            )
        out.append((t, f))
    if not out:
        raise InputError(f"{str(sidecar)!r} lists no frame.")
    return out


def _folder(folder: Path, rate_hz: float | None) -> FrameSequence:
    sidecar = folder / TIMES_SIDECAR
    files = sorted(
        f
        for f in folder.iterdir()
        if f.is_file() and f.suffix.lower() in CLOUD_EXTENSIONS and f.name != TIMES_SIDECAR
    )
    if sidecar.is_file():
        timed = _sidecar_times(folder, sidecar)
    else:
        if not files:
            raise InputError(
                f"folder {str(folder)!r} holds no point-cloud file ({', '.join(CLOUD_EXTENSIONS)})."
            )
        try:
            timed = [(float(f.stem), f) for f in files]
        except ValueError:
            if rate_hz is None:
                raise InputError(
                    f"cannot time the frames in {str(folder)!r}: give a sidecar "
                    f"{TIMES_SIDECAR} ('file,time_s' rows), name the files by their time in "
                    "seconds (12.300.pcd), or pass --rate HZ (frames in name order)."
                ) from None
            if not rate_hz > 0:
                raise InputError(f"--rate must be > 0 Hz, got {rate_hz}.") from None
            timed = [(k / rate_hz, f) for k, f in enumerate(files)]
    timed.sort(key=lambda tf: tf[0])
    for (t0, f0), (t1, f1) in itertools.pairwise(timed):
        if not t1 > t0:
            raise InputError(
                f"frames {f0.name!r} and {f1.name!r} in {str(folder)!r} have the same time "
                f"{t0} s; every frame needs its own time."
            )
    return FrameSequence(folder, "folder", tuple(timed))


def open_frames(
    path: PathLike, *, topic: str | None = None, rate_hz: float | None = None
) -> FrameSequence:
    """Find the frames at ``path`` (see the module docstring for the forms accepted).

    Parameters
    ----------
    path : str or PathLike
        A folder of per-frame clouds, a 2D scan file (``.npz``, ``.csv``: :mod:`stemmap.io
        .scans`), a frames bundle with lidar frames (``.npz``: :mod:`stemmap.io.frames`), or a
        ROS bag.
    topic : str, optional
        Bag topic (PointCloud2 or LaserScan); default: the only PointCloud2 topic, else the
        only LaserScan topic.
    rate_hz : float, optional
        Frame rate for a folder whose files carry no time.

    Raises
    ------
    InputError
        Missing path, no frames, untimed frames, an ambiguous or missing bag topic.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"frames {str(p)!r} do not exist.")
    from stemmap.io.rosbag import IMU, LASERSCAN, POINTCLOUD2, is_bag, list_topics

    if is_bag(p):
        topics = list_topics(p)
        clouds = [t for t, m in topics.items() if m == POINTCLOUD2]
        scans = [t for t, m in topics.items() if m == LASERSCAN]
        if topic is not None:
            if topic not in topics:
                raise InputError(
                    f"bag {str(p)!r} has no topic {topic!r}; it has {', '.join(topics) or 'none'}."
                )
            if topics[topic] not in (POINTCLOUD2, LASERSCAN):
                raise InputError(
                    f"topic {topic!r} of {str(p)!r} is {topics[topic]}, not a PointCloud2 or "
                    "LaserScan topic."
                )
            kind = "pointcloud2" if topics[topic] == POINTCLOUD2 else "laserscan"
            return FrameSequence(p, "bag", topic=topic, msgtype=kind)
        if len(clouds) == 1:
            return FrameSequence(p, "bag", topic=clouds[0], msgtype="pointcloud2")
        if not clouds and len(scans) == 1:
            return FrameSequence(p, "bag", topic=scans[0], msgtype="laserscan")
        found = ", ".join(f"{t} ({m})" for t, m in topics.items() if m != IMU) or "none"
        raise InputError(
            f"bag {str(p)!r}: choose the lidar topic with --topic; PointCloud2 / LaserScan "
            f"topics found: {found}."
        )
    if p.is_dir():
        return _folder(p, rate_hz)
    from stemmap.io.frames import is_frames_npz

    if is_frames_npz(p):
        with np.load(p, allow_pickle=False) as z:
            check_npz_sizes(z, p, "frames bundle")
            if "points" not in z.files:
                raise InputError(
                    f"frames bundle {str(p)!r} holds RGB-D frames but no lidar frames."
                )
            n = int(z["times"].shape[0])
        return FrameSequence(p, "bundle", n_frames=n)
    from stemmap.io.scans import scan_file_kind

    scan_file_kind(p)  # InputError for an unknown file type
    return FrameSequence(p, "scans")
