"""Heights around a stem (ours, docs/algorithms/cloud.md "Ours" step 9): the canopy-height
raster built while the band is streamed, the stem (tree) height read from it, and the absolute
z of breast height under a stem."""

from __future__ import annotations

from typing import Any

import numpy as np

from stemmap.cloud._grid_kernel import max_per_cell
from stemmap.cloud.band import _Band
from stemmap.cloud.ground import cell_index
from stemmap.types import FloatArray

_CANOPY_CELL = 0.25
_KEY_OFF = 1 << 30


def _canopy_update(canopy: dict[str, Any], xy: FloatArray, h: FloatArray) -> dict[str, Any]:
    """Running max height per 0.25 m cell (keys -> max h, keys sorted), for stem height."""
    if xy.shape[0] == 0:
        return canopy
    dense = max_per_cell(xy[:, 0], xy[:, 1], h, _CANOPY_CELL)  # one pass when compact
    if dense is None:
        ij = np.floor(xy / _CANOPY_CELL).astype(np.int64)
    else:
        ij, h = dense
    if canopy:
        i = (canopy["keys"] >> 32) - _KEY_OFF
        j = (canopy["keys"] & 0xFFFFFFFF) - _KEY_OFF
        ij = np.concatenate((np.column_stack((i, j)), ij))
        h = np.concatenate((canopy["h"], h))
    elif dense is not None:
        keys = ((ij[:, 0] + _KEY_OFF) << 32) | (ij[:, 1] + _KEY_OFF)
        return {"keys": keys, "h": h}
    cells, inv = cell_index(ij)  # the distinct cells, sorted, without a sort of the points
    hmax = np.full(cells.shape[0], -np.inf)
    np.maximum.at(hmax, inv, h)
    keys = ((cells[:, 0] + _KEY_OFF) << 32) | (cells[:, 1] + _KEY_OFF)
    return {"keys": keys, "h": hmax}


def _stem_heights(canopy: dict[str, Any], xy: FloatArray, radius: float = 1.0) -> FloatArray:
    """Stem (tree) height at each ``xy``: the highest canopy cell within ``radius`` metres
    (NaN without a canopy raster or without a cell in reach)."""
    if not canopy:
        return np.full(xy.shape[0], np.nan)
    i = (canopy["keys"] >> 32) - _KEY_OFF
    j = (canopy["keys"] & 0xFFFFFFFF) - _KEY_OFF
    cxy = (np.column_stack((i, j)) + 0.5) * _CANOPY_CELL
    from scipy.spatial import cKDTree

    tree = cKDTree(cxy)
    out = np.full(xy.shape[0], np.nan)
    for k, nb in enumerate(tree.query_ball_point(xy, radius)):
        if nb:
            out[k] = float(np.max(canopy["h"][nb]))
    return out


def _breast_height_z(band: _Band, xy: FloatArray, bh: float, tree: Any = None) -> FloatArray:
    """Absolute z of breast height at ``xy``: the median ground z (z - h) of the 16 nearest
    band points plus ``bh``; ``tree``: a cKDTree of ``band.xy`` if built."""
    from scipy.spatial import cKDTree

    if band.xy.shape[0] == 0 or xy.shape[0] == 0:
        return np.full(xy.shape[0], np.nan)
    off = band.z - band.h  # ground z under each band point
    tree = cKDTree(band.xy) if tree is None else tree
    _, idx = tree.query(xy, k=min(16, band.xy.shape[0]))
    idx = np.atleast_2d(idx)
    return np.asarray(np.median(off[idx], axis=1) + bh, dtype=np.float64)
