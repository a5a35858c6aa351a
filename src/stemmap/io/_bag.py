"""Bag container for :mod:`stemmap.io.rosbag`: open a ROS1/ROS2 bag, list and choose topics, and
iterate decoded messages (a damaged ROS1 bag is salvaged chunk by chunk, ``_bag_salvage``).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

from stemmap.errors import InputError
from stemmap.io._bag2_budget import (
    check_mcap_chunks,
    check_ros2_files,
    check_sqlite_messages,
    install_bounded_codecs,
)
from stemmap.io._bag_budget import bound_reader_chunks, check_ros1_chunks
from stemmap.io._bag_salvage import _norm_type, _ros1_salvage, _ros1_stream, _Salvage
from stemmap.io._budget import ReadLimitError
from stemmap.io._util import PathLike, SkippedFrame

log = logging.getLogger("stemmap.io.rosbag")

#: File suffixes recognised as bags (ROS1 ``.bag``; ROS2 storage files ``.db3``, ``.mcap``).
BAG_SUFFIXES = (".bag", ".db3", ".mcap")

LASERSCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"

#: sensor_msgs/PointField datatype codes -> numpy type characters.
POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


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
    ROS2 Humble type store. A ROS1 bag's chunks are checked against the read budget and
    decompressed to at most their announced size (:mod:`stemmap.io._bag_budget`); so are an
    MCAP file's chunks and a ROS2 bag's zstd-compressed messages; a file-compressed ROS2 bag
    is inflated to at most the temporary folder's free space, and its largest message then
    checked (:mod:`stemmap.io._bag2_budget`).

    Raises
    ------
    InputError
        If the path does not exist or the bag cannot be opened (truncated, not a bag, ...).
    ReadLimitError
        (an InputError) If reading it would exceed the read budget (``STEMMAP_MAX_READ_GB``).
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
    if store == Stores.ROS2_HUMBLE:  # before rosbags decompresses anything at open
        install_bounded_codecs()
        if p.is_dir():
            check_ros2_files(p)
        for f in sorted(p.glob("*.mcap")) if p.is_dir() else [p]:
            if f.suffix.lower() == ".mcap":
                check_mcap_chunks(f)
    try:
        reader = AnyReader([p], default_typestore=get_typestore(store))
        reader.open()
    except ReadLimitError as exc:  # inflating a file-compressed bag, an MCAP chunk at open
        raise ReadLimitError(f"ROS bag {str(p)!r}: {exc}") from exc
    except Exception as exc:  # rosbags raises many types on damaged files; wrap them all
        raise InputError(
            f"cannot open ROS bag {str(p)!r} ({type(exc).__name__}: {exc}); the file may be "
            "truncated or not a bag."
        ) from exc
    try:
        if p.suffix.lower() == ".bag" and p.is_file():  # chunk sizes: budget, bounded reads
            bound_reader_chunks(reader, p, check_ros1_chunks(p))
        else:
            check_sqlite_messages(reader, p)
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
    topic: str = ""


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
        yield from _decoded(reader, p, conns, msgtype, f"topic {chosen}")


def _decoded(
    reader: Any, path: Path, conns: list[Any], msgtype: str, what: str
) -> Iterator[_Message]:
    """The messages of ``conns`` of an open bag in bag order, decoded (``seq`` counts them).

    A message that cannot be decoded comes back with ``msg`` None and its error; damage or
    truncation met mid-read (rosbags, mcap, sqlite or decompressor exceptions) ends the
    stream with one such message saying the rest is lost; a read-limit refusal is raised,
    naming the bag. ``what`` names the topic(s) in those texts (``"topic /scan"``).
    """
    gen = reader.messages(connections=conns)
    k = 0
    while True:
        try:
            conn, t_ns, raw = next(gen)
        except StopIteration:
            return
        except ReadLimitError as exc:  # a refusal, not damage
            raise ReadLimitError(f"ROS bag {str(path)!r}, {what}, message {k}: {exc}") from exc
        except Exception as exc:  # damaged chunk / truncated file
            rest = "of the topic " if what.startswith("topic ") else ""
            yield _Message(
                k,
                math.nan,
                None,
                f"the bag's data end or are damaged after message {k} of {what} "
                f"({type(exc).__name__}: {exc}); the rest {rest}is lost",
            )
            return
        try:
            # a memoryview: rosbags' CDR decoder slices off the 4-byte header, which copies
            # a bytes message (its arrays view the message either way)
            msg = reader.deserialize(memoryview(raw), conn.msgtype)
        except Exception as exc:
            yield _Message(
                k,
                t_ns * 1e-9,
                None,
                f"message {k} of {what} cannot be decoded as {msgtype} "
                f"({type(exc).__name__}: {exc})",
                conn.topic,
            )
        else:
            yield _Message(k, t_ns * 1e-9, msg, "", conn.topic)
        k += 1


def _salvage_or_raise(path: Path, open_error: InputError, keep_topic: str | None) -> _Salvage:
    check_ros1_chunks(path)  # before a chunk is decompressed (the salvage reads them whole)
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
    store = get_typestore(Stores.ROS1_NOETIC)
    for t, m, definition in first.conns.values():  # non-standard types: the bag's definitions
        if t == chosen and m not in store.types and definition:
            with contextlib.suppress(Exception):
                store.register(get_types_from_msg(definition, m))
    # pass 2: this topic's messages, one at a time as their chunk is read (not the whole topic:
    # compressed chunks can hold many times the file's size)
    gen = _ros1_stream(path, chosen)
    k = 0
    while True:
        try:
            rec = next(gen)
        except StopIteration as end:
            stop = end.value.stop
            break
        except (InputError, OSError, ValueError, KeyError) as exc:  # read once in pass 1
            stop = f"reading it again failed ({type(exc).__name__}: {exc})"
            break
        try:
            msg = store.deserialize_ros1(rec.raw, first.conns[rec.conn][1])
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
    if stop:
        yield _Message(
            k,
            math.nan,
            None,
            f"the bag has no valid index and {stop}; messages of {chosen} after message "
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
