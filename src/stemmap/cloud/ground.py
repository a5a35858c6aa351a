"""Ground model and height normalisation (ours).

The ground is a raster of cell minima, cleaned of low outliers and of cells without ground
returns (a trunk or a shrub filling a cell), gaps filled from the nearest cell, and evaluated by
bilinear interpolation between cell centres. It can be built in one pass over a stream of
chunks (:class:`GroundAccumulator`), so a 20-million-point file never sits in memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = ["GroundAccumulator", "GroundModel", "fit_ground", "normalize_heights"]


@dataclass(frozen=True, eq=False)
class GroundModel:
    """Ground heights on a regular grid.

    Attributes
    ----------
    origin : (x0, y0), metres; lower-left corner of cell (0, 0)
    cell : float, metres
    z : ndarray (nx, ny), metres; ground height at cell centres
    """

    origin: tuple[float, float]
    cell: float
    z: FloatArray

    def height_of(self, xyz: ArrayLike) -> FloatArray:
        """Height above ground of (N, 3) points (bilinear between cell centres, clamped)."""
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        return np.asarray(p[:, 2] - self.ground_at(p[:, :2]), dtype=np.float64)

    def ground_at(self, xy: ArrayLike) -> FloatArray:
        """Ground z at (N, 2) positions."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        fi = (q[:, 0] - self.origin[0]) / self.cell - 0.5
        fj = (q[:, 1] - self.origin[1]) / self.cell - 0.5
        return np.asarray(
            ndimage.map_coordinates(self.z, [fi, fj], order=1, mode="nearest"),
            dtype=np.float64,
        )


_OFF = 1 << 30  # cell indices are shifted to be non-negative before packing into int64 keys


class GroundAccumulator:
    """Per-cell minimum z over a stream of chunks; :meth:`model` builds the GroundModel."""

    def __init__(self, cell: float = 1.0) -> None:
        if not cell > 0:
            raise ConfigError(f"ground cell must be > 0 m, got {cell}.")
        self.cell = float(cell)
        self._keys = np.zeros(0, dtype=np.int64)
        self._low = np.zeros((0, 3))  # lowest point of each cell

    def update(self, xyz: ArrayLike) -> None:
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if p.shape[0] == 0:
            return
        ij = np.floor(p[:, :2] / self.cell).astype(np.int64)
        ij += _OFF
        keys = (ij[:, 0] << 32) | ij[:, 1]
        # reduce the chunk to its lowest point per cell first (one int sort + ufunc.at, much
        # cheaper than a lexsort of the whole chunk), then merge with the running minima
        uk, inv = np.unique(keys, return_inverse=True)
        zmin = np.full(uk.shape[0], np.inf)
        np.minimum.at(zmin, inv, p[:, 2])
        cand = np.flatnonzero(p[:, 2] == zmin[inv])
        _, first = np.unique(inv[cand], return_index=True)
        sel = cand[first]
        keys = np.concatenate((self._keys, keys[sel]))
        pts = np.concatenate((self._low, p[sel]))
        order = np.lexsort((pts[:, 2], keys))
        keys, pts = keys[order], pts[order]
        first = np.ones(keys.shape[0], dtype=bool)
        first[1:] = keys[1:] != keys[:-1]
        self._keys, self._low = keys[first], pts[first]

    def model(self, *, max_step: float = 0.5) -> GroundModel:
        """Clean and fill the minima raster.

        A cell more than ``max_step`` metres above the median of its 3 x 3 neighbourhood holds
        no ground (trunk, shrub) and one more than ``max_step`` below it is a low outlier: both
        take the neighbourhood median.
        """
        if self._keys.size == 0:
            raise InputError("cannot build a ground model from an empty cloud.")
        i = (self._keys >> 32) - _OFF
        j = (self._keys & 0xFFFFFFFF) - _OFF
        i0, j0 = int(i.min()), int(j.min())
        nx, ny = int(i.max() - i0 + 1), int(j.max() - j0 + 1)
        ox, oy = i0 * self.cell, j0 * self.cell
        grid = np.full((3, nx, ny), np.nan)
        grid[:, i - i0, j - j0] = (self._low - [ox, oy, 0.0]).T
        X, Y, Z = grid
        valid = ~np.isnan(Z)
        if not valid.all():
            _, (fi, fj) = ndimage.distance_transform_edt(~valid, return_indices=True)
            Z = Z[fi, fj]
        med = ndimage.median_filter(Z, size=3, mode="nearest")
        good = valid & (np.abs(Z - med) <= max_step)
        # local plane through the lowest points of the 3 x 3 neighbourhood, evaluated at the
        # cell centre: removes the bias of a raw cell minimum on a slope (it sits at the cell's
        # low edge, slope x cell / 2 below the centre)
        w = good.astype(np.float64)
        Xg, Yg, Zg = (np.where(good, a, 0.0) for a in (X, Y, Z))
        k = np.ones((3, 3))

        def box_sum(a: FloatArray) -> FloatArray:
            return np.asarray(ndimage.convolve(a, k, mode="constant"), dtype=np.float64)

        s1, sx, sy, sz = box_sum(w), box_sum(Xg), box_sum(Yg), box_sum(Zg)
        sxx, sxy, syy = box_sum(Xg * Xg), box_sum(Xg * Yg), box_sum(Yg * Yg)
        sxz, syz = box_sum(Xg * Zg), box_sum(Yg * Zg)
        A = np.stack(
            (
                np.stack((sxx, sxy, sx), -1),
                np.stack((sxy, syy, sy), -1),
                np.stack((sx, sy, s1), -1),
            ),
            -2,
        )
        b = np.stack((sxz, syz, sz), -1)
        det = np.linalg.det(A)
        scale = np.maximum(s1, 1.0) ** 3 * self.cell**4
        solvable = (s1 >= 4) & (np.abs(det) > 1e-9 * scale)
        coef = np.zeros_like(b)
        if solvable.any():
            coef[solvable] = np.linalg.solve(A[solvable], b[solvable][..., None])[..., 0]
        xc = (np.arange(nx)[:, None] + 0.5) * self.cell * np.ones((1, ny))
        yc = (np.arange(ny)[None, :] + 0.5) * self.cell * np.ones((nx, 1))
        plane = coef[..., 0] * xc + coef[..., 1] * yc + coef[..., 2]
        z = np.where(solvable, plane, np.where(good, Z, med))
        return GroundModel((ox, oy), self.cell, z + 0.0)


def fit_ground(xyz: ArrayLike, cell: float = 1.0, *, max_step: float = 0.5) -> GroundModel:
    """Ground model of an in-memory cloud (see :class:`GroundAccumulator`)."""
    acc = GroundAccumulator(cell)
    acc.update(xyz)
    return acc.model(max_step=max_step)


def normalize_heights(xyz: ArrayLike, ground: GroundModel) -> NDArray[np.float64]:
    """Copy of ``xyz`` with z replaced by the height above ``ground``."""
    p = np.array(xyz, dtype=np.float64).reshape(-1, 3)
    p[:, 2] = ground.height_of(p)
    return p
