"""Decode every LAS/LAZ tile once: split its points into the buffered chunks that need them.

Without a spatial index, reading a chunk's buffer from a neighbouring LAZ tile means decoding
that whole tile: with chunks the size of the tiles every tile is decoded by nine chunks. The
engine therefore runs in two stages (lidR users do the same with ``catalog_retile``):

1. one task per tile (:func:`stage_tile`) streams the tile once and appends each block's points
   to one raw fragment per overlapping buffered chunk (the file's int32 X, Y, Z after a header
   of its scales and offsets, and the requested extra fields as float64), renamed into place
   when the tile is complete;
2. one task per chunk (:func:`read_staged`) concatenates its fragments in tile order, scaling
   the integers as laspy does (``X * scale + offset``) -- the same points, bit for bit, in the
   same order, as :func:`~stemmap.engine.catalog.read_chunk` would read. Integers halve the
   bytes written and read back (12 instead of 24 a point).

COPC tiles skip the stage: a COPC spatial query decodes only the octree nodes a chunk needs.
Fragments live in ``<work>/stage/<chunk id>/<tile index>.{xyz,<field>}`` and are removed once
their chunk is done.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from stemmap.engine.catalog import Catalog, Chunk
from stemmap.errors import InputError
from stemmap.types import FloatArray

__all__ = ["clear_stage", "laz_selection", "read_staged", "stage_tile", "stage_tile_outcome"]


def _frag(stage: Path, chunk_id: str, tile: int, what: str) -> Path:
    return stage / chunk_id / f"{tile}.{what}"


def stage_tile(
    catalog: Catalog,
    tile: int,
    chunks: Sequence[Chunk],
    stage: str,
    fields: Sequence[str] = (),
    read_points: int = 250_000,
) -> dict[str, int]:
    """Stream tile ``tile`` once and write its points inside each chunk's buffered box.

    Runs on a worker; memory is bounded by ``read_points``. Returns points read per chunk.
    """
    import laspy

    t = catalog.tiles[tile]
    root = Path(stage)
    boxes = [(c.id, c.buffered) for c in chunks]
    groups = _box_groups(boxes)
    cids_of = [cids for _, _, cids in groups]
    split = _Splitter(groups, catalog.unit_scale)
    what = ("xyz", *fields)
    handles: dict[tuple[str, str], IO[bytes]] = {}
    counts = {c.id: 0 for c in chunks}
    # unique per call, not per process: two runs of one stage task (Dask re-runs a task whose
    # result was lost with a worker) never share a temporary file
    tmp_suffix = f".tmp{os.getpid()}-{uuid.uuid4().hex[:12]}"
    head: bytes | None = None
    try:
        for cid, _ in boxes:
            (root / cid).mkdir(parents=True, exist_ok=True)
            for w in what:
                p = _frag(root, cid, tile, w + tmp_suffix)
                handles[(cid, w)] = open(p, "wb")  # noqa: SIM115 - closed in finally
        try:
            with laspy.open(
                t.path,
                laz_backend=_one_thread_laz(),
                decompression_selection=laz_selection(fields),
            ) as rd:
                names = set(rd.header.point_format.dimension_names)
                missing = [f for f in fields if f not in names]
                if missing:
                    raise InputError(f"tile {t.path!r} has no point field {missing[0]!r}.")
                for pts in rd.chunk_iterator(read_points):
                    if len(pts) == 0:
                        continue
                    views = (pts.x, pts.y, pts.z)  # laspy's scaled views of X, Y, Z
                    if head is None:
                        head = _frag_header(views)
                        for cid, _ in boxes:
                            handles[(cid, "xyz")].write(head)
                    elif _frag_header(views) != head:
                        raise InputError(f"tile {t.path!r} changes its scales mid-file.")
                    raw = [_raw(v) for v in views]
                    offs, buf, idx = split.run(views, raw, bool(fields))
                    vals = [np.asarray(pts[f], dtype=np.float64) for f in fields]
                    for g, cids in enumerate(cids_of):
                        a, b = int(offs[g]), int(offs[g + 1])
                        if a == b:
                            continue
                        sel = buf[a:b]  # C-contiguous rows: written as they are
                        got = [v[idx[a:b]] for v in vals]
                        for cid in cids:
                            handles[(cid, "xyz")].write(sel.data)
                            for f, v in zip(fields, got, strict=True):
                                handles[(cid, f)].write(v.data)
                            counts[cid] += b - a
            if head is None:  # no point: the header of an empty fragment
                head = _frag_header(None)
                for cid, _ in boxes:
                    handles[(cid, "xyz")].write(head)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"reading tile {t.path!r} failed: {exc}") from exc
        # closed, not fsynced: fragments are scratch, read by this run's chunk tasks through
        # the page cache (or the shared file system, which close() flushes to) and rewritten
        # by a resumed run (docs/reliability.md, "Scale-out engine")
        for h in handles.values():
            h.close()
        for cid, _ in boxes:
            for w in what:
                try:
                    os.replace(_frag(root, cid, tile, w + tmp_suffix), _frag(root, cid, tile, w))
                except FileNotFoundError:
                    # the chunk finished and the run cleared its folder (`clear_stage`) while
                    # this task -- a re-run of a tile whose result was lost with a killed
                    # worker -- was staging it: nothing needs these points any more
                    if (root / cid).is_dir() and not (root / cid / f"{tile}.{w}").exists():
                        raise
    finally:
        for h in handles.values():
            h.close()
        for cid, _ in boxes:
            for w in what:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(_frag(root, cid, tile, w + tmp_suffix))
    return counts


#: bytes before a staged xyz fragment's points: scale and offset of x, y, z (float64)
_HEAD = 48


def _frag_header(views: Sequence[Any] | None) -> bytes:
    """The scales and offsets of laspy's scaled coordinate views, as a fragment's header."""
    if views is None:
        return np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]).tobytes()
    vals = [float(v.scale) for v in views] + [float(v.offset) for v in views]
    return np.array(vals, dtype=np.float64).tobytes()


def _raw(view: Any) -> NDArray[np.int32]:
    """The stored integers behind a laspy scaled view (what it multiplies by its scale)."""
    a = np.asarray(view.array)
    if a.dtype != np.int32:
        raise InputError(f"unexpected LAS coordinate type {a.dtype}.")
    return a


def _box_groups(
    boxes: Sequence[tuple[str, tuple[float, float, float, float]]],
) -> list[tuple[tuple[float, float], tuple[float, float], list[str]]]:
    """The distinct buffered boxes as ((x0, x1), (y0, y1), chunk ids), grouped by x range:
    chunks on a grid share their x ranges, so a point's x is tested once per range and its
    y only against the boxes of the ranges that hold it."""
    by_x: dict[tuple[float, float], dict[tuple[float, float], list[str]]] = {}
    for cid, bx in boxes:
        by_x.setdefault((bx[0], bx[2]), {}).setdefault((bx[1], bx[3]), []).append(cid)
    return [(xr, yr, cids) for xr, by_y in by_x.items() for yr, cids in by_y.items()]


class _Splitter:
    """Splits LAZ blocks into the box groups of :func:`_box_groups` in two passes of one
    numba kernel (count, then copy), into one buffer reused from block to block: the
    block's raw X, Y, Z rows of each group, in point order."""

    def __init__(self, groups: Sequence[tuple[Any, Any, Any]], unit_scale: float = 1.0) -> None:
        self.unit_scale = float(unit_scale)
        xs = list(dict.fromkeys(xr for xr, _, _ in groups))  # groups are contiguous per x
        self.xr = np.array(xs, dtype=np.float64).reshape(-1, 2)
        self.yr = np.array([yr for _, yr, _ in groups], dtype=np.float64).reshape(-1, 2)
        starts = [0]
        for xr in xs:
            starts.append(starts[-1] + sum(1 for g in groups if g[0] == xr))
        self.ystart = np.array(starts, dtype=np.int64)
        self.buf = np.empty((0, 3), dtype=np.int32)
        self.idx = np.empty(0, dtype=np.int64)

    def run(
        self, views: Sequence[Any], raw: Sequence[NDArray[np.int32]], want_idx: bool
    ) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.int64]]:
        """(offsets, rows, indices): group g's rows are ``rows[offsets[g]:offsets[g + 1]]``
        and ``indices`` their positions in the block (filled only with ``want_idx``)."""
        sc = np.array(
            [float(v.scale) for v in views[:2]]
            + [float(v.offset) for v in views[:2]]
            + [self.unit_scale]
        )
        x, y, z = raw
        offs = np.zeros(self.yr.shape[0] + 1, dtype=np.int64)
        grid = (sc, self.xr, self.ystart, self.yr)
        counts = _into_boxes(x, y, z, *grid, offs, self.buf, self.idx, False, False)
        np.cumsum(counts, out=offs[1:])
        total = int(offs[-1])
        if total > self.buf.shape[0]:
            self.buf = np.empty((total, 3), dtype=np.int32)
            self.idx = np.empty(total if want_idx else 0, dtype=np.int64)
        _into_boxes(x, y, z, *grid, offs, self.buf, self.idx, True, want_idx)
        return offs, self.buf, self.idx


@njit(cache=True)
def _into_boxes(
    xi: NDArray[np.int32],
    yi: NDArray[np.int32],
    zi: NDArray[np.int32],
    sc: FloatArray,
    xr: FloatArray,
    ystart: NDArray[np.int64],
    yr: FloatArray,
    offs: NDArray[np.int64],
    buf: NDArray[np.int32],
    idx: NDArray[np.int64],
    fill: bool,
    want_idx: bool,
) -> NDArray[np.int64]:
    # the points of each box group; with ``fill`` also copied to buf[offs[g]:] (and their
    # positions to idx). x = float64(X) * scale + offset: laspy's scaled coordinate, bit for
    # bit (no fused multiply-add: numba compiles without fastmath), times sc[4], the
    # catalog's metres per file unit (exact when 1); the boxes are closed
    counts = np.zeros(yr.shape[0], dtype=np.int64)
    for k in range(xi.shape[0]):
        x = (float(xi[k]) * sc[0] + sc[2]) * sc[4]
        y = (float(yi[k]) * sc[1] + sc[3]) * sc[4]
        for a in range(xr.shape[0]):
            if x >= xr[a, 0] and x <= xr[a, 1]:
                for g in range(ystart[a], ystart[a + 1]):
                    if y >= yr[g, 0] and y <= yr[g, 1]:
                        if fill:
                            r = offs[g] + counts[g]
                            buf[r, 0] = xi[k]
                            buf[r, 1] = yi[k]
                            buf[r, 2] = zi[k]
                            if want_idx:
                                idx[r] = k
                        counts[g] += 1
    return counts


def _one_thread_laz() -> Any:
    """lazrs' single-threaded LAZ decoder when available (laspy's default decodes on every
    core: in a one-thread Dask worker that oversubscribes the cores the other workers use;
    the decoded points are the same)."""
    from laspy import LazBackend

    return LazBackend.Lazrs if LazBackend.Lazrs.is_available() else None


def laz_selection(fields: Sequence[str] = ()) -> Any:
    """The LAZ layers to decompress for x, y, z and ``fields``: LAS 1.4 point formats 6-10
    store each group of dimensions in its own layer, so the others (intensity,
    classification, flags, scan angle, colours, ...) are skipped undecoded; the decoded
    coordinates are the same. Other formats and LAS files read everything."""
    from laspy import DecompressionSelection as Sel

    sel = Sel.XY_RETURNS_CHANNEL | Sel.Z
    for f in fields:
        if f != "gps_time":
            return Sel.all()
        sel |= Sel.GPS_TIME
    return sel


def stage_tile_outcome(
    catalog: Catalog,
    tile: int,
    chunks: Sequence[Chunk],
    stage: str,
    fields: Sequence[str] = (),
    retries: int = 2,
) -> dict[str, Any]:
    """:func:`stage_tile` as a graph task that never raises: tries ``1 + retries`` times and
    returns ``{"ok": True, "tile", "counts"}`` or ``{"ok": False, "tile", "error"}``, so the
    tasks depending on it (the chunks reading the tile, the pilot region) still run and
    decide: a chunk fails with the tile's error, the pilot reports it unreadable."""
    c0 = task_clock()
    error = ""
    for _ in range(1 + max(retries, 0)):
        try:
            counts = stage_tile(catalog, tile, chunks, stage, fields)
            return {"ok": True, "tile": tile, "counts": counts, **task_spent(c0)}
        except Exception as exc:
            error = f"{type(exc).__name__}: {exc}"
    path = catalog.tiles[tile].path
    return {"ok": False, "tile": tile, "error": f"tile {path}: {error}", **task_spent(c0)}


def task_clock() -> tuple[float, float]:
    """(wall, thread CPU) seconds now: a task's start, for :func:`task_spent`."""
    return time.perf_counter(), time.thread_time()


def task_spent(c0: tuple[float, float]) -> dict[str, float]:
    """Wall and CPU seconds of the calling thread since ``c0`` (``task_s``, ``cpu_s``): what
    a task reports so the client can break a run down by phase (a one-thread worker runs the
    task in this thread; LAZ decoding is single-threaded there)."""
    return {"task_s": time.perf_counter() - c0[0], "cpu_s": time.thread_time() - c0[1]}


def check_staged(outcomes: Sequence[dict[str, Any]]) -> None:
    """Raise the error of the first tile that could not be staged (InputError)."""
    for oc in outcomes:
        if not oc.get("ok", False):
            raise InputError(str(oc.get("error", "a tile could not be read")))


def read_staged(
    stage: str,
    chunk: Chunk,
    tiles: Sequence[int],
    fields: Sequence[str] = (),
    unit_scale: float = 1.0,
) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
    """A chunk's points from the fragments of ``tiles`` (in that order), times
    ``unit_scale`` (metres per file unit)."""
    return _gather(stage, chunk, [(k, True) for k in tiles], fields, None, unit_scale)


def _frag_points(root: Path, chunk: Chunk, k: int) -> int:
    p = _frag(root, chunk.id, k, "xyz")
    try:
        size = p.stat().st_size
    except FileNotFoundError:
        raise InputError(
            f"staged points of tile {k} for chunk {chunk.id} are missing ({p})."
        ) from None
    if size < _HEAD or (size - _HEAD) % 12:
        raise InputError(f"staged points of tile {k} for chunk {chunk.id} are torn ({p}).")
    return (size - _HEAD) // 12


def _read_into(path: Path, out: NDArray[Any], what: str, skip: int = 0) -> bytes:
    """Fill the C-contiguous ``out`` with the bytes of ``path`` after its first ``skip``
    (exactly the rest of the file); returns those ``skip`` bytes."""
    with open(path, "rb") as fh:
        head = fh.read(skip)
        if len(head) != skip:
            raise InputError(f"{what} is torn ({path}).")
        if out.size == 0:  # an empty fragment (a memoryview of no bytes cannot be cast)
            if fh.read(1):
                raise InputError(f"{what} is torn ({path}).")
            return head
        view = out.data.cast("B")
        got = fh.readinto(view)
        if got != view.nbytes or fh.read(1):
            raise InputError(f"{what} is torn ({path}).")
    return head


def _read_xyz(path: Path, out: FloatArray, what: str, unit_scale: float = 1.0) -> None:
    """A staged xyz fragment into the (m, 3) float64 rows ``out``: its integers times their
    scale plus their offset, laspy's ``X * scale + offset`` (the same float64 operations on
    the same values, so the same coordinates bit for bit), times ``unit_scale`` (metres per
    file unit, :class:`~stemmap.io.conventions.CloudConvention`'s product; exact when 1)."""
    raw = np.empty(out.shape, dtype=np.int32)
    head = np.frombuffer(_read_into(path, raw, what, _HEAD), dtype=np.float64)
    _scale_into(raw, head[:3].copy(), head[3:].copy(), float(unit_scale), out)


@njit(cache=True)
def _scale_into(
    raw: NDArray[np.int32], scale: FloatArray, offset: FloatArray, unit: float, out: FloatArray
) -> None:
    # float64(X) * scale, then + offset, then * unit: three roundings, as numpy's (no fused
    # multiply-add: numba compiles without fastmath)
    for k in range(raw.shape[0]):
        for c in range(3):
            out[k, c] = (float(raw[k, c]) * scale[c] + offset[c]) * unit


def _gather(
    stage: str | None,
    chunk: Chunk,
    sources: Sequence[tuple[int, bool]],
    fields: Sequence[str],
    direct: Any,
    unit_scale: float = 1.0,
) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
    """Concatenate the points of ``sources`` ((tile, staged?) in order) into arrays
    allocated once: staged fragments are read straight into their rows, the other tiles by
    ``direct(tile)`` (a COPC query)."""
    root = Path(stage) if stage is not None else Path()
    parts: list[tuple[int, Any]] = []
    for k, staged in sources:
        if staged:
            parts.append((k, _frag_points(root, chunk, k)))
        else:
            parts.append((k, direct(k)))
    sizes = [v if isinstance(v, int) else int(v[0].shape[0]) for _, v in parts]
    n = sum(sizes)
    xyz = np.empty((n, 3), dtype=np.float64)
    extra: dict[str, NDArray[Any]] = {}
    for f in fields:
        kinds = [v[1][f].dtype for _, v in parts if not isinstance(v, int)]
        kinds += [np.dtype(np.float64)] * sum(isinstance(v, int) for _, v in parts)
        extra[f] = np.empty(n, dtype=np.result_type(*kinds) if kinds else np.float64)
    at = 0
    for (k, v), m in zip(parts, sizes, strict=True):
        rows = slice(at, at + m)
        if isinstance(v, int):
            what = f"staged points of tile {k} for chunk {chunk.id}"
            _read_xyz(_frag(root, chunk.id, k, "xyz"), xyz[rows], what, unit_scale)
            for f in fields:
                fp = _frag(root, chunk.id, k, f)
                if not fp.exists() or fp.stat().st_size != 8 * m:
                    raise InputError(f"staged field {f!r} of tile {k}, chunk {chunk.id} is torn.")
                if extra[f].dtype == np.float64:
                    _read_into(fp, extra[f][rows], f"staged field {f!r} of tile {k}")
                else:
                    extra[f][rows] = np.fromfile(fp, dtype=np.float64)
        else:
            xyz[rows] = v[0]
            for f in fields:
                extra[f][rows] = v[1][f]
        at += m
    return xyz, extra


def clear_stage(stage: str | Path, chunk_id: str | None = None) -> None:
    """Remove one chunk's fragments (or the whole stage folder)."""
    p = Path(stage) if chunk_id is None else Path(stage) / chunk_id
    shutil.rmtree(p, ignore_errors=True)


def chunk_points(
    catalog: Catalog, chunk: Chunk, stage: str | None, fields: Sequence[str] = ()
) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
    """A buffered chunk's points in tile order: staged fragments for LAS/LAZ tiles (when
    ``stage`` is given), a direct read (a COPC query) otherwise; one array, filled in place."""
    from dataclasses import replace

    from stemmap.engine.catalog import read_chunk

    def direct(k: int) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
        return read_chunk(catalog, replace(chunk, tiles=(k,)), fields=fields)

    sources = [(k, stage is not None and not catalog.tiles[k].copc) for k in chunk.tiles]
    return _gather(stage, chunk, sources, fields, direct, catalog.unit_scale)
