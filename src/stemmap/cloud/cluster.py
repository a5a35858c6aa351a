"""Clustering of point clouds: DBSCAN (Munjer et al. 2025) and grid connected components (ours).

Labels are int64 per point, ``-1`` for noise, clusters numbered 0..K-1.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from stemmap.errors import ConfigError, InputError

__all__ = ["dbscan", "grid_components"]


def dbscan(points: ArrayLike, eps: float, min_points: int) -> NDArray[np.int64]:
    """DBSCAN clustering (Munjer et al. 2025, §3.3; Table 1: eps 0.25 m, minPts 20).

    Parameters
    ----------
    points : array_like (N, D), metres
    eps : float, > 0
        Neighbourhood radius.
    min_points : int, >= 1
        Minimum neighbourhood size (the point itself included) of a core point.

    Returns
    -------
    ndarray (N,) int64, -1 for noise.

    Notes
    -----
    scikit-learn's implementation (KD-tree neighbourhoods). Memory grows with the number of
    neighbours per point, so voxel-reduce dense clouds first (as the paper does).
    """
    from sklearn.cluster import DBSCAN

    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2:
        raise InputError(f"points must be (N, D), got shape {p.shape}.")
    if not eps > 0 or min_points < 1:
        raise ConfigError(f"DBSCAN needs eps > 0 and min_points >= 1, got {eps}, {min_points}.")
    if p.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    return DBSCAN(eps=eps, min_samples=min_points).fit_predict(p).astype(np.int64)


def grid_components(
    xy: ArrayLike, cell: float, *, min_points: int = 1, connectivity: int = 2
) -> NDArray[np.int64]:
    """Connected components of occupied cells of a 2D grid (a linear-time DBSCAN stand-in).

    Points are binned into square cells of edge ``cell``; cells holding at least ``min_points``
    points are occupied; occupied cells touching (8-neighbourhood for ``connectivity=2``, 4 for
    1) form one cluster. Points in unoccupied cells are noise (-1).

    Cost O(N + cells), memory one small int32 raster over the points' bounding box.
    """
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 2:
        raise InputError(f"xy must be (N, 2), got shape {p.shape}.")
    if not cell > 0:
        raise ConfigError(f"cell must be > 0 m, got {cell}.")
    n = p.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    # cells on the global lattice floor(x / cell), offset to start at 0 (independent of the
    # extent of the points given)
    ij = np.floor(p[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0)
    shape = ij.max(axis=0) + 1
    if shape[0] * shape[1] > 400_000_000:
        raise InputError(
            f"grid of {shape[0]} x {shape[1]} cells at {cell} m is too large; crop the cloud."
        )
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    counts = np.bincount(flat, minlength=int(shape[0] * shape[1]))
    occ = (counts >= min_points).reshape(int(shape[0]), int(shape[1]))
    structure = ndimage.generate_binary_structure(2, connectivity)
    lab, _ = ndimage.label(occ, structure=structure)
    out = lab.ravel()[flat].astype(np.int64) - 1
    return out
