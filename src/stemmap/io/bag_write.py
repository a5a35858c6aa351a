"""Writing LaserScan bags (ROS1 ``.bag``, ROS2 sqlite3 / mcap); re-exported by
:mod:`stemmap.io.rosbag`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.errors import ConfigError
from stemmap.io._bag import (
    LASERSCAN,
)
from stemmap.io._util import PathLike
from stemmap.types import ScanBatch

# --------------------------------------------------------------------------------------------
# writing LaserScan bags
# --------------------------------------------------------------------------------------------


def write_scans_bag(
    path: PathLike,
    batch: ScanBatch,
    *,
    topic: str = "/scan",
    ros: int = 1,
    storage: str = "sqlite3",
    compression: str | None = None,
    chunk_bytes: int | None = None,
    compression_mode: str = "message",
) -> Path:
    """Write a :class:`ScanBatch` as ``sensor_msgs/LaserScan`` messages in a ROS bag.

    The bag is first written beside the target under a temporary name and then renamed into
    place, so an interrupted write never leaves a half-written bag (ROS2 bags are folders: an
    existing folder is replaced only after the new one is complete).

    Parameters
    ----------
    path : str or PathLike
        ROS1: the ``.bag`` file (suffix added if missing). ROS2: the bag folder.
    batch : ScanBatch
        Ranges are stored as float32 (the message type's precision); NaN stays NaN.
    topic : str
    ros : {1, 2}
        ROS1 (Noetic types) or ROS2 (Humble types, rosbag2 format version 9).
    storage : {"sqlite3", "mcap"}
        ROS2 storage plugin.
    compression : {None, "bz2", "lz4", "zstd"}
        ROS1: compress each chunk with bz2 or lz4. ROS2: zstd, as ``compression_mode`` says
        (None: uncompressed).
    chunk_bytes : int, optional
        ROS1: start a new chunk once one holds this many bytes (None: rosbags' default).
    compression_mode : {"message", "file", "storage"}
        ROS2 with ``compression="zstd"``: compress each message, each storage file when it is
        closed, or (``storage="mcap"`` only) each MCAP chunk.

    Returns
    -------
    Path
        The path written (with ``.bag`` added for ROS1 if it was missing).

    Raises
    ------
    ConfigError
        For an unknown ``ros`` version, ``storage`` or ``compression``, or chunk options
        given for ROS2.
    """
    import os
    import shutil
    import tempfile

    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    if ros not in (1, 2):
        raise ConfigError(f"ros must be 1 or 2, got {ros!r}.")
    if storage not in ("sqlite3", "mcap"):
        raise ConfigError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}.")
    if compression not in (None, "bz2", "lz4", "zstd"):
        raise ConfigError(f"compression must be None, 'bz2', 'lz4' or 'zstd', got {compression!r}.")
    if ros == 2 and (compression in ("bz2", "lz4") or chunk_bytes is not None):
        raise ConfigError("bz2 / lz4 compression and chunk_bytes apply to ROS1 bags only.")
    if ros == 1 and compression == "zstd":
        raise ConfigError("zstd compression applies to ROS2 bags only (ROS1: bz2 or lz4).")
    if compression_mode not in ("message", "file", "storage") or (
        compression_mode == "storage" and storage != "mcap"
    ):
        raise ConfigError(
            "compression_mode must be 'message', 'file' or (mcap storage) 'storage', got "
            f"{compression_mode!r}."
        )
    target = Path(path)
    if ros == 1 and target.suffix.lower() != ".bag":
        target = target.with_name(target.name + ".bag")
    target.parent.mkdir(parents=True, exist_ok=True)
    ts = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    T = ts.types
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    tmp = tmpdir / target.name
    n = batch.n_beams
    try:
        if ros == 1:
            writer: Any = Writer1(tmp)
            if compression is not None:
                writer.set_compression(Writer1.CompressionFormat[compression.upper()])
            if chunk_bytes is not None:
                writer.chunk_threshold = chunk_bytes
        else:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(tmp, version=9, storage_plugin=plugin)
            if compression == "zstd":
                writer.set_compression(
                    CompressionMode[compression_mode.upper()], CompressionFormat.ZSTD
                )
        with writer:
            conn = writer.add_connection(topic, LASERSCAN, typestore=ts)
            ser = ts.serialize_ros1 if ros == 1 else ts.serialize_cdr
            empty = np.zeros(0, dtype=np.float32)
            for k, (t, r) in enumerate(zip(batch.times, batch.ranges, strict=True)):
                sec = math.floor(t)
                nsec = min(round((t - sec) * 1e9), 999_999_999)
                stamp = T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nsec))
                hdr_kw: dict[str, Any] = {"stamp": stamp, "frame_id": batch.frame}
                if ros == 1:
                    hdr_kw["seq"] = k
                msg = T[LASERSCAN](
                    header=T["std_msgs/msg/Header"](**hdr_kw),
                    angle_min=batch.angle_min,
                    angle_max=batch.angle_min + batch.angle_increment * (n - 1),
                    angle_increment=batch.angle_increment,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=batch.range_min,
                    range_max=batch.range_max,
                    ranges=np.asarray(r, dtype=np.float32),
                    intensities=empty,
                )
                writer.write(
                    conn, max(int(sec) * 1_000_000_000 + int(nsec), 1), ser(msg, LASERSCAN)
                )
        if ros == 1 or not target.exists():
            os.replace(tmp, target)
        else:  # replace an existing ROS2 folder: move it aside, move the new one in
            old = tmpdir / "previous"
            os.replace(target, old)
            os.replace(tmp, target)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return target
