"""Point-cloud filters: pass-through box, voxel-grid averaging, point spacing.

All functions take ``xyz`` of shape (N, 3) in metres and never modify their input.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = ["as_xyz", "pass_through", "point_spacing", "voxel_downsample", "voxel_keys"]


def as_xyz(xyz: ArrayLike, name: str = "xyz") -> FloatArray:
    """Validate and promote to a float64 (N, 3) array of finite values; InputError otherwise."""
    a = np.asarray(xyz, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {a.shape}.")
    # min and max propagate NaN and hold any inf: no (N, 3) temporary of np.isfinite
    if a.size and not (np.isfinite(a.min()) and np.isfinite(a.max())):
        raise InputError(f"{name} contains NaN or inf coordinates; drop them first.")
    return a


def pass_through(
    xyz: ArrayLike,
    *,
    x: tuple[float, float] | None = None,
    y: tuple[float, float] | None = None,
    z: tuple[float, float] | None = None,
) -> NDArray[np.bool_]:
    """Mask of points strictly inside an axis-aligned box (Munjer et al. 2025, §3.2).

    A point is kept if ``lo < coord < hi`` on every axis that has bounds (``None`` = unbounded).
    The paper's box is x in (0, 10), y in (-10, 10), z in (-0.5, 0) m in the lidar frame.

    Examples
    --------
    >>> pass_through([[1.0, 0, -0.2], [-1.0, 0, -0.2]], x=(0, 10)).tolist()
    [True, False]
    """
    p = as_xyz(xyz)
    keep = np.ones(p.shape[0], dtype=bool)
    for axis, bounds in enumerate((x, y, z)):
        if bounds is None:
            continue
        lo, hi = float(bounds[0]), float(bounds[1])
        if not hi > lo:
            raise ConfigError(f"pass-through bounds on axis {'xyz'[axis]} must have lo < hi.")
        keep &= (p[:, axis] > lo) & (p[:, axis] < hi)
    return keep


def voxel_keys(xyz: FloatArray, voxel: float) -> NDArray[np.int64]:
    """One int64 key per point naming its voxel (21 bits per axis after shifting to >= 0).

    Voxels lie on the global lattice ``floor(x / voxel)`` (not anchored at the points'
    minimum), so a point falls in the same voxel in any chunk of a catalog as in the whole
    cloud; keys are offset by the smallest voxel index of ``xyz``.
    """
    q = np.floor(xyz / voxel).astype(np.int64)
    q -= q.min(axis=0)
    if np.any(q >= (1 << 21)):
        raise InputError(
            f"cloud extent {np.ptp(xyz, axis=0).max():.1f} m is too large for voxel {voxel} m "
            "(more than 2 million voxels along an axis); crop it or use a larger voxel."
        )
    return np.asarray((q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2], dtype=np.int64)


def voxel_downsample(
    xyz: ArrayLike, voxel: float, *, return_counts: bool = False
) -> FloatArray | tuple[FloatArray, NDArray[np.int64]]:
    """Voxel-grid averaging: one point per occupied voxel, the mean of its points.

    Parameters
    ----------
    xyz : array_like (N, 3), metres
    voxel : float, > 0, metres
        Edge of the cubic voxels (Munjer et al. 2025, Table 1: 0.01 m).
    return_counts : bool
        Also return how many input points each output point averages.

    Returns
    -------
    ndarray (M, 3) [, ndarray (M,) int]

    Notes
    -----
    Munjer et al. (2025) eq. (2): ``P' = { (1/|V|) sum_{p in V} p : V subset P, |V| > 0 }``.
    Output order is by voxel key, and each voxel's sum adds its points in the canonical order
    (x, then y, then z: :func:`stemmap.cloud.canonical.canonical_order`), so the output is the
    same to the last bit in any order of the input points (floating-point addition is not
    associative: in file order the means of a dense TLS slice moved by up to 6e-14 m between
    point orders; docs/algorithms/cloud.md, "Point order", munjer2025).
    """
    from stemmap.cloud.canonical import canonical_order

    p = as_xyz(xyz)
    if not voxel > 0:
        raise ConfigError(f"voxel size must be > 0 m, got {voxel}.")
    if p.shape[0] == 0:
        empty = np.zeros((0, 3))
        return (empty, np.zeros(0, dtype=np.int64)) if return_counts else empty
    if p.shape[0] > 1:
        p = p[canonical_order(p[:, 0], p[:, 1], p[:, 2])]
    keys = voxel_keys(p, voxel)
    _, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    m = counts.shape[0]
    out = np.empty((m, 3))
    for k in range(3):
        out[:, k] = np.bincount(inv, weights=p[:, k], minlength=m) / counts
    return (out, counts.astype(np.int64)) if return_counts else out


def point_spacing(
    xyz: ArrayLike, *, sample: int = 20_000, rng: np.random.Generator | int | None = 0
) -> float:
    """Typical point spacing: the median distance from a point to its nearest neighbour.

    Computed on a random sample of at most ``sample`` query points against the whole cloud, so
    it costs O(N log N) for the tree and O(sample log N) for the queries. Duplicate points
    (distance 0) are ignored. Returns NaN for fewer than 2 distinct points.
    """
    p = as_xyz(xyz)
    if p.shape[0] < 2:
        return math.nan
    gen = np.random.default_rng(rng)
    q = p if p.shape[0] <= sample else p[gen.choice(p.shape[0], sample, replace=False)]
    tree = cKDTree(p)
    d, _ = tree.query(q, k=4)
    d = d[:, 1:]
    pos = np.where(d > 1e-9, d, np.inf).min(axis=1)
    pos = pos[np.isfinite(pos)]
    return float(np.median(pos)) if pos.size else math.nan
