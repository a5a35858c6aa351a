"""Per-cell reductions of a point chunk on a dense grid, in one or two passes (numba).

The ground accumulator (lowest point of each ground cell and its support) and the canopy
raster (highest point of each canopy cell) reduce millions of points to a few thousand cells.
In numpy that takes a cell index per point, :func:`~stemmap.cloud.ground.cell_index` (the
distinct cells and each point's position among them) and ``ufunc.at`` scatters: several
passes and temporaries over the points. These kernels compute the cell of each point
(``floor(x / cell)``, as numpy does) and reduce in place over a dense array spanning the
occupied cells' bounding box, then list the occupied cells in (i, j) order -- the same
cells, values and order as the numpy code, bit for bit. A bounding box much larger than the
point count (stray points far away) is refused (``None``) and the caller falls back to numpy.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from stemmap.types import FloatArray

__all__ = [
    "bilinear_nearest",
    "dense_span",
    "heights_in_band",
    "lowest_per_cell",
    "max_per_cell",
]


@njit(cache=True)
def _extremes(x: FloatArray, y: FloatArray) -> tuple[float, float, float, float]:
    x0 = x1 = x[0]
    y0 = y1 = y[0]
    for k in range(1, x.shape[0]):
        x0, x1 = min(x0, x[k]), max(x1, x[k])
        y0, y1 = min(y0, y[k]), max(y1, y[k])
    return x0, x1, y0, y1


def _bounds(x: FloatArray, y: FloatArray, cell: float) -> tuple[int, int, int, int]:
    # floor(v / cell) is non-decreasing in v (IEEE division and floor are monotonic), so the
    # extreme cells are those of the extreme coordinates: the same cells as flooring every
    # point, in one pass over both columns without a division per point
    x0, x1, y0, y1 = _extremes(x, y)
    return (
        int(np.floor(x0 / cell)),
        int(np.floor(x1 / cell)),
        int(np.floor(y0 / cell)),
        int(np.floor(y1 / cell)),
    )


def dense_span(
    x: FloatArray, y: FloatArray, cell: float, per_point: float = 1.0
) -> tuple[int, int, int, int] | None:
    """(i0, j0, ni, nj): the cell box of the points, or None when it holds more than
    ``per_point`` cells per point + one million (a dense array would not pay)."""
    n = x.shape[0]
    if n == 0:
        return None
    i0, i1, j0, j1 = _bounds(x, y, float(cell))
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    if float(ni) * float(nj) > per_point * n + 1_000_000:
        return None
    return int(i0), int(j0), int(ni), int(nj)


@njit(cache=True)
def _lowest(
    x: FloatArray,
    y: FloatArray,
    z: FloatArray,
    cell: float,
    i0: int,
    j0: int,
    ni: int,
    nj: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = ni * nj
    low3 = np.full((m, 3), np.inf)  # the three lowest z of each cell, ascending
    first = np.full(m, -1, dtype=np.int64)
    n = x.shape[0]
    for k in range(n):
        d = (int(np.floor(x[k] / cell)) - i0) * nj + (int(np.floor(y[k] / cell)) - j0)
        f = first[d]
        v = z[k]
        # equal minima: the smallest x, then y (not the first in point order: the same cloud
        # in another order gives the same ground)
        if (
            f < 0
            or v < low3[d, 0]
            or (v == low3[d, 0] and (x[k] < x[f] or (x[k] == x[f] and y[k] < y[f])))
        ):
            first[d] = k
        if v < low3[d, 0]:
            low3[d, 2] = low3[d, 1]
            low3[d, 1] = low3[d, 0]
            low3[d, 0] = v
        elif v < low3[d, 1]:
            low3[d, 2] = low3[d, 1]
            low3[d, 1] = v
        elif v < low3[d, 2]:
            low3[d, 2] = v
    n_occ = 0
    for q in range(m):
        if first[q] >= 0:
            n_occ += 1
    cells = np.empty((n_occ, 2), dtype=np.int64)
    sel = np.empty(n_occ, dtype=np.int64)
    out3 = np.empty((n_occ, 3))
    c = 0
    for q in range(m):
        if first[q] >= 0:
            cells[c, 0] = q // nj + i0
            cells[c, 1] = q % nj + j0
            sel[c] = first[q]
            out3[c] = low3[q]
            c += 1
    return cells, sel, out3


def lowest_per_cell(
    x: FloatArray, y: FloatArray, z: FloatArray, cell: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The occupied cells (M, 2) sorted by (i, j), the index of each cell's lowest point
    (among equal minima the one of smallest x, then y: independent of the point order; points
    equal in x, y and z are the same point) and the cell's three lowest z, ascending (M, 3;
    ``inf`` where it holds fewer points: what the ground's support test needs, and unlike a
    count of the points near the minimum it merges exactly over chunks); None when the
    points spread too far for a dense grid."""
    span = dense_span(x, y, cell)
    if span is None:
        return None
    return _lowest(x, y, z, float(cell), *span)


@njit(cache=True)
def _highest(
    x: FloatArray, y: FloatArray, h: FloatArray, cell: float, i0: int, j0: int, ni: int, nj: int
) -> tuple[np.ndarray, np.ndarray]:
    m = ni * nj
    hmax = np.full(m, -np.inf)
    seen = np.zeros(m, dtype=np.bool_)
    for k in range(x.shape[0]):
        d = (int(np.floor(x[k] / cell)) - i0) * nj + (int(np.floor(y[k] / cell)) - j0)
        seen[d] = True
        if h[k] > hmax[d]:
            hmax[d] = h[k]
    n_occ = 0
    for q in range(m):
        if seen[q]:
            n_occ += 1
    cells = np.empty((n_occ, 2), dtype=np.int64)
    out = np.empty(n_occ)
    c = 0
    for q in range(m):
        if seen[q]:
            cells[c, 0] = q // nj + i0
            cells[c, 1] = q % nj + j0
            out[c] = hmax[q]
            c += 1
    return cells, out


def max_per_cell(
    x: FloatArray, y: FloatArray, h: FloatArray, cell: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """The occupied cells (M, 2) sorted by (i, j) and the largest ``h`` in each; None when
    the points spread too far for a dense grid."""
    span = dense_span(x, y, cell)
    if span is None:
        return None
    return _highest(x, y, h, float(cell), *span)


@njit(cache=True)
def _axis(c: float, n: int) -> tuple[int, int, float, float]:
    """The two grid indices and weights along one axis of scipy.ndimage's order-1 spline
    with mode "nearest" (scipy 1.17): the nodes floor(c) and floor(c) + 1, each clamped to
    [0, n - 1] (the coordinate itself is not clamped), weights 1 - frac(c) and 1 minus that
    (ni_splines.c). Checked bit for bit against map_coordinates (tests)."""
    f = np.floor(c)
    s = int(f)
    w0 = 1.0 - (c - f)
    w1 = 1.0 - w0
    return min(max(s, 0), n - 1), min(max(s + 1, 0), n - 1), w0, w1


@njit(cache=True)
def _at(grid: FloatArray, ox: float, oy: float, cell: float, x: float, y: float) -> float:
    # the interpolated value at one finite point (scipy's operations, in its order)
    nx, ny = grid.shape
    fi = (x - ox) / cell - 0.5
    fj = (y - oy) / cell - 0.5
    i0, i1, a0, a1 = _axis(fi, nx)
    j0, j1, b0, b1 = _axis(fj, ny)
    t = 0.0
    t += grid[i0, j0] * a0 * b0
    t += grid[i0, j1] * a0 * b1
    t += grid[i1, j0] * a1 * b0
    t += grid[i1, j1] * a1 * b1
    return t


@njit(cache=True)
def _bilinear(
    grid: FloatArray, ox: float, oy: float, cell: float, x: FloatArray, y: FloatArray
) -> FloatArray | None:
    out = np.empty(x.shape[0])
    for k in range(x.shape[0]):
        if not (np.isfinite(x[k]) and np.isfinite(y[k])):
            return None
        out[k] = _at(grid, ox, oy, cell, x[k], y[k])
    return out


@njit(cache=True)
def _heights(
    grid: FloatArray,
    ox: float,
    oy: float,
    cell: float,
    x: FloatArray,
    y: FloatArray,
    z: FloatArray,
    lo: float,
    hi: float,
    h: FloatArray,
) -> int:
    # h = z - ground (numpy's subtraction of the interpolated ground); returns how many lie
    # in [lo, hi], or -1 at a non-finite coordinate
    cnt = 0
    for k in range(x.shape[0]):
        if not (np.isfinite(x[k]) and np.isfinite(y[k])):
            return -1
        v = z[k] - _at(grid, ox, oy, cell, x[k], y[k])
        h[k] = v
        if v >= lo and v <= hi:
            cnt += 1
    return cnt


@njit(cache=True)
def _in_range(h: FloatArray, lo: float, hi: float, cnt: int) -> np.ndarray:
    idx = np.empty(cnt, dtype=np.int64)
    c = 0
    for k in range(h.shape[0]):
        if h[k] >= lo and h[k] <= hi:
            idx[c] = k
            c += 1
    return idx


def heights_in_band(
    grid: FloatArray,
    origin: tuple[float, float],
    cell: float,
    xyz: FloatArray,
    lo: float,
    hi: float,
) -> tuple[FloatArray, np.ndarray] | None:
    """Heights ``z - ground(x, y)`` of the (N, 3) points (the ground interpolated as
    :func:`bilinear_nearest`) and the indices, in point order, of those with
    ``lo <= h <= hi``: bit for bit ``h = z - bilinear_nearest(...)`` and
    ``flatnonzero((h >= lo) & (h <= hi))``, in two passes without the temporaries (the
    interpolated ground, the masks). None when a coordinate is not finite."""
    g = np.ascontiguousarray(grid, dtype=np.float64)
    h = np.empty(xyz.shape[0])
    ox, oy, c = float(origin[0]), float(origin[1]), float(cell)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    cnt = _heights(g, ox, oy, c, x, y, z, float(lo), float(hi), h)
    if cnt < 0:
        return None
    return h, _in_range(h, float(lo), float(hi), cnt)


def bilinear_nearest(
    grid: FloatArray, origin: tuple[float, float], cell: float, x: FloatArray, y: FloatArray
) -> FloatArray | None:
    """Bilinear interpolation of ``grid`` (values at cell centres, lower-left corner at
    ``origin``) at the points (``x``, ``y``), clamped at the border: bit for bit
    ``scipy.ndimage.map_coordinates(grid, [(x - ox) / cell - 0.5, (y - oy) / cell - 0.5],
    order=1, mode="nearest")`` (same operations in the same order; tested), in one pass
    without the index arrays. None when a coordinate is not finite (the caller uses
    scipy, whose result for NaN coordinates is its own)."""
    g = np.ascontiguousarray(grid, dtype=np.float64)
    out = _bilinear(g, float(origin[0]), float(origin[1]), float(cell), x, y)
    return None if out is None else np.asarray(out)
