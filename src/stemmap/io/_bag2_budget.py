"""Memory bounds for ROS 2 bags and MCAP files (:mod:`stemmap.io.rosbag`); ROS 1 bags:
:mod:`stemmap.io._bag_budget`.

rosbags decompresses three things stemmap does not see being decompressed, each whole and with
no limit: zstd expands a run of equal bytes ~10^4-10^5:1 and lz4 ~250:1, so a small file can
ask for gigabytes.

* **MCAP chunks** (zstd or lz4; ``.mcap`` files, ROS 2 bags with mcap storage): a chunk record
  announces its ``uncompressed_size`` (a uint64) and rosbags decompresses it whole, then
  compares. :func:`check_mcap_chunks` reads every chunk record's header (and the summary's
  chunk indexes) and compares the largest chunk with the read budget before anything is
  decompressed. The decompression itself (rosbags' ``storage_mcap.DECOMPRESSORS``, looked up
  on every chunk) is replaced by :func:`inflate_bounded` to at most the announced size + 1
  byte (:func:`install_bounded_codecs`): a chunk whose data expand past its announcement is
  reported as damage before more is allocated, one announcing more than the budget (an index
  that disagrees with its chunk) is refused.
* **ROS 2 message compression** (``compression_mode: message``): every message is one zstd
  frame, decompressed whole. Nothing announces its size except the frame header, which may
  leave it out. rosbags' ``zstd.decompress`` in ``rosbag2.reader`` is replaced by one that
  refuses a frame announcing more than the budget / :data:`CHUNK_READ_FACTOR` and stops
  decompressing at that size otherwise.
* **ROS 2 file compression** (``compression_mode: file``): rosbags inflates every storage file
  into a temporary folder when the bag is opened (streamed: memory is bounded, the disk is
  not). :func:`check_ros2_files` refuses a bag whose zstd frame headers announce more than the
  temporary folder's free space (less :data:`DISK_MARGIN_BYTES`), and the stream rosbags reads
  (``zstd.open``) stops at that size.

Once inflated, a file-compressed bag's sqlite3 database's largest message
(:func:`check_sqlite_messages`, from ``length(data)``: sqlite reads a blob's length without
its content) is compared with the budget: rosbags reads a message whole.

The replacements are installed once into rosbags' modules (their names are looked up when a
bag is read, so there is no per-reader hook as for ROS 1); they return what rosbags' own code
returns for every file that decompresses to its announced size, so a legitimate bag reads
identically. If a later rosbags moves these names, :func:`install_bounded_codecs` does nothing
and the header checks still apply.
"""

from __future__ import annotations

import io
import mmap
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from stemmap.errors import InputError
from stemmap.io._bag_budget import CHUNK_READ_FACTOR, ChunkSize, check_largest_chunk, drain
from stemmap.io._budget import (
    BUDGET_ENV,
    ReadLimitError,
    check_read_budget,
    human_bytes,
    over_read_budget,
    read_budget,
    read_limit_text,
)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_CHUNK, _OP_CHUNK_INDEX = 0x02, 0x06, 0x08

#: Free space left on the disk when a file-compressed ROS 2 bag is inflated (1 GB).
DISK_MARGIN_BYTES = 10**9


# --------------------------------------------------------------------------------------------
# bounded decompression
# --------------------------------------------------------------------------------------------


_ZSTD: list[Any] = []


def _zstd() -> Any:
    """The zstd module rosbags uses (``compression.zstd`` from Python 3.14, else
    ``backports.zstd``, a dependency of rosbags); looked up once (a failed import searches
    sys.path every time, ~0.15 ms: a bag has thousands of messages)."""
    if not _ZSTD:
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        _ZSTD.append(zstd)
    return _ZSTD[0]


def _decompressor(compression: str) -> Any:
    if compression == "zstd":
        return _zstd().ZstdDecompressor()
    if compression == "lz4":
        from lz4.frame import LZ4FrameDecompressor

        return LZ4FrameDecompressor()
    raise InputError(f"unknown compression {compression!r}")


def inflate_bounded(compression: str, data: bytes | memoryview, limit: int) -> bytes | None:
    """Decompress ``data`` (zstd or lz4 frames, one after another as ``zstd.decompress`` and
    ``lz4.frame.decompress`` read them) to at most ``limit`` bytes.

    Returns the bytes, or None if the data expand past ``limit`` (found out in steps of 1 MB,
    so at most ``limit`` + ~2 MB are allocated).

    Raises
    ------
    InputError
        If the data end inside a frame or are not frames of this compression.
    """
    sink = io.BytesIO()  # one buffer, grown in place: the output is in memory once
    rest = bytes(data)
    while rest:
        d = _decompressor(compression)
        try:
            within = drain(d, rest, limit, sink)
        except Exception as exc:  # zstd.ZstdError / RuntimeError (lz4): damaged data
            raise InputError(f"cannot {compression}-decompress the data ({exc})") from exc
        if not within:
            return None
        if not d.eof:
            raise InputError(f"the {compression} data end inside a frame")
        rest = d.unused_data
    return sink.getvalue()


def _mcap_inflate(compression: str, data: bytes, size: int) -> bytes:
    """rosbags' MCAP chunk decompressor, bounded: ``size`` is the chunk's announcement."""
    need = len(data) + CHUNK_READ_FACTOR * size
    if over_read_budget(need):
        raise ReadLimitError(
            read_limit_text(
                need,
                f"a {compression}-compressed MCAP chunk holds {human_bytes(size)} of messages "
                f"({human_bytes(len(data))} in the file), ~{human_bytes(need)} to read",
            )
        )
    out = inflate_bounded(compression, data, size)
    if out is None:
        raise InputError(
            f"a {compression}-compressed MCAP chunk decompresses past the {size:,} bytes its "
            "header announces: the file is damaged"
        )
    return out


_LIMIT_CACHE: list[float] = []  # [time it was read, message limit]


def message_limit() -> int:
    """The largest decompressed message the read budget admits: 1 / ``CHUNK_READ_FACTOR`` of
    it (the message, its decoded float64 arrays, their stack). Read again at most once a
    second (it reads /proc/meminfo; a bag has thousands of messages)."""
    if os.environ.get(BUDGET_ENV, "").strip():  # no /proc read: not cached
        return int(min(read_budget()[0] / CHUNK_READ_FACTOR, 1 << 62))
    now = time.monotonic()
    if not _LIMIT_CACHE or now - _LIMIT_CACHE[0] > 1:
        _LIMIT_CACHE[:] = [now, min(read_budget()[0] / CHUNK_READ_FACTOR, 1 << 62)]
    return int(_LIMIT_CACHE[1])


def inflate_message(data: bytes) -> bytes:
    """rosbags' ROS 2 per-message ``zstd.decompress``, bounded by :func:`message_limit`.

    Raises
    ------
    ReadLimitError
        If the frame header announces more, or the data expand past it.
    """
    try:
        told = _zstd().get_frame_info(data).decompressed_size
    except Exception:  # a damaged header: the decompressor reports it
        told = None
    limit = message_limit()
    if told is not None and told > limit:
        need = CHUNK_READ_FACTOR * told
        raise ReadLimitError(
            read_limit_text(
                need,
                f"a zstd-compressed message announces {human_bytes(told)} ({human_bytes(len(data))}"
                f" in the file), ~{human_bytes(need)} to read",
            )
        )
    out = inflate_bounded("zstd", data, limit)
    if out is None:
        raise ReadLimitError(
            read_limit_text(
                CHUNK_READ_FACTOR * (limit + 1),
                f"a zstd-compressed message ({human_bytes(len(data))} in the file) decompresses "
                f"past {human_bytes(limit)}, the largest message the limit admits (1/"
                f"{CHUNK_READ_FACTOR} of it: the message, its decoded arrays and their stack)",
            )
        )
    return out


class _CappedStream:
    """A ``zstd.open(..., 'rb')`` stream that raises once more than ``cap`` bytes came out."""

    def __init__(self, inner: Any, cap: int, where: str) -> None:
        self._inner, self._cap, self._where, self._n = inner, cap, where, 0

    def _count(self, k: int) -> None:
        self._n += k
        if self._n > self._cap:
            raise ReadLimitError(
                f"{self._where} inflates past {human_bytes(self._cap)}, what the temporary folder "
                f"{tempfile.gettempdir()!r} can take (its free space less "
                f"{human_bytes(DISK_MARGIN_BYTES)}; rosbags inflates a file-compressed ROS 2 bag "
                "there before reading it). If the bag is genuine, point TMPDIR at a disk with "
                "more room."
            )

    def read(self, size: int = -1) -> bytes:
        want = self._cap + 1 - self._n
        out: bytes = self._inner.read(want if size is None or size < 0 else min(size, want))
        self._count(len(out))
        return out

    def readinto(self, buf: Any) -> int:
        k: int = self._inner.readinto(buf)
        self._count(k)
        return k

    def close(self) -> None:
        self._inner.close()

    def __enter__(self) -> _CappedStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def disk_room() -> int:
    """Bytes the temporary folder may take before the disk is left with less than
    :data:`DISK_MARGIN_BYTES`."""
    free = shutil.disk_usage(tempfile.gettempdir()).free
    return max(int(free) - DISK_MARGIN_BYTES, 0)


class _BoundedZstd:
    """What ``rosbags.rosbag2.reader`` sees as its ``zstd`` module: ``decompress`` bounded by
    :func:`inflate_message`, ``open`` (file mode) capped at :func:`disk_room`; the rest is the
    real module."""

    def __init__(self, real: Any) -> None:
        self._real = real

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)

    def decompress(self, data: bytes, *args: Any, **kwargs: Any) -> bytes:
        if args or kwargs:  # not how rosbags calls it: leave it alone
            return bytes(self._real.decompress(data, *args, **kwargs))
        return inflate_message(data)

    def open(self, file: Any, mode: str = "rb", *args: Any, **kwargs: Any) -> Any:
        inner = self._real.open(file, mode, *args, **kwargs)
        if "r" not in mode:
            return inner
        name = getattr(file, "name", file)
        return _CappedStream(inner, disk_room(), f"the zstd-compressed file {str(name)!r}")


_INSTALLED: list[bool] = []


def install_bounded_codecs() -> None:
    """Replace rosbags' unbounded MCAP chunk decompressors and ROS 2 zstd (once; see the
    module). Does nothing where rosbags keeps them under other names."""
    if _INSTALLED:
        return
    _INSTALLED.append(True)
    from rosbags.rosbag2 import reader as r2
    from rosbags.rosbag2 import storage_mcap

    table = getattr(storage_mcap, "DECOMPRESSORS", None)
    if isinstance(table, dict):
        for comp in ("zstd", "lz4"):
            if comp in table:
                table[comp] = lambda data, size, c=comp: _mcap_inflate(c, data, size)
    real = getattr(r2, "zstd", None)
    if real is not None and not isinstance(real, _BoundedZstd):
        r2.zstd = _BoundedZstd(real)  # type: ignore[assignment]


# --------------------------------------------------------------------------------------------
# header checks
# --------------------------------------------------------------------------------------------


def mcap_chunks(path: Path) -> list[ChunkSize]:
    """The chunks of an MCAP file from their record headers and the summary's chunk indexes
    (memory-mapped; no chunk is decompressed): ``ChunkSize(offset of the record, compression,
    compressed bytes, announced uncompressed bytes)``, one per chunk record and one per chunk
    index. Stops at the footer or the first record that does not fit; a file that is not MCAP
    gives []."""
    out: list[ChunkSize] = []
    with path.open("rb") as fh:
        try:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # empty file
            return out
        try:
            _scan_mcap(mm, out)
        finally:
            mm.close()
    return out


def _u64(b: Any, at: int) -> int:
    return int.from_bytes(b[at : at + 8], "little")


def _u32(b: Any, at: int) -> int:
    return int.from_bytes(b[at : at + 4], "little")


def _scan_mcap(b: Any, out: list[ChunkSize]) -> None:
    n = len(b)
    if b[:8] != MCAP_MAGIC:
        return
    pos = 8
    while pos + 9 <= n:
        op, length, body = b[pos], _u64(b, pos + 1), pos + 9
        end = body + length
        if end > n or op == _OP_FOOTER:
            return
        if op == _OP_CHUNK and length >= 40:
            usize = _u64(b, body + 16)
            clen = _u32(b, body + 28)
            at = body + 32 + clen
            if at + 8 <= end:
                comp = bytes(b[body + 32 : at]).decode("latin-1") or "none"
                out.append(ChunkSize(pos, comp, _u64(b, at), usize))
        elif op == _OP_CHUNK_INDEX and length >= 40:
            mlen = _u32(b, body + 32)
            at = body + 36 + mlen + 8  # past the message index offsets and their length
            if at + 4 <= end:
                clen = _u32(b, at)
                q = at + 4 + clen
                if q + 16 <= end:
                    comp = bytes(b[at + 4 : q]).decode("latin-1") or "none"
                    out.append(ChunkSize(_u64(b, body + 16), comp, _u64(b, q), _u64(b, q + 8)))
        pos = end


def check_mcap_chunks(path: Path) -> list[ChunkSize]:
    """Refuse an MCAP file whose largest chunk would take more than the read budget to read
    (its compressed bytes + ``CHUNK_READ_FACTOR`` x its announced size: rosbags decompresses
    a chunk whole, then keeps its messages for the time merge). Returns the chunk table.

    Raises
    ------
    ReadLimitError
        Naming the file, the chunk, its sizes, the limit and how to raise it.
    """
    return check_largest_chunk(mcap_chunks(path), path, "MCAP file")


def _zstd_announced(path: Path) -> int | None:
    """The decompressed size a zstd file's first frame header announces (None: not said)."""
    with path.open("rb") as fh:
        head = fh.read(18)  # the longest frame header
    try:
        told = _zstd().get_frame_info(head).decompressed_size
    except Exception:  # not a zstd frame: rosbags reports it when it opens the bag
        return None
    return None if told is None else int(told)


def _ros2_metadata(folder: Path) -> dict[str, Any]:
    from ruamel.yaml import YAML

    try:
        doc = YAML(typ="safe").load((folder / "metadata.yaml").read_text())
        info = doc["rosbag2_bagfile_information"]
    except Exception:  # a damaged metadata.yaml: rosbags says what is wrong when it opens it
        return {}
    return info if isinstance(info, dict) else {}


def check_ros2_files(folder: Path) -> None:
    """Refuse a file-compressed ROS 2 bag whose storage files announce (zstd frame headers)
    more than :func:`disk_room` once inflated. A frame that does not announce its size is
    capped while it is inflated (:class:`_CappedStream`).

    Raises
    ------
    ReadLimitError
        Naming the bag, the sizes and the temporary folder.
    """
    info = _ros2_metadata(folder)
    if str(info.get("compression_mode", "")).lower() != "file":
        return
    total = 0
    for rel in info.get("relative_file_paths") or []:
        f = folder / Path(str(rel)).name
        if f.is_file():
            total += _zstd_announced(f) or 0
    room = disk_room()
    if total > room:
        raise ReadLimitError(
            f"ROS 2 bag {str(folder)!r}: its zstd-compressed storage files announce "
            f"{human_bytes(total)} once inflated, more than the {human_bytes(room)} the temporary "
            f"folder {tempfile.gettempdir()!r} can take (its free space less "
            f"{human_bytes(DISK_MARGIN_BYTES)}), where rosbags inflates a file-compressed bag "
            "before reading it. If the bag is genuine, point TMPDIR at a disk with more room."
        )


def check_sqlite_messages(reader: Any, path: Path) -> None:
    """Refuse an open file-compressed ROS 2 bag whose inflated sqlite3 database holds a message
    larger than the read budget / ``CHUNK_READ_FACTOR``: rosbags reads a message whole before
    it is decoded, and a few kB of zstd can inflate to a database holding a GB-sized message.
    (An uncompressed database is not scanned: its messages are no larger than the file, and
    the query reads every row, the whole file for small messages, at every open.)"""
    for r in getattr(reader, "readers", ()):
        storage = getattr(r, "storage", None)
        if getattr(getattr(storage, "metadata", None), "compression_mode", None) != "file":
            continue
        for s in getattr(storage, "storages", None) or []:
            db = getattr(s, "dbconn", None)
            if db is None:
                continue
            try:
                row = next(iter(db.execute("SELECT max(length(data)) FROM messages")), None)
            except Exception:  # no messages table: rosbags says so when it reads
                continue
            biggest = int(row[0]) if row and row[0] is not None else 0
            if over_read_budget(CHUNK_READ_FACTOR * biggest):
                check_read_budget(
                    CHUNK_READ_FACTOR * biggest,
                    path,
                    "ROS 2 bag",
                    f"its largest message holds {human_bytes(biggest)} once the bag is "
                    f"inflated, ~{human_bytes(CHUNK_READ_FACTOR * biggest)} to read and decode "
                    "(a message is read whole)",
                )


__all__ = [
    "BUDGET_ENV",
    "DISK_MARGIN_BYTES",
    "check_mcap_chunks",
    "check_ros2_files",
    "check_sqlite_messages",
    "inflate_bounded",
    "inflate_message",
    "install_bounded_codecs",
    "mcap_chunks",
]
