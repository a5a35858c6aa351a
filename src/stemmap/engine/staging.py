"""Decode every LAS/LAZ tile once: split its points into the buffered chunks that need them.

Without a spatial index, reading a chunk's buffer from a neighbouring LAZ tile means decoding
that whole tile: with chunks the size of the tiles every tile is decoded by nine chunks. The
engine therefore runs in two stages (lidR users do the same with ``catalog_retile``):

1. one task per tile (:func:`stage_tile`) streams the tile once and appends each block's points
   to one raw fragment per overlapping buffered chunk (float64 x, y, z and the requested extra
   fields), renamed into place when the tile is complete;
2. one task per chunk (:func:`read_staged`) concatenates its fragments in tile order -- the same
   points, in the same order, as :func:`~stemmap.engine.catalog.read_chunk` would read.

COPC tiles skip the stage: a COPC spatial query decodes only the octree nodes a chunk needs.
Fragments live in ``<work>/stage/<chunk id>/<tile index>.{xyz,<field>}`` and are removed once
their chunk is done.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from stemmap.engine.catalog import Catalog, Chunk
from stemmap.errors import InputError
from stemmap.types import FloatArray

__all__ = ["clear_stage", "read_staged", "stage_tile", "stage_tile_outcome"]


def _frag(stage: Path, chunk_id: str, tile: int, what: str) -> Path:
    return stage / chunk_id / f"{tile}.{what}"


def stage_tile(
    catalog: Catalog,
    tile: int,
    chunks: Sequence[Chunk],
    stage: str,
    fields: Sequence[str] = (),
    read_points: int = 1_000_000,
) -> dict[str, int]:
    """Stream tile ``tile`` once and write its points inside each chunk's buffered box.

    Runs on a worker; memory is bounded by ``read_points``. Returns points read per chunk.
    """
    import laspy

    t = catalog.tiles[tile]
    root = Path(stage)
    boxes = [(c.id, c.buffered) for c in chunks]
    what = ("xyz", *fields)
    handles: dict[tuple[str, str], IO[bytes]] = {}
    counts = {c.id: 0 for c in chunks}
    tmp_suffix = f".tmp{os.getpid()}"
    try:
        for cid, _ in boxes:
            (root / cid).mkdir(parents=True, exist_ok=True)
            for w in what:
                p = _frag(root, cid, tile, w + tmp_suffix)
                handles[(cid, w)] = open(p, "wb")  # noqa: SIM115 - closed in finally
        try:
            with laspy.open(t.path, laz_backend=_one_thread_laz()) as rd:
                names = set(rd.header.point_format.dimension_names)
                missing = [f for f in fields if f not in names]
                if missing:
                    raise InputError(f"tile {t.path!r} has no point field {missing[0]!r}.")
                for pts in rd.chunk_iterator(read_points):
                    if len(pts) == 0:
                        continue
                    x, y = np.asarray(pts.x), np.asarray(pts.y)
                    xyz: FloatArray | None = None
                    for cid, bx in boxes:
                        m = (x >= bx[0]) & (x <= bx[2]) & (y >= bx[1]) & (y <= bx[3])
                        if not m.any():
                            continue
                        if xyz is None:
                            xyz = np.column_stack((x, y, np.asarray(pts.z)))
                        handles[(cid, "xyz")].write(np.ascontiguousarray(xyz[m]).tobytes())
                        for f in fields:
                            v = np.asarray(pts[f], dtype=np.float64)[m]
                            handles[(cid, f)].write(v.tobytes())
                        counts[cid] += int(m.sum())
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"reading tile {t.path!r} failed: {exc}") from exc
        for h in handles.values():
            h.flush()
            os.fsync(h.fileno())
            h.close()
        for cid, _ in boxes:
            for w in what:
                os.replace(_frag(root, cid, tile, w + tmp_suffix), _frag(root, cid, tile, w))
    finally:
        for h in handles.values():
            h.close()
        for cid, _ in boxes:
            for w in what:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(_frag(root, cid, tile, w + tmp_suffix))
    return counts


def _one_thread_laz() -> Any:
    """lazrs' single-threaded LAZ decoder when available (laspy's default decodes on every
    core: in a one-thread Dask worker that oversubscribes the cores the other workers use;
    the decoded points are the same)."""
    from laspy import LazBackend

    return LazBackend.Lazrs if LazBackend.Lazrs.is_available() else None


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
    stage: str, chunk: Chunk, tiles: Sequence[int], fields: Sequence[str] = ()
) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
    """A chunk's points from the fragments of ``tiles`` (in that order)."""
    root = Path(stage)
    parts: list[FloatArray] = []
    extra: dict[str, list[NDArray[Any]]] = {f: [] for f in fields}
    for k in tiles:
        p = _frag(root, chunk.id, k, "xyz")
        if not p.exists():
            raise InputError(f"staged points of tile {k} for chunk {chunk.id} are missing ({p}).")
        xyz = np.fromfile(p, dtype=np.float64).reshape(-1, 3)
        parts.append(xyz)
        for f in fields:
            v = np.fromfile(_frag(root, chunk.id, k, f), dtype=np.float64)
            if v.shape[0] != xyz.shape[0]:
                raise InputError(f"staged field {f!r} of tile {k}, chunk {chunk.id} is torn.")
            extra[f].append(v)
    if not parts:
        return np.zeros((0, 3)), {f: np.zeros(0) for f in fields}
    return np.concatenate(parts), {f: np.concatenate(v) for f, v in extra.items()}


def clear_stage(stage: str | Path, chunk_id: str | None = None) -> None:
    """Remove one chunk's fragments (or the whole stage folder)."""
    p = Path(stage) if chunk_id is None else Path(stage) / chunk_id
    shutil.rmtree(p, ignore_errors=True)


def chunk_points(
    catalog: Catalog, chunk: Chunk, stage: str | None, fields: Sequence[str] = ()
) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
    """A buffered chunk's points in tile order: staged fragments for LAS/LAZ tiles (when
    ``stage`` is given), a direct read (a COPC query) otherwise."""
    from dataclasses import replace

    from stemmap.engine.catalog import read_chunk

    parts: list[FloatArray] = []
    extra: dict[str, list[NDArray[Any]]] = {f: [] for f in fields}
    for k in chunk.tiles:
        if stage is not None and not catalog.tiles[k].copc:
            xyz, ex = read_staged(stage, chunk, (k,), fields)
        else:
            xyz, ex = read_chunk(catalog, replace(chunk, tiles=(k,)), fields=fields)
        parts.append(xyz)
        for f in fields:
            extra[f].append(ex[f])
    if not parts:
        return np.zeros((0, 3)), {f: np.zeros(0) for f in fields}
    return np.concatenate(parts), {f: np.concatenate(v) for f, v in extra.items()}
