"""Tile catalog of LAS/LAZ files and its buffered processing chunks (anchor: lidR's LAScatalog).

A :class:`Catalog` indexes tiles from their headers only (bounds, point count, COPC or not:
``laspy.open`` reads the header, never the points). :func:`plan_chunks` cuts the catalog's extent
into a grid of square chunks of ``chunk_size`` metres aligned on multiples of ``chunk_size``
(lidR's default alignment at (0, 0)); each chunk is read with a ``buffer`` of extra metres all
round (lidR's ``opt_chunk_buffer``), and a chunk whose buffered area is expected to hold more
points than the memory budget is split into quarters until it fits. :func:`read_chunk` reads the
points of one buffered chunk from the overlapping tiles in bounded memory: laspy's chunked
reader for LAS/LAZ (only the points inside the box are kept), a COPC spatial query when the
tile is COPC.

Ownership: every chunk *owns* the half-open rectangle ``[xmin, xmax) x [ymin, ymax)`` of its
unbuffered area, and the chunks on the border of the catalog own everything beyond it too, so
the owned areas partition the plane: a result with a position (a stem centre) belongs to
exactly one chunk (:meth:`Chunk.owns`).
"""

from __future__ import annotations

import glob
import logging
import math
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.io.products import file_sha256
from stemmap.types import FloatArray

__all__ = [
    "Catalog",
    "Chunk",
    "Tile",
    "expand_inputs",
    "plan_chunks",
    "read_chunk",
]

log = logging.getLogger(__name__)

TILE_EXTENSIONS = (".las", ".laz")


@dataclass(frozen=True)
class Tile:
    """One LAS/LAZ file of a catalog, as its header describes it.

    Attributes
    ----------
    path : str -- absolute path
    bounds : (xmin, ymin, zmin, xmax, ymax, zmax), metres (header bounds, times the
        catalog's ``unit_scale``)
    n_points : int -- header point count
    copc : bool -- a COPC file (spatial queries via laspy's CopcReader)
    size : int -- file size, bytes
    """

    path: str
    bounds: tuple[float, float, float, float, float, float]
    n_points: int
    copc: bool
    size: int

    @property
    def area(self) -> float:
        """Horizontal area of the header bounding box, m² (at least 1 m²)."""
        b = self.bounds
        return max((b[3] - b[0]) * (b[4] - b[1]), 1.0)

    def overlaps(self, box: tuple[float, float, float, float]) -> bool:
        """Whether the header box meets ``box`` = (xmin, ymin, xmax, ymax) (closed)."""
        b = self.bounds
        return not (b[3] < box[0] or b[0] > box[2] or b[4] < box[1] or b[1] > box[3])

    def points_in(self, box: tuple[float, float, float, float]) -> float:
        """Expected number of points inside ``box``: uniform density over the header box."""
        b = self.bounds
        w = min(b[3], box[2]) - max(b[0], box[0])
        h = min(b[4], box[3]) - max(b[1], box[1])
        if w < 0 or h < 0:
            return 0.0
        # a degenerate (zero-width) tile puts all its points on a line or a point
        fw = w / (b[3] - b[0]) if b[3] > b[0] else 1.0
        fh = h / (b[4] - b[1]) if b[4] > b[1] else 1.0
        return self.n_points * fw * fh

    def content_hash(self) -> str:
        """SHA-256 of the file's bytes, hex: the input identity a manifest records (the same
        function, and the same per-process memo, as the run's ``run.json``)."""
        return file_sha256(self.path)


def _is_copc(header: Any) -> bool:
    return any(
        getattr(v, "user_id", "") == "copc" and getattr(v, "record_id", -1) == 1
        for v in getattr(header, "vlrs", ())
    )


def read_tile(path: str | os.PathLike[str], unit_scale: float = 1.0) -> Tile:
    """Index one LAS/LAZ file from its header (no point is read); ``unit_scale``: metres per
    file unit (the bounds are returned in metres).

    Raises
    ------
    InputError
        The file is missing, empty or not LAS/LAZ.
    """
    import laspy

    p = Path(path)
    if not p.is_file():
        raise InputError(f"tile {str(p)!r} does not exist.")
    if p.stat().st_size == 0:
        raise InputError(f"tile {str(p)!r} is empty (0 bytes).")
    try:
        with laspy.open(p) as reader:
            hd = reader.header
            lo, hi = np.asarray(hd.mins, dtype=float), np.asarray(hd.maxs, dtype=float)
            n = int(hd.point_count)
            copc = _is_copc(hd)
    except Exception as exc:
        raise InputError(f"{str(p)!r} is not a readable LAS/LAZ file: {exc}") from exc
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise InputError(f"{str(p)!r}: its header bounds are not finite ({lo}, {hi}).")
    if unit_scale != 1.0:
        lo, hi = lo * unit_scale, hi * unit_scale
    return Tile(
        str(p.resolve()),
        (float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2])),
        n,
        copc,
        p.stat().st_size,
    )


def _from_list_file(p: Path) -> list[Path]:
    """Paths listed one per line in a text file (blank lines and ``#`` comments skipped;
    relative paths are relative to the list file's folder)."""
    out = []
    for line in p.read_text(encoding="utf-8").splitlines():
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        q = Path(s).expanduser()
        out.append(q if q.is_absolute() else p.parent / q)
    return out


def expand_inputs(
    inputs: Iterable[str | os.PathLike[str]],
    *,
    extensions: Sequence[str] = TILE_EXTENSIONS,
    unit_dir: Callable[[Path], bool] | None = None,
    companion: Callable[[Path], bool] | None = None,
    what: str = "tile",
) -> list[Path]:
    """Resolve a mix of files, folders (their files with ``extensions``, not recursive), glob
    patterns and text files listing paths (``.txt`` / ``.lst``, one per line) into a sorted
    list of distinct inputs.

    The defaults make a tile catalog (LAS/LAZ). Drive logs (:mod:`stemmap.engine.logs`) pass
    their own ``extensions``, ``unit_dir`` (a folder that is one input itself, e.g. a ROS 2
    bag, is kept as is, and is one entry when met inside a folder) and ``companion`` (files of
    a folder or glob match that belong to another input, e.g. a log's odometry CSV, and are
    not inputs; a file named directly or in a list file is always taken).

    Raises
    ------
    InputError
        An input that does not exist or matches nothing, a folder without inputs, or a
        listed/matched file without one of ``extensions``.
    """
    exts = tuple(e.lower() for e in extensions)
    shown = "/".join(exts)
    kinds = "/".join(e.lstrip(".").upper() for e in exts)

    def unit(q: Path) -> bool:
        return unit_dir is not None and q.is_dir() and unit_dir(q)

    found: list[Path] = []
    for item in inputs:
        s = str(item)
        p = Path(s).expanduser()
        if unit(p):
            found.append(p)
        elif p.is_dir():
            members = sorted(
                q
                for q in p.iterdir()
                if unit(q)
                or (
                    q.is_file()
                    and q.suffix.lower() in exts
                    and not (companion is not None and companion(q))
                )
            )
            if not members:
                raise InputError(
                    f"folder {s!r} holds no {shown} file (a {what} folder is not searched "
                    f"recursively; pass a glob like 'dir/**/*{exts[0]}' for sub-folders)."
                )
            found.extend(members)
        elif p.is_file() and p.suffix.lower() in (".txt", ".lst"):
            listed = _from_list_file(p)
            if not listed:
                raise InputError(f"list file {s!r} names no {what}.")
            found.extend(listed)
        elif p.is_file():
            found.append(p)
        elif any(c in s for c in "*?["):
            matches = sorted(Path(m) for m in glob.glob(os.path.expanduser(s), recursive=True))
            matches = [
                m
                for m in matches
                if unit(m) or (m.is_file() and not (companion is not None and companion(m)))
            ]
            if not matches:
                raise InputError(f"the pattern {s!r} matches no file.")
            found.extend(matches)
        else:
            raise InputError(f"input {s!r} does not exist (a file, folder, glob or list file).")
    bad = [str(q) for q in found if not unit(q) and q.suffix.lower() not in exts]
    if bad:
        raise InputError(
            f"{what} inputs take {kinds} files only; not {kinds}: {', '.join(bad[:5])}"
            + (" ..." if len(bad) > 5 else "")
            + ". Convert other formats, or pass a single file to process it on its own."
        )
    uniq: dict[str, Path] = {}
    for q in found:
        uniq.setdefault(str(q.resolve()), q)
    return [uniq[k] for k in sorted(uniq)]


@dataclass(frozen=True)
class Catalog:
    """Indexed LAS/LAZ tiles (headers only).

    ``unit_scale``: metres per unit of the tiles' coordinates (``stemmap stems --units``; 1 for
    tiles in metres). Everything the engine computes is in metres: the tile bounds, chunks and
    boxes, and the points read (the file's ``X * scale + offset``, times ``unit_scale``).
    """

    tiles: tuple[Tile, ...]
    unit_scale: float = 1.0

    @classmethod
    def from_inputs(
        cls, inputs: Iterable[str | os.PathLike[str]], unit_scale: float = 1.0
    ) -> Catalog:
        """Index files, folders, globs and list files (:func:`expand_inputs`)."""
        tiles = tuple(read_tile(p, unit_scale) for p in expand_inputs(inputs))
        if not tiles:
            raise InputError("no tile to process.")
        return cls(tiles, unit_scale)

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def n_points(self) -> int:
        return sum(t.n_points for t in self.tiles)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of all tiles, metres."""
        b = np.array([t.bounds for t in self.tiles])
        return (
            float(b[:, 0].min()),
            float(b[:, 1].min()),
            float(b[:, 3].max()),
            float(b[:, 4].max()),
        )

    @property
    def z_range(self) -> tuple[float, float]:
        """(zmin, zmax) of all tiles, metres (header bounds)."""
        b = np.array([t.bounds for t in self.tiles])
        return (float(b[:, 2].min()), float(b[:, 5].max()))

    def expected_points(self, box: tuple[float, float, float, float]) -> float:
        return sum(t.points_in(box) for t in self.tiles)

    def density(self) -> float:
        """Mean points per m² over the tiles' header boxes."""
        return self.n_points / max(sum(t.area for t in self.tiles), 1.0)


@dataclass(frozen=True)
class Chunk:
    """One processing unit: an owned rectangle plus a buffer, and the tiles it reads.

    Attributes
    ----------
    id : str -- stable name (from the grid position and the split path), e.g. ``"x3_y-1"``
    box : (xmin, ymin, xmax, ymax), metres -- the owned, unbuffered area
    buffer : float, metres
    tiles : tuple of int -- indices of the catalog tiles the buffered box meets
    open_sides : (left, bottom, right, top) -- sides on the catalog border: the chunk also
        owns everything beyond them
    expected_points : float -- header-based estimate for the buffered box
    """

    id: str
    box: tuple[float, float, float, float]
    buffer: float
    tiles: tuple[int, ...]
    open_sides: tuple[bool, bool, bool, bool]
    expected_points: float

    @property
    def buffered(self) -> tuple[float, float, float, float]:
        b, d = self.box, self.buffer
        return (b[0] - d, b[1] - d, b[2] + d, b[3] + d)

    @property
    def owned_region(self) -> tuple[float, float, float, float]:
        """The owned area as (xmin, ymin, xmax, ymax), infinite on the open sides."""
        x0, y0, x1, y1 = self.box
        left, bottom, right, top = self.open_sides
        inf = math.inf
        return (
            -inf if left else x0,
            -inf if bottom else y0,
            inf if right else x1,
            inf if top else y1,
        )

    def owns(self, xy: FloatArray) -> NDArray[np.bool_]:
        """Which of the (N, 2) positions lie in the owned area (half-open, border sides open)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        x0, y0, x1, y1 = self.box
        left, bottom, right, top = self.open_sides
        ok = np.ones(p.shape[0], dtype=bool)
        if not left:
            ok &= p[:, 0] >= x0
        if not bottom:
            ok &= p[:, 1] >= y0
        if not right:
            ok &= p[:, 0] < x1
        if not top:
            ok &= p[:, 1] < y1
        return ok


def plan_chunks(
    catalog: Catalog,
    chunk_size: float | None,
    buffer: float,
    *,
    max_points: int = 8_000_000,
) -> list[Chunk]:
    """Cut the catalog into buffered chunks.

    Parameters
    ----------
    catalog : Catalog
    chunk_size : float, metres, optional
        Side of the square chunks, aligned on multiples of it. None: the largest multiple of
        10 m whose buffered chunk is expected to hold at most ``max_points`` points at the
        catalog's mean density (at least 10 m).
    buffer : float, metres, >= 0
    max_points : int
        Memory budget of one buffered chunk, points (~100 bytes each while detecting). A chunk
        expected above it (header density; tiles are taken as uniform) is split into four,
        recursively, down to a side of ``2 * buffer`` or 1 m.

    Returns
    -------
    list of Chunk
        Only chunks whose buffered box meets at least one tile and whose owned area is
        expected to hold points, in row-major order.
    """
    if not (math.isfinite(buffer) and buffer >= 0):
        raise ConfigError(f"--buffer must be >= 0 metres, got {buffer}.")
    if max_points < 1:
        raise ConfigError(f"the per-chunk point budget must be >= 1, got {max_points}.")
    if chunk_size is None:
        side = math.sqrt(max_points / max(catalog.density(), 1e-9)) - 2 * buffer
        chunk_size = max(10.0, 10.0 * math.floor(side / 10.0))
    elif not (math.isfinite(chunk_size) and chunk_size > 0):
        raise ConfigError(f"--chunk-size must be > 0 metres, got {chunk_size}.")
    x0, y0, x1, y1 = catalog.bounds
    i0, i1 = math.floor(x0 / chunk_size), math.floor(x1 / chunk_size)
    j0, j1 = math.floor(y0 / chunk_size), math.floor(y1 / chunk_size)
    out: list[Chunk] = []
    for j in range(j0, j1 + 1):
        for i in range(i0, i1 + 1):
            box = (i * chunk_size, j * chunk_size, (i + 1) * chunk_size, (j + 1) * chunk_size)
            sides = (i == i0, j == j0, i == i1, j == j1)
            out.extend(_split(catalog, f"x{i}_y{j}", box, buffer, sides, max_points))
    return out


def _split(
    catalog: Catalog,
    name: str,
    box: tuple[float, float, float, float],
    buffer: float,
    sides: tuple[bool, bool, bool, bool],
    max_points: int,
) -> list[Chunk]:
    bb = (box[0] - buffer, box[1] - buffer, box[2] + buffer, box[3] + buffer)
    tiles = tuple(k for k, t in enumerate(catalog.tiles) if t.overlaps(bb))
    if not tiles:
        return []
    # expected points of the owned part (border chunks own beyond their box: use the buffered
    # box there) -- a chunk that owns nothing is skipped
    own = (
        box[0] - (buffer if sides[0] else 0.0),
        box[1] - (buffer if sides[1] else 0.0),
        box[2] + (buffer if sides[2] else 0.0),
        box[3] + (buffer if sides[3] else 0.0),
    )
    if not any(catalog.tiles[k].overlaps(own) for k in tiles):
        return []
    expected = catalog.expected_points(bb)
    side = box[2] - box[0]
    if expected > max_points and side / 2 >= max(2 * buffer, 1.0):
        xm, ym = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        quads = (
            ("a", (box[0], box[1], xm, ym), (sides[0], sides[1], False, False)),
            ("b", (xm, box[1], box[2], ym), (False, sides[1], sides[2], False)),
            ("c", (box[0], ym, xm, box[3]), (sides[0], False, False, sides[3])),
            ("d", (xm, ym, box[2], box[3]), (False, False, sides[2], sides[3])),
        )
        log.info("chunk %s: ~%.0f points > budget %d, split in four", name, expected, max_points)
        out: list[Chunk] = []
        for suffix, qb, qs in quads:
            out.extend(_split(catalog, f"{name}{suffix}", qb, buffer, qs, max_points))
        return out
    if expected > max_points:
        log.warning(
            "chunk %s: ~%.0f points exceed the budget %d but cannot be split further",
            name,
            expected,
            max_points,
        )
    return [Chunk(name, box, buffer, tiles, sides, expected)]


def read_chunk(
    catalog: Catalog,
    chunk: Chunk,
    *,
    fields: Sequence[str] = (),
    read_points: int = 250_000,
) -> tuple[FloatArray, dict[str, NDArray[Any]]]:
    """The points of ``chunk``'s buffered box from its tiles, in tile then file order.

    LAS/LAZ tiles are streamed ``read_points`` at a time and only the points inside the box
    are kept; COPC tiles are queried with the box (only the octree nodes meeting it are
    decoded). The box is closed: a point on a shared edge is read by both neighbours, which is
    what a buffer wants.

    Returns
    -------
    xyz : ndarray (N, 3), metres
    fields : dict of name -> ndarray (N,)
        The extra LAS dimensions named in ``fields`` (an InputError if a tile lacks one).
    """
    import laspy

    bx = chunk.buffered
    u = catalog.unit_scale
    parts: list[FloatArray] = []
    extra: dict[str, list[NDArray[Any]]] = {f: [] for f in fields}
    for k in chunk.tiles:
        tile = catalog.tiles[k]
        src = repr(tile.path)
        try:
            if tile.copc:
                # the query in the file's units, one ulp wider (the box test is in metres)
                lo, hi = np.array([bx[0], bx[1]]) / u, np.array([bx[2], bx[3]]) / u
                bounds = laspy.copc.Bounds(
                    mins=np.nextafter(lo, -np.inf), maxs=np.nextafter(hi, np.inf)
                )
                with laspy.CopcReader.open(tile.path) as rd:
                    blocks: Iterable[Any] = [rd.query(bounds=bounds)]
                    _keep_box(blocks, bx, fields, parts, extra, src, u)
            else:
                with laspy.open(tile.path) as rd:
                    _keep_box(rd.chunk_iterator(read_points), bx, fields, parts, extra, src, u)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"reading tile {src} failed: {exc}") from exc
    if not parts:
        return np.zeros((0, 3)), {f: np.zeros(0) for f in fields}
    return np.concatenate(parts), {f: np.concatenate(v) for f, v in extra.items()}


def _keep_box(
    blocks: Iterable[Any],
    bx: tuple[float, float, float, float],
    fields: Sequence[str],
    parts: list[FloatArray],
    extra: dict[str, list[NDArray[Any]]],
    src: str,
    unit_scale: float = 1.0,
) -> None:
    for pts in blocks:
        if len(pts) == 0:
            continue
        x, y, z = np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)
        if unit_scale != 1.0:  # to metres, as CloudConvention.apply: (X * scale + offset) * u
            x, y, z = x * unit_scale, y * unit_scale, z * unit_scale
        m = (x >= bx[0]) & (x <= bx[2]) & (y >= bx[1]) & (y <= bx[3])
        if not m.any():
            continue
        parts.append(np.column_stack((x[m], y[m], z[m])))
        names = set(pts.point_format.dimension_names)
        for f in fields:
            if f not in names:
                raise InputError(f"tile {src} has no point field {f!r}.")
            extra[f].append(np.asarray(pts[f])[m])
