"""Hostile ROS 2 bags and MCAP files for benchmarks/hostile_inputs.py and tests/io: small files
that decompress to gigabytes of ``sensor_msgs/LaserScan`` (ranges of 0.0).

* :func:`zstd_rle` writes a zstd frame by hand from raw blocks and RLE blocks (4 bytes per
  128 kB of equal bytes: 32768:1, so 1 GB is ~31 kB on disk, written in milliseconds),
  with or without the decompressed size in its header;
* :func:`mcap_bomb`: an MCAP file whose one chunk (zstd or lz4) holds ``n`` scans of
  ``beams`` ranges, its header announcing their size or ``size`` (a lie), with or without a
  summary (chunk index);
* :func:`ros2_message_bomb`: a ROS 2 sqlite3 bag compressed per message (zstd) whose last
  message inflates to ``beams`` ranges;
* :func:`ros2_file_bomb`: a ROS 2 bag compressed per file whose storage file inflates to
  ``gb`` GB, its frame header announcing it (or not).
"""

from __future__ import annotations

import math
import sqlite3
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

_ZSTD_MAGIC = struct.pack("<I", 0xFD2FB528)
_BLOCK = 1 << 17  # zstd's largest block: 128 kB


def zstd_rle(parts: Iterable[bytes | int], content_size: int | None = None) -> bytes:
    """One zstd frame holding ``parts`` in order: ``bytes`` as raw blocks, an ``int`` n as n
    zero bytes in RLE blocks. ``content_size``: announce this decompressed size in the frame
    header (None: announce none, as a streaming compressor does)."""
    out = bytearray(_ZSTD_MAGIC)
    if content_size is None:
        out += bytes([0x00, 0x50])  # no size; window 2^20 (>= one block)
    else:
        out += bytes([0xC0, 0x50]) + struct.pack("<Q", content_size)
    blocks: list[tuple[int, int, bytes]] = []  # (type, size, payload)
    for p in parts:
        if isinstance(p, int):
            for k in range(0, p, _BLOCK):
                blocks.append((1, min(_BLOCK, p - k), b"\x00"))
        else:
            for k in range(0, len(p), _BLOCK):
                chunk = p[k : k + _BLOCK]
                blocks.append((0, len(chunk), chunk))
    if not blocks:
        blocks.append((0, 0, b""))
    for i, (kind, size, payload) in enumerate(blocks):
        last = 1 if i == len(blocks) - 1 else 0
        out += (last | kind << 1 | size << 3).to_bytes(3, "little") + payload
    return bytes(out)


def laserscan_message(types: Any, beams: int, ranges: np.ndarray, stamp_s: int = 1) -> Any:
    """A full-circle ``sensor_msgs/msg/LaserScan`` of ``beams`` beams holding ``ranges`` (any
    length: the hostile inputs put a marker or zeros there), stamped ``stamp_s``, built with
    the typestore ``types`` (ROS 1 or ROS 2: ROS 1's header also takes ``seq``)."""
    inc = 2 * math.pi / max(beams, 1)
    stamp = types["builtin_interfaces/msg/Time"](sec=stamp_s, nanosec=0)
    header_type = types["std_msgs/msg/Header"]
    ros1 = "seq" in getattr(header_type, "__dataclass_fields__", {})
    header = (
        header_type(seq=0, stamp=stamp, frame_id="laser")
        if ros1
        else header_type(stamp=stamp, frame_id="laser")
    )
    return types["sensor_msgs/msg/LaserScan"](
        header=header,
        angle_min=-math.pi,
        angle_max=-math.pi + inc * (beams - 1),
        angle_increment=inc,
        time_increment=0.0,
        scan_time=0.0,
        range_min=0.1,
        range_max=30.0,
        ranges=ranges,
        intensities=np.zeros(0, np.float32),
    )


def laserscan_cdr_parts(beams: int, stamp_s: int = 1) -> tuple[bytes, bytes]:
    """(bytes before the ranges, bytes after them) of a CDR ``sensor_msgs/msg/LaserScan``
    whose ``beams`` ranges are zero bytes in between."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    marker = np.array([1.2345], np.float32)
    msg = laserscan_message(T, beams, marker, stamp_s)
    ser = bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))
    at = ser.find(marker.tobytes())
    return ser[: at - 4] + struct.pack("<I", beams), ser[at + 4 :]


# --------------------------------------------------------------------------------------------
# MCAP
# --------------------------------------------------------------------------------------------

MCAP_MAGIC = b"\x89MCAP0\r\n"


def _s(text: str) -> bytes:
    b = text.encode()
    return struct.pack("<I", len(b)) + b


def _rec(op: int, body: bytes) -> bytes:
    return bytes([op]) + struct.pack("<Q", len(body)) + body


def _schema_channel() -> bytes:
    schema = _rec(0x03, struct.pack("<H", 1) + _s("sensor_msgs/msg/LaserScan") + _s("") + _s(""))
    channel = _rec(0x04, struct.pack("<HH", 1, 1) + _s("/scan") + _s("cdr") + struct.pack("<I", 0))
    return schema + channel


def _message_head(k: int, data_len: int) -> bytes:
    t = (1 + k) * 1_000_000_000
    return bytes([0x05]) + struct.pack("<QHIQQ", 22 + data_len, 1, k, t, t)


def mcap_bomb(
    path: Path,
    n: int,
    beams: int,
    *,
    compression: str = "zstd",
    size: int | None = None,
    indexed: bool = False,
) -> Path:
    """An MCAP file (profile ros2) whose one chunk holds ``n`` LaserScans of ``beams`` zero
    ranges (4 x n x beams bytes), compressed with ``compression`` (``"zstd"``: hand-made RLE
    frame; ``"lz4"``: python-lz4's frame compressor, ~250:1, streamed). The chunk header
    announces the true size or ``size``. ``indexed``: add a summary (schema, channel, chunk
    index, message index) as rosbags' writer does; otherwise rosbags scans the file."""
    pre, post = laserscan_cdr_parts(beams)
    data_len = len(pre) + 4 * beams + len(post)
    head = _schema_channel()
    msg_offsets = []
    parts: list[bytes | int] = [head]
    at = len(head)
    for k in range(n):
        msg_offsets.append(at)
        parts += [_message_head(k, data_len) + pre, 4 * beams, post]
        at += 31 + data_len
    usize = at
    if compression == "zstd":
        comp = zstd_rle(parts, content_size=usize)
    else:
        from lz4.frame import LZ4FrameCompressor

        c = LZ4FrameCompressor()
        pieces = [c.begin()]
        zeros = bytes(1 << 22)
        for p in parts:
            if isinstance(p, int):
                for k in range(0, p, len(zeros)):
                    pieces.append(c.compress(zeros[: min(len(zeros), p - k)]))
            else:
                pieces.append(c.compress(p))
        pieces.append(c.flush())
        comp = b"".join(pieces)
    t0, t1 = 1_000_000_000, n * 1_000_000_000
    announced = usize if size is None else size
    chunk_body = (
        struct.pack("<QQQI", t0, t1, announced, 0) + _s(compression) + struct.pack("<Q", len(comp))
    )
    header = _rec(0x01, _s("ros2") + _s("stemmap-hostile"))
    out = bytearray(MCAP_MAGIC + header)
    chunk_start = len(out)
    out += bytes([0x06]) + struct.pack("<Q", len(chunk_body) + len(comp)) + chunk_body + comp
    chunk_len = len(out) - chunk_start
    summary_start = 0
    if indexed:
        mi_start = len(out)
        entries = b"".join(
            struct.pack("<QQ", (1 + k) * 1_000_000_000, o) for k, o in enumerate(msg_offsets)
        )
        out += _rec(0x07, struct.pack("<HI", 1, len(entries)) + entries)
        mi_len = len(out) - mi_start
        out += _rec(0x0F, struct.pack("<I", 0))  # data end
        summary_start = len(out)
        out += _schema_channel()
        offsets = struct.pack("<HQ", 1, mi_start)
        out += _rec(
            0x08,
            struct.pack("<QQQQ", t0, t1, chunk_start, chunk_len)
            + struct.pack("<I", len(offsets))
            + offsets
            + struct.pack("<Q", mi_len)
            + _s(compression)
            + struct.pack("<QQ", len(comp), announced),
        )
    else:
        out += _rec(0x0F, struct.pack("<I", 0))
    out += _rec(0x02, struct.pack("<QQI", summary_start, 0, 0)) + MCAP_MAGIC
    path.write_bytes(bytes(out))
    return path


# --------------------------------------------------------------------------------------------
# ROS 2 bags compressed with zstd
# --------------------------------------------------------------------------------------------


def _small_ros2_bag(folder: Path, mode: str, n: int = 3, beams: int = 90) -> Path:
    """A ROS 2 sqlite3 bag of ``n`` LaserScans written by rosbags, zstd-compressed per
    ``mode`` (``"message"`` or ``"file"``)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    writer = Writer(folder, version=9)
    writer.set_compression(
        CompressionMode.MESSAGE if mode == "message" else CompressionMode.FILE,
        CompressionFormat.ZSTD,
    )
    with writer:
        conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        for k in range(n):
            pre, post = laserscan_cdr_parts(beams, stamp_s=1 + k)
            writer.write(conn, (1 + k) * 1_000_000_000, ts_bytes(pre, beams, post))
    return folder


def ts_bytes(pre: bytes, beams: int, post: bytes) -> bytes:
    return pre + bytes(4 * beams) + post


def ros2_message_bomb(folder: Path, beams: int, *, announce: bool = True) -> Path:
    """A message-compressed ROS 2 bag of 3 LaserScans whose last message's zstd frame inflates
    to ``beams`` zero ranges (4 x beams bytes), announced in its frame header or not."""
    _small_ros2_bag(folder, "message")
    pre, post = laserscan_cdr_parts(beams, stamp_s=3)
    size = len(pre) + 4 * beams + len(post)
    blob = zstd_rle([pre, 4 * beams, post], content_size=size if announce else None)
    db = next(folder.glob("*.db3"))
    con = sqlite3.connect(db)
    with con:
        con.execute(
            "UPDATE messages SET data = ? WHERE id = (SELECT max(id) FROM messages)", (blob,)
        )
    con.close()
    return folder


def ros2_file_bomb(
    folder: Path, gb: float, *, announce: bool = True, content_size: int | None = None
) -> Path:
    """A file-compressed ROS 2 bag whose storage file inflates to the real bag's database
    followed by ``gb`` GB of zero bytes (sqlite ignores them), its size announced in the frame
    header or not; ``content_size``: announce this instead (a lie)."""
    from stemmap.io._bag2_budget import _zstd

    _small_ros2_bag(folder, "file")
    f = next(folder.glob("*.zstd"))
    db = _zstd().decompress(f.read_bytes())
    pad = int(gb * 1e9)
    told = content_size if content_size is not None else len(db) + pad if announce else None
    f.write_bytes(zstd_rle([db, pad], content_size=told))
    return folder


# --------------------------------------------------------------------------------------------
# ROS 1 bag without its index
# --------------------------------------------------------------------------------------------


def ros1_unindexed_bag(
    path: Path, gb: float, *, beams: int = 1_000_000, chunk_mb: float = 64
) -> Path:
    """A ROS 1 bag of ``gb`` GB of LaserScans (``beams`` zero ranges each) in lz4 chunks of
    ``chunk_mb`` MB (~4 MB on disk a GB), cut at its index (``index_pos``): every chunk is
    complete, the connection and chunk records at the end are gone, so rosbags cannot open it
    and stemmap reads it chunk by chunk (the salvage path)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from stemmap.io._bag_salvage import _ROS1_MAGIC, _parse_header

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    msg = laserscan_message(T, beams, np.zeros(beams, np.float32))
    ser = ts.serialize_ros1(msg, "sensor_msgs/msg/LaserScan")
    writer = Writer(path)
    writer.set_compression(Writer.CompressionFormat.LZ4)
    writer.chunk_threshold = int(chunk_mb * 1e6)
    with writer:
        conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        for k in range(max(1, int(gb * 1e9 / len(ser)))):
            writer.write(conn, (1 + k) * 1_000_000_000, ser)
    with path.open("r+b") as fh:
        head = fh.read(4096)
        hlen = int.from_bytes(head[len(_ROS1_MAGIC) : len(_ROS1_MAGIC) + 4], "little")
        at = len(_ROS1_MAGIC) + 4
        index_pos = int.from_bytes(_parse_header(head[at : at + hlen])["index_pos"][:8], "little")
        fh.truncate(index_pos)
    return path
