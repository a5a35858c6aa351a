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

__all__ = ["dense_span", "lowest_per_cell", "max_per_cell"]


@njit(cache=True)
def _bounds(x: FloatArray, y: FloatArray, cell: float) -> tuple[int, int, int, int]:
    i0 = i1 = int(np.floor(x[0] / cell))
    j0 = j1 = int(np.floor(y[0] / cell))
    for k in range(1, x.shape[0]):
        i = int(np.floor(x[k] / cell))
        j = int(np.floor(y[k] / cell))
        i0, i1 = min(i0, i), max(i1, i)
        j0, j1 = min(j0, j), max(j1, j)
    return i0, i1, j0, j1


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
    support: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    m = ni * nj
    zmin = np.full(m, np.inf)
    first = np.full(m, -1, dtype=np.int64)
    n = x.shape[0]
    for k in range(n):
        d = (int(np.floor(x[k] / cell)) - i0) * nj + (int(np.floor(y[k] / cell)) - j0)
        if first[d] < 0 or z[k] < zmin[d]:  # strict: the first point of equal minima
            zmin[d] = z[k]
            first[d] = k
    cnt = np.zeros(m, dtype=np.int64)
    for k in range(n):
        d = (int(np.floor(x[k] / cell)) - i0) * nj + (int(np.floor(y[k] / cell)) - j0)
        if z[k] <= zmin[d] + support:
            cnt[d] += 1
    n_occ = 0
    for q in range(m):
        if first[q] >= 0:
            n_occ += 1
    cells = np.empty((n_occ, 2), dtype=np.int64)
    sel = np.empty(n_occ, dtype=np.int64)
    sup = np.empty(n_occ, dtype=np.int64)
    c = 0
    for q in range(m):
        if first[q] >= 0:
            cells[c, 0] = q // nj + i0
            cells[c, 1] = q % nj + j0
            sel[c] = first[q]
            sup[c] = cnt[q]
            c += 1
    return cells, sel, sup, zmin


def lowest_per_cell(
    x: FloatArray, y: FloatArray, z: FloatArray, cell: float, support: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The occupied cells (M, 2) sorted by (i, j), the index of each cell's lowest point
    (the first in point order among equal minima) and its support (the cell's points within
    ``support`` of that minimum); None when the points spread too far for a dense grid."""
    span = dense_span(x, y, cell)
    if span is None:
        return None
    cells, sel, sup, _ = _lowest(x, y, z, float(cell), *span, float(support))
    return cells, sel, sup


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
