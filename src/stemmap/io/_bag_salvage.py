"""ROS1 salvage for :mod:`stemmap.io.rosbag`: read the records and chunks of a ``.bag`` whose index
is missing or damaged (a truncated recording).
"""

from __future__ import annotations

import contextlib
from collections import Counter
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from stemmap.errors import InputError

# --------------------------------------------------------------------------------------------
# ROS1 salvage: read the chunks of a bag whose index is missing or damaged
# --------------------------------------------------------------------------------------------


def _norm_type(msgtype: str) -> str:
    """``sensor_msgs/LaserScan`` and ``sensor_msgs/msg/LaserScan`` -> the latter."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return msgtype


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

    Counts the messages of every connection and keeps the raw messages of ``keep_topic`` only
    (all of them, in ``msgs``: :func:`_ros1_stream` yields them one at a time instead).
    A chunk whose recorded size is missing (recording killed mid-chunk: rosbag writes the size
    when it closes the chunk) or runs past the end of the file is read as far as its
    uncompressed message records are complete, like ``rosbag reindex``.
    """
    gen = _ros1_stream(path, keep_topic)
    msgs: list[_Salvaged] = []
    while True:
        try:
            msgs.append(next(gen))
        except StopIteration as end:
            sv: _Salvage = end.value
            return sv._replace(msgs=msgs)


def _ros1_stream(path: Path, keep_topic: str | None) -> Generator[_Salvaged, None, _Salvage]:
    """:func:`_ros1_salvage` as a generator: yields the raw messages of ``keep_topic`` as their
    chunk is read (one decompressed chunk in memory at a time, as rosbags reads an indexed
    bag), and returns the :class:`_Salvage` (``msgs`` empty) when the file is read."""
    import mmap

    from stemmap.io._bag_budget import bounded_decompress

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
            return (yield from _salvage_view(view, keep_topic, bounded_decompress))
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


def _salvage_view(
    view: memoryview, keep_topic: str | None, decompress: Any
) -> Generator[_Salvaged, None, _Salvage]:
    conns: dict[int, tuple[str, str, str]] = {}
    counts: Counter[int] = Counter()
    stop = ""
    pos_end = len(_ROS1_MAGIC)

    def inner(buf: bytes | memoryview) -> Generator[_Salvaged, None, int]:
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
                    yield _Salvaged(cid, sec * 1_000_000_000 + nsec, bytes(buf[a:b]))
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
                    else:  # to at most the announced size (stemmap.io._bag_budget)
                        size = int.from_bytes(h.get("size", b"")[:4], "little")
                        raw = decompress(comp, view[a:b], size, f"the chunk at byte {off}")
                except Exception as exc:
                    stop = f"the chunk at byte {off} cannot be decompressed ({exc})"
                    break
                yield from inner(raw)
            elif comp == "none":
                end = yield from inner(view[a:])
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
    return _Salvage(conns, counts, [], stop)
