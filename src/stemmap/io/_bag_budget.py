"""Memory bounds for the compressed chunks of ROS 1 bags (:mod:`stemmap.io.rosbag`).

A ROS 1 bag stores its messages in chunks, each optionally compressed with bz2 or lz4, and a
chunk is decompressed whole before its first message is read (by rosbags, and by
:mod:`stemmap.io._bag_salvage` when the index is missing). bz2 expands a run of equal bytes
~10^5-10^6:1 and lz4 ~250:1, so a small file can ask for gigabytes:

* honestly: the chunk record's header announces the uncompressed ``size`` (a uint32: up to
  4.29 GB a chunk); :func:`check_ros1_chunks` compares every chunk's announced size with the
  read budget (:mod:`stemmap.io._budget`, ``STEMMAP_MAX_READ_GB``) before a message is read;
* dishonestly: the data expand past the announced size. :func:`bounded_decompress` stops at
  the announced size + 1 byte and reports the chunk as damaged, so nothing beyond what the
  budget admitted is allocated. rosbags' chunk table is given this bounded decompressor
  (:func:`bound_reader_chunks`).

ROS 2 bags compressed with zstd (message or file mode) and MCAP files with compressed chunks:
:mod:`stemmap.io._bag2_budget` (docs/reliability.md, "Read budget").
"""

from __future__ import annotations

import bz2
import contextlib
import io
import mmap
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from stemmap.errors import InputError
from stemmap.io._bag_salvage import _OP_CHUNK, _ROS1_MAGIC, _records
from stemmap.io._budget import check_read_budget, human_bytes

#: Bytes of memory reading a chunk takes per byte of its uncompressed size, measured
#: (docs/reliability.md, "Memory per byte of a bag chunk"): LaserScans read by ``read_scans``
#: (what ``stemmap detect`` / ``map`` do) peak at 4.0-4.2 x on every path (ROS 1 none / bz2 /
#: lz4, MCAP zstd / lz4, a ROS 2 zstd message), one scan at a time (``iter_laser_scans``)
#: 1.6-3.0 x; a chunk that is one PointCloud2 message (``read_pointclouds``) 5.9 x (x, y, z,
#: intensity) and 6.35 x (x, y, z only: the chunk, rosbags' copy of the message, its points
#: in float64 and the PointCloud's copy of them). 7: the largest + 10 %.
CHUNK_READ_FACTOR = 7


class ChunkSize(NamedTuple):
    """One chunk record of a ROS 1 bag: where it starts, how it is stored, its sizes."""

    offset: int
    compression: str
    stored: int  # bytes of (compressed) data in the file
    size: int  # uncompressed bytes, as the chunk header announces them


def ros1_chunks(path: Path) -> list[ChunkSize]:
    """The chunk records of a ROS 1 bag, in file order, from their headers alone (the file is
    memory-mapped and only record headers are read). Stops at the first record that is cut
    or damaged, as the salvage does; a file that is not a ROS 1 bag gives []."""
    out: list[ChunkSize] = []
    with path.open("rb") as fh:
        try:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # empty file
            return out
        view = memoryview(mm)
        try:
            if view[: len(_ROS1_MAGIC)] != _ROS1_MAGIC:
                return out
            for off, header, a, b in _records(view, len(_ROS1_MAGIC)):
                if header.get("op", b"\x00")[:1] != bytes([_OP_CHUNK]):
                    continue
                comp = header.get("compression", b"none").decode("latin-1")
                size = int.from_bytes(header.get("size", b"")[:4], "little")
                out.append(ChunkSize(off, comp, b - a, size))
        finally:
            view.release()
            with contextlib.suppress(BufferError):
                mm.close()
    return out


def check_ros1_chunks(path: Path, chunks: list[ChunkSize] | None = None) -> list[ChunkSize]:
    """Refuse a ROS 1 bag whose largest chunk would take more than the read budget to read
    (``CHUNK_READ_FACTOR`` x its announced uncompressed size + its stored bytes).

    Returns the chunk table (read here when not given).

    Raises
    ------
    InputError
        Naming the bag, the chunk, its sizes, the limit and how to raise it.
    """
    table = ros1_chunks(path) if chunks is None else chunks
    return check_largest_chunk(table, path, "ROS bag")


def check_largest_chunk(table: list[ChunkSize], path: Path, what: str) -> list[ChunkSize]:
    """Refuse ``path`` (a ``what``: "ROS bag", "MCAP file") when the largest chunk of its
    ``table`` would take more than the read budget to read (its stored bytes +
    ``CHUNK_READ_FACTOR`` x its announced size: a chunk is decompressed whole). Returns
    ``table``."""
    if not table:
        return table
    big = max(table, key=lambda c: c.stored + CHUNK_READ_FACTOR * c.size)
    need = big.stored + CHUNK_READ_FACTOR * big.size
    kind = "uncompressed" if big.compression == "none" else f"{big.compression}-compressed"
    check_read_budget(
        need,
        path,
        what,
        f"its {kind} chunk at byte {big.offset:,} holds {human_bytes(big.size)} of messages "
        f"({human_bytes(big.stored)} in the file), ~{human_bytes(need)} to read (a chunk is "
        "decompressed whole)",
    )
    return table


def bounded_decompress(compression: str, data: bytes | memoryview, size: int, where: str) -> bytes:
    """Decompress a bz2 / lz4 chunk to at most ``size`` bytes (its header's announcement).

    The output is built in one buffer, 1 MB at a time (:func:`drain`): a one-shot
    ``decompress`` holds its output twice at the end (python-lz4 copies its buffer into the
    returned bytes, bz2 joins its blocks), which doubled the memory a large chunk takes.

    Raises
    ------
    InputError
        If the data expand past ``size`` (``where`` names the chunk), before more than
        ``size`` + 1 MB are allocated.
    """
    d: Any
    if compression == "bz2":
        d = bz2.BZ2Decompressor()
    elif compression == "lz4":
        from lz4.frame import LZ4FrameDecompressor

        d = LZ4FrameDecompressor()
    else:
        raise InputError(f"{where} uses the unknown compression {compression!r}.")
    sink = io.BytesIO()
    if not drain(d, bytes(data), size, sink):
        raise InputError(
            f"{where} decompresses past the {size:,} bytes its header announces: the file is "
            "damaged"
        )
    return sink.getvalue()


#: Bytes decompressed per call by :func:`drain`: a bomb stops within this much of its limit.
STEP_BYTES = 1 << 20


def drain(d: Any, data: bytes, limit: int, sink: io.BytesIO) -> bool:
    """Feed ``data`` to the decompressor ``d`` (bz2 / lz4 / zstd, their ``decompress(data,
    max_length)`` protocol) and write its output to ``sink`` in steps of :data:`STEP_BYTES`,
    until its stream ends (``d.eof``) or the data run out. False (and nothing more is
    decompressed) once ``sink`` holds more than ``limit`` bytes.

    ``sink`` is a ``BytesIO``: it grows its one buffer in place (``realloc``) and
    ``getvalue()`` returns that buffer without a copy, so the output is in memory once.
    Raises what ``d.decompress`` raises on damaged data."""
    feed = data
    while True:
        piece = d.decompress(feed, max_length=min(limit + 1 - sink.tell(), STEP_BYTES))
        feed = b""
        sink.write(piece)
        if sink.tell() > limit:
            return False
        if d.eof or d.needs_input:  # needs_input: the data end inside the stream
            return True


def bound_reader_chunks(reader: Any, path: Path, chunks: list[ChunkSize]) -> None:
    """Give every compressed chunk of an open rosbags ROS 1 reader (``AnyReader``) a
    decompressor bounded by the chunk's announced size. rosbags keeps its chunk table as
    ``Reader.chunks`` ({offset: Chunk(datasize, datapos, decompressor)}); if a later rosbags
    stores it otherwise, the budget check of :func:`check_ros1_chunks` still applies."""
    sizes = {c.offset: c for c in chunks if c.compression in ("bz2", "lz4")}
    for r in getattr(reader, "readers", ()):
        table = getattr(r, "chunks", None)
        if not isinstance(table, dict):
            continue
        for pos, chunk in list(table.items()):
            c = sizes.get(pos)
            if c is not None and hasattr(chunk, "_replace"):
                table[pos] = chunk._replace(decompressor=_bounded(c, path))


def _bounded(c: ChunkSize, path: Path) -> Callable[[bytes], bytes]:
    where = f"the {c.compression}-compressed chunk at byte {c.offset:,} of {str(path)!r}"
    return lambda data: bounded_decompress(c.compression, data, c.size, where)
