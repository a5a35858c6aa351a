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

import contextlib
import logging
import math
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.io._util import PathLike, SkippedFrame
from stemmap.io.maps import lonlat_to_local
from stemmap.io.trajectory import yaw_from_quaternion
from stemmap.types import FloatArray, LaserScan, PointCloud, ScanBatch, Trajectory

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

log = logging.getLogger(__name__)

#: File suffixes recognised as bags (ROS1 ``.bag``; ROS2 storage files ``.db3``, ``.mcap``).
BAG_SUFFIXES = (".bag", ".db3", ".mcap")

LASERSCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"

#: sensor_msgs/PointField datatype codes -> numpy type characters.
POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _norm_type(msgtype: str) -> str:
    """``sensor_msgs/LaserScan`` and ``sensor_msgs/msg/LaserScan`` -> the latter."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return msgtype


def is_bag(path: PathLike) -> bool:
    """True if ``path`` looks like a ROS bag: a ``.bag``/``.db3``/``.mcap`` file or a folder
    holding ``metadata.yaml`` (ROS2)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in BAG_SUFFIXES


@contextlib.contextmanager
def open_bag(path: PathLike) -> Iterator[Any]:
    """Open a ROS1 or ROS2 bag as a ``rosbags.highlevel.AnyReader`` (context manager).

    Bags without embedded message definitions are decoded with the ROS1 Noetic (``.bag``) or
    ROS2 Humble type store.

    Raises
    ------
    InputError
        If the path does not exist or the bag cannot be opened (truncated, not a bag, ...).
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    p = Path(path)
    if not p.exists():
        raise InputError(f"ROS bag {str(p)!r} does not exist.")
    if p.is_dir() and not (p / "metadata.yaml").is_file():
        raise InputError(
            f"{str(p)!r} is a folder without metadata.yaml, so it is not a ROS2 bag; "
            "pass the bag folder, a .db3/.mcap file or a ROS1 .bag file."
        )
    store = Stores.ROS1_NOETIC if p.suffix.lower() == ".bag" else Stores.ROS2_HUMBLE
    try:
        reader = AnyReader([p], default_typestore=get_typestore(store))
        reader.open()
    except Exception as exc:  # rosbags raises many types on damaged files; wrap them all
        raise InputError(
            f"cannot open ROS bag {str(p)!r} ({type(exc).__name__}: {exc}); the file may be "
            "truncated or not a bag."
        ) from exc
    try:
        yield reader
    finally:
        reader.close()


def list_topics(path: PathLike) -> dict[str, str]:
    """Topics of a bag and their message types (``pkg/msg/Type``), sorted by topic name."""
    return {t.topic: t.msgtype for t in bag_summary(path)}


class TopicSummary(NamedTuple):
    """One topic of a bag: name, message type (``pkg/msg/Type``) and message count."""

    topic: str
    msgtype: str
    n_messages: int


def bag_summary(path: PathLike) -> list[TopicSummary]:
    """Every topic of a bag with its type and message count, sorted by topic name.

    For a ROS1 bag without a valid index, the counts are those recovered from its chunks.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.

    Returns
    -------
    list of TopicSummary
        ``(topic, msgtype, n_messages)``; types as ``pkg/msg/Type`` for ROS1 and ROS2 alike.

    Raises
    ------
    InputError
        If the path does not exist or is not a readable bag.
    """
    p = Path(path)
    try:
        with open_bag(p) as reader:
            return [
                TopicSummary(name, _norm_type(str(info.msgtype)), int(info.msgcount))
                for name, info in sorted(reader.topics.items())
            ]
    except InputError as exc:
        if not (p.suffix.lower() == ".bag" and p.is_file()):
            raise
        sv = _salvage_or_raise(p, exc, None)
    counts: Counter[str] = Counter()
    for cid, n in sv.counts.items():
        if cid in sv.conns:
            counts[sv.conns[cid][0]] += n
    topics = {t: m for t, m, _ in sv.conns.values()}
    return [TopicSummary(t, topics[t], counts.get(t, 0)) for t in sorted(topics)]


def _describe_topics(topics: dict[str, str]) -> str:
    if not topics:
        return "the bag has no topics"
    return "available topics: " + ", ".join(f"{t} ({m})" for t, m in sorted(topics.items()))


def _select_topic(reader: Any, path: Path, msgtype: str, topic: str | None) -> str:
    topics = {name: _norm_type(str(info.msgtype)) for name, info in reader.topics.items()}
    return _choose_topic(topics, path, msgtype, topic)


def _choose_topic(topics: dict[str, str], path: Path, msgtype: str, topic: str | None) -> str:
    if topic is not None:
        if topic not in topics:
            raise InputError(
                f"ROS bag {str(path)!r} has no topic {topic!r}; {_describe_topics(topics)}."
            )
        if topics[topic] != msgtype:
            raise InputError(
                f"topic {topic!r} in ROS bag {str(path)!r} carries {topics[topic]}, "
                f"not {msgtype}; {_describe_topics(topics)}."
            )
        return topic
    matching = sorted(t for t, m in topics.items() if m == msgtype)
    if len(matching) == 1:
        return matching[0]
    if not matching:
        raise InputError(
            f"ROS bag {str(path)!r} has no {msgtype} topic; {_describe_topics(topics)}."
        )
    raise InputError(
        f"ROS bag {str(path)!r} has {len(matching)} {msgtype} topics ({', '.join(matching)}); "
        "choose one with topic=... (--topic on the command line)."
    )


class _Message(NamedTuple):
    seq: int
    bag_time: float
    msg: Any  # None when decoding failed
    error: str


def _iter_messages(path: PathLike, msgtype: str, topic: str | None) -> Iterator[_Message]:
    """Decoded messages of one topic; decode failures and truncation come back as errors.

    A ROS1 bag that rosbags cannot open (index missing or damaged: a recording that was
    killed, a copy cut short) is salvaged by reading its chunks in file order.
    """
    p = Path(path)
    with contextlib.ExitStack() as stack:
        try:
            reader = stack.enter_context(open_bag(p))
        except InputError as exc:
            if not (p.suffix.lower() == ".bag" and p.is_file()):
                raise
            yield from _iter_salvaged(p, msgtype, topic, exc)
            return
        chosen = _select_topic(reader, p, msgtype, topic)
        conns = [c for c in reader.connections if c.topic == chosen]
        gen = reader.messages(connections=conns)
        k = 0
        while True:
            try:
                conn, t_ns, raw = next(gen)
            except StopIteration:
                return
            except Exception as exc:  # damaged chunk / truncated file
                yield _Message(
                    k,
                    math.nan,
                    None,
                    f"the bag's data end or are damaged after message {k} of topic {chosen} "
                    f"({type(exc).__name__}: {exc}); the rest of the topic is lost",
                )
                return
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as exc:
                yield _Message(
                    k,
                    t_ns * 1e-9,
                    None,
                    f"message {k} of topic {chosen} cannot be decoded as {msgtype} "
                    f"({type(exc).__name__}: {exc})",
                )
            else:
                yield _Message(k, t_ns * 1e-9, msg, "")
            k += 1


def _salvage_or_raise(path: Path, open_error: InputError, keep_topic: str | None) -> _Salvage:
    try:
        sv = _ros1_salvage(path, keep_topic)
    except (InputError, OSError, ValueError, KeyError) as exc:
        raise open_error from exc
    if not sv.counts:
        raise InputError(
            f"{open_error} Reading its chunks without the index recovered no message either."
        ) from open_error
    if keep_topic is None:
        log.warning(
            "ROS bag %s: the index is missing or damaged; found %d messages by reading its "
            "chunks%s.",
            path,
            sum(sv.counts.values()),
            f" ({sv.stop})" if sv.stop else "",
        )
    return sv


def _iter_salvaged(
    path: Path, msgtype: str, topic: str | None, open_error: InputError
) -> Iterator[_Message]:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    first = _salvage_or_raise(path, open_error, None)  # pass 1: topics and counts only
    topics = {t: m for t, m, _ in first.conns.values()}
    chosen = _choose_topic(topics, path, msgtype, topic)
    sv = _salvage_or_raise(path, open_error, chosen)  # pass 2: this topic's messages
    store = get_typestore(Stores.ROS1_NOETIC)
    for t, m, definition in sv.conns.values():  # non-standard types: the bag's definitions
        if t == chosen and m not in store.types and definition:
            with contextlib.suppress(Exception):
                store.register(get_types_from_msg(definition, m))
    k = 0
    for rec in sv.msgs:
        try:
            msg = store.deserialize_ros1(rec.raw, sv.conns[rec.conn][1])
        except Exception as exc:
            yield _Message(
                k,
                rec.t_ns * 1e-9,
                None,
                f"message {k} of topic {chosen} cannot be decoded as {msgtype} "
                f"({type(exc).__name__}: {exc})",
            )
        else:
            yield _Message(k, rec.t_ns * 1e-9, msg, "")
        k += 1
    if sv.stop:
        yield _Message(
            k,
            math.nan,
            None,
            f"the bag has no valid index and {sv.stop}; messages of {chosen} after message "
            f"{k - 1} are lost",
        )


def _stamp(header: Any, fallback: float) -> float:
    st = header.stamp
    t = float(st.sec) + 1e-9 * float(st.nanosec)
    return t if t != 0.0 else fallback


def _skip(skipped: list[SkippedFrame] | None, path: PathLike, m: _Message, reason: str) -> None:
    log.warning("skipping a frame of %s: %s.", path, reason)
    if skipped is not None:
        skipped.append(SkippedFrame(m.seq, m.bag_time, reason))


def _checked(
    messages: Iterator[_Message], path: PathLike, skipped: list[SkippedFrame] | None
) -> Iterator[_Message]:
    """Good messages only; the bad ones are logged and recorded."""
    for m in messages:
        if m.msg is None:
            _skip(skipped, path, m, m.error)
        else:
            yield m


# --------------------------------------------------------------------------------------------
# ROS1 salvage: read the chunks of a bag whose index is missing or damaged
# --------------------------------------------------------------------------------------------

_ROS1_MAGIC = b"#ROSBAG V2.0\n"
_OP_MSGDATA, _OP_BAGHEADER, _OP_INDEX, _OP_CHUNK, _OP_CHUNKINFO, _OP_CONNECTION = 2, 3, 4, 5, 6, 7


def _parse_header(buf: bytes | memoryview) -> dict[str, bytes]:
    """ROS1 record header: repeated ``uint32 len`` + ``name=value``; ValueError if malformed."""
    out: dict[str, bytes] = {}
    pos, n = 0, len(buf)
    while pos < n:
        if pos + 4 > n:
            raise ValueError("header field length runs past the header")
        ln = int.from_bytes(buf[pos : pos + 4], "little")
        pos += 4
        if ln == 0 or pos + ln > n:
            raise ValueError("header field runs past the header")
        field = bytes(buf[pos : pos + ln])
        pos += ln
        name, sep, value = field.partition(b"=")
        if not sep:
            raise ValueError("header field without '='")
        out[name.decode("latin-1")] = value
    return out


def _records(
    buf: bytes | memoryview, start: int
) -> Iterator[tuple[int, dict[str, bytes], int, int]]:
    """``(offset, header, data_start, data_end)`` of consecutive ROS1 records; stops at the first
    record that does not fit in ``buf`` (its offset is then returned by StopIteration value)."""
    pos, n = start, len(buf)
    while pos + 4 <= n:
        hlen = int.from_bytes(buf[pos : pos + 4], "little")
        if pos + 4 + hlen + 4 > n:
            return
        try:
            header = _parse_header(buf[pos + 4 : pos + 4 + hlen])
        except ValueError:
            return
        dpos = pos + 4 + hlen
        dlen = int.from_bytes(buf[dpos : dpos + 4], "little")
        yield pos, header, dpos + 4, min(dpos + 4 + dlen, n)
        if dpos + 4 + dlen > n:
            return
        pos = dpos + 4 + dlen


class _Salvaged(NamedTuple):
    conn: int
    t_ns: int
    raw: bytes


class _Salvage(NamedTuple):
    conns: dict[int, tuple[str, str, str]]  # id -> (topic, msgtype, message definition)
    counts: Counter[int]  # messages per connection id
    msgs: list[_Salvaged]  # messages of the kept topic, in file order
    stop: str  # where and why reading stopped; "" if the file ended cleanly


def _ros1_salvage(path: Path, keep_topic: str | None = None) -> _Salvage:
    """Messages of a ROS1 bag read chunk by chunk, without its index (memory-mapped).

    Counts the messages of every connection and keeps the raw messages of ``keep_topic`` only.
    A chunk whose recorded size is missing (recording killed mid-chunk: rosbag writes the size
    when it closes the chunk) or runs past the end of the file is read as far as its
    uncompressed message records are complete, like ``rosbag reindex``.
    """
    import bz2
    import mmap

    with path.open("rb") as fh:
        try:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # empty file
            mm = None
        if mm is None or mm[: len(_ROS1_MAGIC)] != _ROS1_MAGIC:
            if mm is not None:
                mm.close()
            raise InputError(f"{str(path)!r} does not start with the ROS1 magic '#ROSBAG V2.0'.")
        view = memoryview(mm)
        try:
            return _salvage_view(view, keep_topic, bz2.decompress)
        finally:
            # slices still referenced by a traceback keep the map alive: let GC close it then
            with contextlib.suppress(BufferError):
                view.release()
                mm.close()


def _conn_record(h: dict[str, bytes], buf: bytes | memoryview) -> tuple[int, tuple[str, str, str]]:
    c = _parse_header(buf)
    return int.from_bytes(h["conn"], "little"), (
        h.get("topic", c.get("topic", b"")).decode(),
        _norm_type(c.get("type", b"").decode()),
        c.get("message_definition", b"").decode(errors="replace"),
    )


def _salvage_view(view: memoryview, keep_topic: str | None, bz2_decompress: Any) -> _Salvage:
    conns: dict[int, tuple[str, str, str]] = {}
    counts: Counter[int] = Counter()
    msgs: list[_Salvaged] = []
    stop = ""
    pos_end = len(_ROS1_MAGIC)

    def inner(buf: bytes | memoryview) -> int:
        end = 0
        for _, h, a, b in _records(buf, 0):
            op = h.get("op", b"\x00")[0]
            if b - a < int.from_bytes(buf[a - 4 : a], "little"):
                break  # record cut by the end of the file
            if op == _OP_CONNECTION:
                cid, info = _conn_record(h, buf[a:b])
                conns[cid] = info
            elif op == _OP_MSGDATA:
                cid = int.from_bytes(h["conn"], "little")
                counts[cid] += 1
                if keep_topic is not None and cid in conns and conns[cid][0] == keep_topic:
                    t = h.get("time", bytes(8))
                    sec, nsec = int.from_bytes(t[:4], "little"), int.from_bytes(t[4:8], "little")
                    msgs.append(_Salvaged(cid, sec * 1_000_000_000 + nsec, bytes(buf[a:b])))
            end = b
        return end

    for off, h, a, b in _records(view, len(_ROS1_MAGIC)):
        op = h.get("op", b"\x00")[0]
        declared = int.from_bytes(view[a - 4 : a], "little")
        complete = b - a == declared and declared > 0
        if op == _OP_CHUNK:
            comp = h.get("compression", b"none").decode()
            if comp not in ("none", "bz2", "lz4"):
                stop = f"the chunk at byte {off} uses the unknown compression {comp!r}"
                break
            if complete:
                try:
                    if comp == "none":
                        raw: bytes | memoryview = view[a:b]
                    elif comp == "bz2":
                        raw = bz2_decompress(view[a:b])
                    else:
                        from lz4.frame import decompress as lz4_decompress

                        raw = lz4_decompress(bytes(view[a:b]))
                except Exception as exc:
                    stop = f"the chunk at byte {off} cannot be decompressed ({exc})"
                    break
                inner(raw)
            elif comp == "none":
                end = inner(view[a:])
                stop = f"the last chunk (byte {off}) is incomplete; read up to byte {a + end}"
                break
            else:
                stop = f"the {comp}-compressed chunk at byte {off} is cut by the end of the file"
                break
        elif b - a != declared:
            stop = f"the file ends inside a record at byte {off}"
            break
        elif op == _OP_CONNECTION:
            cid, info = _conn_record(h, view[a:b])
            conns.setdefault(cid, info)
        pos_end = b
    else:
        if pos_end < len(view):
            stop = f"the file ends inside a record at byte {pos_end}"
    return _Salvage(conns, counts, msgs, stop)


# --------------------------------------------------------------------------------------------
# LaserScan
# --------------------------------------------------------------------------------------------


def laserscan_from_msg(msg: Any, time: float) -> LaserScan:
    """A :class:`LaserScan` from a decoded ``sensor_msgs/LaserScan`` message.

    ``intensities`` are kept when they have one value per beam, dropped otherwise (many
    drivers publish an empty array). Raises InputError on invalid geometry.
    """
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    inten = np.asarray(msg.intensities, dtype=np.float64)
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
# Odometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class OdometryLog:
    """``nav_msgs/Odometry`` messages as arrays, sorted by time.

    Attributes
    ----------
    times : ndarray (N,), seconds
    poses : ndarray (N, 3)
        x, y (m) and yaw (rad, in (-pi, pi]) of ``child_frame`` in ``frame``.
    z : ndarray (N,), metres
    quaternions : ndarray (N, 4)
        Full orientation ``(qx, qy, qz, qw)``.
    twists : ndarray (N, 3)
        Forward and lateral speed (m/s) and yaw rate (rad/s), in ``child_frame``.
    pose_cov : ndarray (N, 3, 3)
        Covariance over (x, y, yaw) taken from the 6x6 ROS covariance (rows/cols 0, 1, 5).
    frame, child_frame : str
    """

    times: FloatArray
    poses: FloatArray
    z: FloatArray
    quaternions: FloatArray
    twists: FloatArray
    pose_cov: FloatArray
    frame: str
    child_frame: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def trajectory(self) -> Trajectory:
        """The poses as a :class:`Trajectory` (later duplicates of a time stamp dropped)."""
        keep = np.concatenate(([True], np.diff(self.times) > 0))
        return Trajectory(self.times[keep], self.poses[keep], frame=self.frame)


def _sorted(times: FloatArray, *arrays: NDArray[Any]) -> list[NDArray[Any]]:
    order = np.argsort(times, kind="stable")
    return [times[order], *(a[order] for a in arrays)]


def read_odometry(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> OdometryLog:
    """Read every ``nav_msgs/Odometry`` message of a topic into an :class:`OdometryLog`.

    Messages with a NaN/inf or zero-quaternion pose are skipped and recorded.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Returns
    -------
    OdometryLog
        Sorted by ``header.stamp``; yaw by the z-y-x (ROS tf) convention.

    Raises
    ------
    InputError
        Bag unreadable, topic missing or ambiguous, or no usable message.
    """
    rows: list[list[float]] = []
    covs: list[NDArray[np.float64]] = []
    frame = child = ""
    for m in _checked(_iter_messages(path, ODOMETRY, topic), path, skipped):
        msg = m.msg
        try:
            pos, q = msg.pose.pose.position, msg.pose.pose.orientation
            lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
            row = [
                _stamp(msg.header, m.bag_time),
                pos.x,
                pos.y,
                pos.z,
                q.x,
                q.y,
                q.z,
                q.w,
                lin.x,
                lin.y,
                ang.z,
            ]
            cov6 = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
        except (AttributeError, TypeError, ValueError) as exc:
            _skip(skipped, path, m, f"Odometry message {m.seq} is malformed: {exc}")
            continue
        vals = np.asarray(row, dtype=np.float64)
        if not np.all(np.isfinite(vals[:8])) or not np.linalg.norm(vals[4:8]) > 0:
            _skip(skipped, path, m, f"Odometry message {m.seq} has a NaN/inf or zero pose")
            continue
        rows.append(row)
        covs.append(cov6[np.ix_([0, 1, 5], [0, 1, 5])])
        frame = frame or str(msg.header.frame_id)
        child = child or str(msg.child_frame_id)
    if not rows:
        raise InputError(f"ROS bag {str(path)!r} holds no usable nav_msgs/Odometry message.")
    a = np.asarray(rows)
    t, a, cov = _sorted(a[:, 0], a, np.asarray(covs))
    yaw = yaw_from_quaternion(a[:, 4:8])
    return OdometryLog(
        times=t,
        poses=np.column_stack((a[:, 1], a[:, 2], yaw)),
        z=a[:, 3],
        quaternions=a[:, 4:8],
        twists=a[:, 8:11],
        pose_cov=cov,
        frame=frame or "odom",
        child_frame=child or "base_link",
    )


# --------------------------------------------------------------------------------------------
# IMU
# --------------------------------------------------------------------------------------------


def roll_pitch_from_quaternion(q: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Roll and pitch (rad) of quaternions ``(qx, qy, qz, qw)`` (N, 4), z-y-x Euler (ROS tf).

    roll = atan2(2 (w x + y z), 1 - 2 (x^2 + y^2)); pitch = asin(2 (w y - z x)).
    """
    qa = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    qa = qa / np.linalg.norm(qa, axis=1, keepdims=True)
    x, y, z, w = qa.T
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    return roll, pitch


def roll_pitch_from_acceleration(acc: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Roll and pitch (rad) from accelerometer specific force (N, 3), valid when the sensor
    is not accelerating (gravity dominates).

    A level sensor reads (0, 0, +g). With the z-y-x convention the body-frame gravity reading
    is g (-sin p, sin r cos p, cos r cos p), hence roll = atan2(a_y, a_z) and
    pitch = atan2(-a_x, hypot(a_y, a_z)).
    """
    a = np.asarray(acc, dtype=np.float64).reshape(-1, 3)
    roll = np.arctan2(a[:, 1], a[:, 2])
    pitch = np.arctan2(-a[:, 0], np.hypot(a[:, 1], a[:, 2]))
    return roll, pitch


@dataclass(frozen=True, eq=False)
class ImuLog:
    """``sensor_msgs/Imu`` messages as arrays, sorted by time.

    Attributes
    ----------
    times : ndarray (N,), seconds
    roll, pitch : ndarray (N,), radians
        From the orientation quaternion when the message has one, else from the
        accelerometer (see :func:`roll_pitch_from_acceleration`); ``from_orientation`` says which.
    yaw : ndarray (N,), radians; NaN where the message had no orientation
    angular_velocity : ndarray (N, 3), rad/s
    linear_acceleration : ndarray (N, 3), m/s^2
    from_orientation : ndarray (N,) of bool
    frame : str
    """

    times: FloatArray
    roll: FloatArray
    pitch: FloatArray
    yaw: FloatArray
    angular_velocity: FloatArray
    linear_acceleration: FloatArray
    from_orientation: NDArray[np.bool_]
    frame: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    def tilt_at(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Roll and pitch (rad) linearly interpolated at ``times`` (held at the ends)."""
        tq = np.asarray(times, dtype=np.float64)
        return np.interp(tq, self.times, self.roll), np.interp(tq, self.times, self.pitch)


def read_imu(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> ImuLog:
    """Read every ``sensor_msgs/Imu`` message of a topic into an :class:`ImuLog`.

    ROS marks "no orientation" with ``orientation_covariance[0] == -1``; those messages (and
    any with a zero/NaN quaternion) take roll and pitch from the accelerometer instead.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Returns
    -------
    ImuLog
        Sorted by time; ``from_orientation`` tells which source gave roll and pitch.

    Raises
    ------
    InputError
        Bag unreadable, topic missing or ambiguous, or no usable message.
    """
    rows: list[list[float]] = []
    has_q: list[bool] = []
    frame = ""
    for m in _checked(_iter_messages(path, IMU, topic), path, skipped):
        msg = m.msg
        try:
            q, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
            row = [_stamp(msg.header, m.bag_time), q.x, q.y, q.z, q.w, w.x, w.y, w.z, a.x, a.y]
            row.append(a.z)
            ocov0 = float(np.asarray(msg.orientation_covariance, dtype=np.float64)[0])
        except (AttributeError, TypeError, ValueError, IndexError) as exc:
            _skip(skipped, path, m, f"Imu message {m.seq} is malformed: {exc}")
            continue
        vals = np.asarray(row)
        qok = (
            ocov0 != -1.0
            and bool(np.all(np.isfinite(vals[1:5])))
            and (float(np.linalg.norm(vals[1:5])) > 0)
        )
        if not qok and not np.all(np.isfinite(vals[8:11])):
            _skip(skipped, path, m, f"Imu message {m.seq} has neither orientation nor gravity")
            continue
        rows.append(row)
        has_q.append(qok)
        frame = frame or str(msg.header.frame_id)
    if not rows:
        raise InputError(f"ROS bag {str(path)!r} holds no usable sensor_msgs/Imu message.")
    t, a, hq = _sorted(np.asarray(rows)[:, 0], np.asarray(rows), np.asarray(has_q))
    quat = np.where(hq[:, None], a[:, 1:5], np.array([0.0, 0.0, 0.0, 1.0]))
    r_q, p_q = roll_pitch_from_quaternion(quat)
    r_a, p_a = roll_pitch_from_acceleration(a[:, 8:11])
    yaw = np.where(hq, yaw_from_quaternion(quat), np.nan)
    return ImuLog(
        times=t,
        roll=np.where(hq, r_q, r_a),
        pitch=np.where(hq, p_q, p_a),
        yaw=yaw,
        angular_velocity=a[:, 5:8],
        linear_acceleration=a[:, 8:11],
        from_orientation=hq.astype(bool),
        frame=frame or "imu",
    )


# --------------------------------------------------------------------------------------------
# NavSatFix
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class GnssLog:
    """``sensor_msgs/NavSatFix`` messages as arrays, sorted by time.

    Attributes
    ----------
    times : ndarray (N,), seconds
    lat, lon : ndarray (N,), degrees (WGS84); alt : ndarray (N,), metres
    status : ndarray (N,) of int
        ROS NavSatStatus: -1 no fix, 0 fix, 1 SBAS-augmented, 2 ground-based augmentation (RTK).
    cov : ndarray (N, 3, 3), m^2, east-north-up
    cov_type : ndarray (N,) of int (0 unknown, 1 approximated, 2 diagonal known, 3 known)
    frame : str
    """

    times: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt: FloatArray
    status: NDArray[np.int64]
    cov: FloatArray
    cov_type: NDArray[np.int64]
    frame: str

    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Fixes with status >= 0 and finite latitude/longitude."""
        return (self.status >= 0) & np.isfinite(self.lat) & np.isfinite(self.lon)

    def to_local(self, origin_lonlat: tuple[float, float] | None = None) -> FloatArray:
        """East-north metres (N, 2) around ``origin_lonlat`` (default: the first valid fix),
        by the tangent-plane approximation of :func:`stemmap.io.maps.lonlat_to_local`."""
        if origin_lonlat is None:
            v = np.flatnonzero(self.valid)
            if v.size == 0:
                raise InputError("the GNSS log has no valid fix to use as the local origin.")
            origin_lonlat = (float(self.lon[v[0]]), float(self.lat[v[0]]))
        return lonlat_to_local(self.lon, self.lat, origin_lonlat)


def read_navsatfix(
    path: PathLike, topic: str | None = None, *, skipped: list[SkippedFrame] | None = None
) -> GnssLog:
    """Read every ``sensor_msgs/NavSatFix`` message of a topic into a :class:`GnssLog`.

    Messages without a fix (status -1, or NaN position as some drivers send) are kept with
    their status so that gaps stay visible; use :attr:`GnssLog.valid` to filter.

    Parameters
    ----------
    path : str or PathLike
        ROS1 ``.bag``, ROS2 bag folder, or ROS2 ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Topic name; default: the only topic of this message type in the bag.
    skipped : list of SkippedFrame, optional
        Receives one entry per message that could not be used (also logged as a warning).

    Returns
    -------
    GnssLog
        Sorted by time; degrees, metres, ENU covariance in m^2.

    Raises
    ------
    InputError
        Bag unreadable, topic missing or ambiguous, or no message at all.
    """
    rows: list[list[float]] = []
    covs: list[NDArray[np.float64]] = []
    frame = ""
    for m in _checked(_iter_messages(path, NAVSATFIX, topic), path, skipped):
        msg = m.msg
        try:
            row = [
                _stamp(msg.header, m.bag_time),
                float(msg.latitude),
                float(msg.longitude),
                float(msg.altitude),
                int(msg.status.status),
                int(msg.position_covariance_type),
            ]
            cov = np.asarray(msg.position_covariance, dtype=np.float64).reshape(3, 3)
        except (AttributeError, TypeError, ValueError) as exc:
            _skip(skipped, path, m, f"NavSatFix message {m.seq} is malformed: {exc}")
            continue
        rows.append(row)
        covs.append(cov)
        frame = frame or str(msg.header.frame_id)
    if not rows:
        raise InputError(f"ROS bag {str(path)!r} holds no usable sensor_msgs/NavSatFix message.")
    a = np.asarray(rows)
    t, a, cov = _sorted(a[:, 0], a, np.asarray(covs))
    return GnssLog(
        times=t,
        lat=a[:, 1],
        lon=a[:, 2],
        alt=a[:, 3],
        status=a[:, 4].astype(np.int64),
        cov=cov,
        cov_type=a[:, 5].astype(np.int64),
        frame=frame or "gps",
    )


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
    xyz = np.column_stack([recs[c].astype(np.float64) for c in ("x", "y", "z")])
    keep = np.all(np.isfinite(xyz), axis=1) if skip_nans else np.ones(n, dtype=bool)
    extra = {}
    for c in names:
        if c in ("x", "y", "z"):
            continue
        col = recs[c]
        extra[c] = col[keep].astype(col.dtype.newbyteorder("="))
    return PointCloud(xyz[keep], time=time, frame=frame, fields=extra)


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

    Returns
    -------
    Path
        The path written (with ``.bag`` added for ROS1 if it was missing).

    Raises
    ------
    ConfigError
        For an unknown ``ros`` version or ``storage``.
    """
    import os
    import shutil
    import tempfile

    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    if ros not in (1, 2):
        raise ConfigError(f"ros must be 1 or 2, got {ros!r}.")
    if storage not in ("sqlite3", "mcap"):
        raise ConfigError(f"storage must be 'sqlite3' or 'mcap', got {storage!r}.")
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
        else:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer2(tmp, version=9, storage_plugin=plugin)
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
