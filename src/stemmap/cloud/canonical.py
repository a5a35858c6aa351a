"""A canonical order of points: the detector's results do not depend on the point order.

The same cloud re-exported by another tool, merged from tiles or converted to COPC holds the
same points in another order. Every step of our detector after the ground reads the slice
band (a few per cent of a plot's points), and its sums, its random samples (the spacing
sample, RANSAC draws), its tie-breaks (nearest neighbours at equal distances, the first of
equal values) and its KD-trees follow the band's order. So the band is put in one order that
depends only on its points -- lexicographic by x, then y, then height, then the sensor
position when known -- before anything reads it (:func:`canonical_band`); the raw cloud is
never sorted (the ground step reduces it to cell minima with coordinate tie-breaks:
:func:`stemmap.cloud._grid_kernel.lowest_per_cell`). Points equal in every key are the same
point and may come in any order.

The sort is ``argsort`` of x, then each run of equal x (LAS coordinates are integers of the
scale: a 1 mm grid ties thousands of points) is sorted by the next key, and so on, in one
compiled pass per key: ~3x cheaper than ``np.lexsort`` of the three columns (measured:
docs/algorithms/cloud.md "Point order").
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from stemmap.cloud.band import _Band
from stemmap.types import FloatArray

__all__ = ["canonical_band", "canonical_order"]


@njit(cache=True)
def _refine(order: NDArray[np.int64], key: FloatArray, tie: NDArray[np.bool_]) -> None:
    """Sort each run of ``order`` whose items are tied (``tie[i]``: item i equals item i - 1
    on the keys so far) by ``key``, in place, and keep ``tie`` only where ``key`` ties too."""
    n = order.shape[0]
    a = 0
    while a < n:
        b = a + 1
        while b < n and tie[b]:
            b += 1
        if b - a > 1:
            run = order[a:b].copy()
            vals = np.empty(b - a)
            for i in range(b - a):
                vals[i] = key[run[i]]
            o = np.argsort(vals)
            for i in range(b - a):
                order[a + i] = run[o[i]]
            for i in range(a + 1, b):
                tie[i] = vals[o[i - a]] == vals[o[i - a - 1]]
        a = b


def canonical_order(*keys: FloatArray) -> NDArray[np.int64]:
    """Indices sorting the points lexicographically by ``keys`` (1-D float arrays of equal
    length, the first the primary key): ``np.lexsort(keys[::-1])`` up to the order of points
    equal in every key. NaN sorts last, as in numpy."""
    first = np.asarray(keys[0], dtype=np.float64)
    order = np.argsort(first).astype(np.int64)
    if order.size < 2:
        return order
    v = first[order]
    tie = np.zeros(order.size, dtype=bool)
    tie[1:] = (v[1:] == v[:-1]) | (np.isnan(v[1:]) & np.isnan(v[:-1]))
    for k in keys[1:]:
        if not tie.any():
            break
        _refine(order, np.ascontiguousarray(k, dtype=np.float64), tie)
    return order


def _sorted_reach(
    reach: tuple[FloatArray, FloatArray] | None,
) -> tuple[FloatArray, FloatArray] | None:
    if reach is None or reach[0].shape[0] < 2:
        return reach
    rxy, rh = reach
    o = canonical_order(rxy[:, 0], rxy[:, 1], rh)
    return rxy[o], rh[o]


def canonical_band(band: _Band) -> _Band:
    """``band`` with its points (and the returns of its reach) in the canonical order: by x,
    then y, then height, then the sensor position's x and y. The canopy raster is keyed by
    cell and already order-free. Returns a new band (the arrays are copied once)."""
    keys = [band.xy[:, 0], band.xy[:, 1], band.h]
    if band.origins is not None:
        keys += [band.origins[:, 0], band.origins[:, 1]]
    o = canonical_order(*keys)
    out = _Band(
        band.xy[o],
        band.h[o],
        band.z[o],
        band.canopy,
        origins=None if band.origins is None else np.ascontiguousarray(band.origins[o]),
        base=band.base,
        base_z=band.base_z,
    )
    out.reach = _sorted_reach(band.reach)
    return out
