"""Ground model and height normalisation (ours).

The ground is a raster of cell minima, cleaned of low outliers and of cells without ground
returns (a trunk or a shrub filling a cell), gaps filled from the nearest cell, and evaluated by
bilinear interpolation between cell centres. It can be built in one pass over a stream of
chunks (:class:`GroundAccumulator`), so a 20-million-point file never sits in memory.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from stemmap.cloud._grid_kernel import bilinear_nearest, heights_in_band, lowest_per_cell
from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_MAX_MEMORY",
    "GroundAccumulator",
    "GroundModel",
    "cell_index",
    "core_cells",
    "fit_ground",
    "normalize_heights",
    "raster_guard",
]

DEFAULT_MAX_MEMORY = 4e9  # bytes: the rasters of one run (ground grid, clustering grid)
# bytes per ground cell while the model is built: ~40 float64 rasters of the cell grid (cell
# minima, median, box sums, the 3 x 3 normal matrices and their solve)
_GROUND_BYTES_PER_CELL = 40 * 8
BASE_GROUND = "ground"
BASE_STEM = "lowest stem points"


@dataclass(frozen=True, eq=False)
class GroundModel:
    """Ground heights on a regular grid.

    Attributes
    ----------
    origin : (x0, y0), metres; lower-left corner of cell (0, 0)
    cell : float, metres
    z : ndarray (nx, ny), metres; ground height at cell centres
    base : str -- how heights are referenced: ``"ground"`` (a ground raster from the cloud's
        lowest points) or ``"lowest stem points"`` (a cloud without ground, e.g. one tree
        segmented by 3DFin, TreeQSM or ITSMe: a flat base at its stem's lowest points)
    observed : ndarray (nx, ny) of bool, optional -- cells that held points (the others were
        filled from the nearest cell); None for a flat base
    """

    origin: tuple[float, float]
    cell: float
    z: FloatArray
    base: str = BASE_GROUND
    observed: NDArray[np.bool_] | None = None

    @property
    def flat_z(self) -> float:
        """z of the flat base of a cloud without ground (base ``"lowest stem points"``), NaN
        for a ground raster: what the summary of a run states its heights came from."""
        return float(self.z.flat[0]) if self.base == BASE_STEM else math.nan

    def height_of(self, xyz: ArrayLike) -> FloatArray:
        """Height above ground of (N, 3) points (bilinear between cell centres, clamped)."""
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        return np.asarray(p[:, 2] - self.ground_at(p[:, :2]), dtype=np.float64)

    def band_of(self, xyz: ArrayLike, lo: float, hi: float) -> tuple[FloatArray, NDArray[np.int64]]:
        """Heights of (N, 3) points (:meth:`height_of`) and the indices, in point order, of
        those with ``lo <= h <= hi`` (the detector's slice band) -- in one compiled pass
        (:func:`~stemmap.cloud._grid_kernel.heights_in_band`), the same values."""
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        fast = heights_in_band(self.z, self.origin, self.cell, p, lo, hi)
        if fast is not None:
            return fast
        h = self.height_of(p)
        return h, np.flatnonzero((h >= lo) & (h <= hi))

    def ground_at(self, xy: ArrayLike) -> FloatArray:
        """Ground z at (N, 2) positions."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        fast = bilinear_nearest(self.z, self.origin, self.cell, q[:, 0], q[:, 1])
        if fast is not None:
            return fast
        fi = (q[:, 0] - self.origin[0]) / self.cell - 0.5
        fj = (q[:, 1] - self.origin[1]) / self.cell - 0.5
        return np.asarray(
            ndimage.map_coordinates(self.z, [fi, fj], order=1, mode="nearest"),
            dtype=np.float64,
        )


def core_cells(ij: NDArray[np.int64], pad: int = 2) -> NDArray[np.bool_]:
    """Cells inside the robust extent of a set of occupied cells (``ij``, (M, 2) indices).

    The extent is the 0.1-99.9 % quantile box of the occupied cells, grown by 10 % of its
    size plus ``pad`` cells on every side: a stray point kilometres away (a GNSS glitch, a
    UTM cloud with one point at 0, 0, 0) falls outside and cannot make a raster span the
    kilometres in between; the edge cells of a real plot stay inside.
    """
    if ij.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    lo = np.floor(np.quantile(ij, 0.001, axis=0))
    hi = np.ceil(np.quantile(ij, 0.999, axis=0))
    grow = 0.1 * (hi - lo) + pad
    return np.asarray(np.all((ij >= lo - grow) & (ij <= hi + grow), axis=1), dtype=bool)


def raster_guard(n_cells: int, bytes_per_cell: float, budget: float, what: str, fix: str) -> None:
    """InputError when a raster of ``n_cells`` cells would need more than ``budget`` bytes."""
    need = float(n_cells) * bytes_per_cell
    if need > budget:
        raise InputError(
            f"{what} would need {need / 1e9:.1f} GB ({n_cells} cells), above the memory "
            f"budget of {budget / 1e9:.1f} GB; {fix}"
        )


_SUPPORT = 0.1  # m: points this close above a cell's minimum support it
# a stem base lies inside the middle of its cloud: beyond the 10 % quantile of the occupied
# cells (grown by one stem footprint) on no side (docs/algorithms/cloud.md "Thinned plots")
_EDGE = 0.1
_OFF = 1 << 30  # cell indices are shifted to be non-negative before packing into int64 keys


def cell_index(ij: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The distinct cells of (N, 2) integer cell indices, sorted by (i, j), and the position
    of each point's cell among them: ``np.unique`` of the packed keys, without its sort.

    Points of a plot or a chunk fill a compact block of cells, so the cells are found by
    marking a dense occupancy array over their bounding box (linear time); a block much
    larger than the points (stray points far away) falls back to ``np.unique``. Both give
    the same cells in the same order and the same inverse.
    """
    n = ij.shape[0]
    if n == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64)
    lo = ij.min(axis=0)
    span = ij.max(axis=0) - lo + 1
    if float(span[0]) * float(span[1]) > 4.0 * n + 1_000_000:
        keys = ((ij[:, 0] + _OFF) << 32) | (ij[:, 1] + _OFF)
        uk, inv = np.unique(keys, return_inverse=True)
        cells = np.column_stack(((uk >> 32) - _OFF, (uk & 0xFFFFFFFF) - _OFF))
        return cells.astype(np.int64), inv.reshape(-1).astype(np.int64)
    d = (ij[:, 0] - lo[0]) * span[1] + (ij[:, 1] - lo[1])
    occ = np.zeros(int(span[0] * span[1]), dtype=bool)
    occ[d] = True
    flat = np.flatnonzero(occ)
    rank = np.cumsum(occ, dtype=np.int64) - 1
    cells = np.column_stack((flat // span[1] + lo[0], flat % span[1] + lo[1]))
    return cells.astype(np.int64), rank[d]


def _three_lowest(z: FloatArray, grp: NDArray[np.int64], n: int) -> FloatArray:
    """The three lowest values of ``z`` in each of the ``n`` groups ``grp`` (ascending, inf
    where a group holds fewer)."""
    o = np.lexsort((z, grp))
    g, v = grp[o], z[o]
    rank = np.arange(g.size) - np.searchsorted(g, g)
    keep = rank < 3
    out = np.full((n, 3), np.inf)
    out[g[keep], rank[keep]] = v[keep]
    return out


class GroundAccumulator:
    """Per-cell minimum z over a stream of chunks; :meth:`model` builds the GroundModel."""

    def __init__(self, cell: float = 1.0, max_memory: float = DEFAULT_MAX_MEMORY) -> None:
        if not cell > 0:
            raise ConfigError(f"ground cell must be > 0 m, got {cell}.")
        if not max_memory > 0:
            raise ConfigError(f"max_memory must be > 0 bytes, got {max_memory}.")
        self.cell = float(cell)
        self.max_memory = float(max_memory)
        self._keys = np.zeros(0, dtype=np.int64)
        self._low = np.zeros((0, 3))  # lowest point of each cell
        self._z3 = np.zeros((0, 3))  # its three lowest z, ascending (inf: fewer points)

    @property
    def _sup(self) -> NDArray[np.int64]:
        """Support of each cell's minimum: its points within ``_SUPPORT`` above it, counted
        up to 3 (the tests ask only whether it is below 3)."""
        return np.sum(self._z3 <= self._z3[:, :1] + _SUPPORT, axis=1).astype(np.int64)

    def update(self, xyz: ArrayLike) -> None:
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if p.shape[0] == 0:
            return
        # reduce the chunk to its lowest point and three lowest z per cell first (one pass on
        # a dense grid; cell_index and a sort of the chunk when its points spread too far for
        # one), then merge with the running ones. Both are exact over
        # chunks, so the accumulator does not depend on how the points were split or ordered.
        low = lowest_per_cell(p[:, 0], p[:, 1], p[:, 2], self.cell)
        if low is not None:
            cells, sel, z3 = low
            new = ((cells[:, 0] + _OFF) << 32) | (cells[:, 1] + _OFF)
        else:
            ij = np.floor(p[:, :2] / self.cell).astype(np.int64)
            cells, inv = cell_index(ij)
            uk = ((cells[:, 0] + _OFF) << 32) | (cells[:, 1] + _OFF)
            zmin = np.full(uk.shape[0], np.inf)
            np.minimum.at(zmin, inv, p[:, 2])
            cand = np.flatnonzero(p[:, 2] == zmin[inv])
            # equal minima: the smallest x, then y (lowest_per_cell's choice)
            cand = cand[np.lexsort((p[cand, 1], p[cand, 0], inv[cand]))]
            _, first = np.unique(inv[cand], return_index=True)
            sel = cand[first]
            z3 = _three_lowest(p[:, 2], inv, uk.shape[0])
            new = uk[inv[sel]]
        keys = np.concatenate((self._keys, new))
        pts = np.concatenate((self._low, p[sel]))
        z3 = np.concatenate((self._z3, z3))
        # per cell the lowest point, of equal minima the smallest x, then y: the same point
        # whichever chunk (and whatever point order) it came in
        order = np.lexsort((pts[:, 1], pts[:, 0], pts[:, 2], keys))
        keys, pts, z3 = keys[order], pts[order], z3[order]
        first = np.ones(keys.shape[0], dtype=bool)
        first[1:] = keys[1:] != keys[:-1]
        if not first.all():  # cells seen before: the three lowest of their rows' values
            grp = np.cumsum(first) - 1
            z3 = _three_lowest(z3.ravel(), np.repeat(grp, 3), int(grp[-1]) + 1)
        self._keys, self._low, self._z3 = keys[first], pts[first], z3

    def stem_base(self, max_width: float, slab: float = 0.5) -> float | None:
        """Base z of a cloud without ground (one segmented tree), or None if it has ground.

        The lowest points of the cells (the accumulator's minima) within ``slab`` metres of
        the cloud's lowest point are the ground where there is ground: they spread over the
        plot (a 2.5 m TLS cut-out of one spruce: 2.5 m). Cells far outside the cloud
        (:func:`core_cells`) and minima with fewer than 3 points within 0.1 m above them (a
        lone noise point below the ground) are left out. A tree exported without ground
        (3DFin, TreeQSM, ITSMe) has only its stem's cut there: they fit inside one stem
        footprint, ``max_width`` (the largest plausible DBH). Then the base is that lowest
        point, and heights are measured from it -- if it lies inside its cloud: a tree's
        crown and branches spread around its stem (archi Tree_1 / Tree_2, treels pine cut
        above its ground: at least 17 % of the occupied cells on every side of the base, at
        every thinning), while the lowest returns of a sloped plot lie at its downhill edge,
        where a thinned or distant scan can leave one pair of sparse points that fits in a
        footprint (the simulated single-scan plot at 10 %: 2 % of the cells beyond it). A
        base more than ``max_width`` outside the 10-90 % quantile box of the occupied cells
        is such an edge: the cloud has ground.
        """
        if self._keys.size == 0:
            return None
        i = (self._keys >> 32) - _OFF
        j = (self._keys & 0xFFFFFFFF) - _OFF
        # stray points far away, and lone noise points below the ground (support < 3 and
        # more than ``slab`` below every neighbouring cell's minimum), are no base
        zc = self._low[:, 2]
        nbr = np.full(zc.shape[0], np.inf)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                if di == dj == 0:
                    continue
                k2 = ((i + di + _OFF) << 32) | (j + dj + _OFF)
                pos = np.clip(np.searchsorted(self._keys, k2), 0, self._keys.size - 1)
                hit = self._keys[pos] == k2
                nbr = np.where(hit, np.minimum(nbr, zc[pos]), nbr)
        lone = (self._sup < 3) & (zc < nbr - slab)
        ok = core_cells(np.column_stack((i, j))) & ~lone
        if not ok.any():
            return None
        cells = self._low[ok]
        z0 = float(cells[:, 2].min())
        low = cells[cells[:, 2] <= z0 + slab, :2]
        if float(np.max(np.ptp(low, axis=0))) > max_width:
            return None
        # a tree's points lie around its stem; a plot's lowest points can be a pair of sparse
        # returns at its downhill edge (a thinned scan of a sloped plot, docs "thinned plots")
        lo, hi = np.quantile(cells[:, :2], [_EDGE, 1.0 - _EDGE], axis=0)
        if np.any(low.min(axis=0) < lo - max_width) or np.any(low.max(axis=0) > hi + max_width):
            return None
        return z0

    def flat(self, z: float, base: str) -> GroundModel:
        """A flat 'ground' at ``z`` (one cell; ``base`` says what it is)."""
        return GroundModel((0.0, 0.0), self.cell, np.full((1, 1), float(z)), base)

    def model(
        self,
        *,
        max_step: float = 0.5,
        extent: tuple[float, float, float, float] | None = None,
    ) -> GroundModel:
        """Clean and fill the minima raster.

        A cell more than ``max_step`` metres above the median of its 3 x 3 neighbourhood holds
        no ground (trunk, shrub) and one more than ``max_step`` below it is a low outlier: both
        take the neighbourhood median.

        The raster spans the occupied cells' bounding box, grown to the cells of ``extent``
        ((xmin, ymin, xmax, ymax), metres) when given: a tile engine's chunk passes the part
        of the catalog's box its buffer covers, so near a data edge inside that box (a
        catalog corner) its raster holds the same empty, filled cells as the whole cloud's
        and the ground there does not depend on where the chunk was cut
        (docs/algorithms/engine.md).
        """
        if self._keys.size == 0:
            raise InputError("cannot build a ground model from an empty cloud.")
        i = (self._keys >> 32) - _OFF
        j = (self._keys & 0xFFFFFFFF) - _OFF
        low = self._low
        core = core_cells(np.column_stack((i, j)))
        if not core.all():
            log.warning(
                "ground: %d of %d occupied %.1f m cells lie far outside the cloud's extent "
                "(stray points); the ground raster covers the rest, and they get the nearest "
                "ground",
                int((~core).sum()),
                core.size,
                self.cell,
            )
            i, j, low = i[core], j[core], low[core]
        sup = self._sup if core.all() else self._sup[core]
        i0, j0, i1, j1 = int(i.min()), int(j.min()), int(i.max()), int(j.max())
        if extent is not None:
            e = np.floor(np.asarray(extent, dtype=np.float64) / self.cell)
            i0, j0 = min(i0, int(e[0])), min(j0, int(e[1]))
            i1, j1 = max(i1, int(e[2])), max(j1, int(e[3]))
        nx, ny = i1 - i0 + 1, j1 - j0 + 1
        raster_guard(
            nx * ny,
            _GROUND_BYTES_PER_CELL,
            self.max_memory,
            f"the ground raster ({nx} x {ny} cells of {self.cell:g} m)",
            "tile the cloud into smaller plots, or raise --max-memory.",
        )
        ox, oy = i0 * self.cell, j0 * self.cell
        grid = np.full((3, nx, ny), np.nan)
        grid[:, i - i0, j - j0] = (low - [ox, oy, 0.0]).T
        X, Y, Z = grid
        observed = ~np.isnan(Z)
        support = np.zeros((nx, ny), dtype=np.int64)
        support[i - i0, j - j0] = sup
        valid = observed & ~_groundless_cells(Z, support, self.cell, max_step)
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
        return GroundModel((ox, oy), self.cell, z + 0.0, observed=observed)


def _groundless_cells(
    z: FloatArray, support: NDArray[np.int64], cell: float, max_step: float
) -> NDArray[np.bool_]:
    """Cells of the minima raster ``z`` (NaN: empty) that hold no ground: canopy or a stem
    overhanging the edge of the scanned ground (a plot clipped in a tilted frame, crowns
    leaning past a plot's edge, an unlevelled scanner), whose minimum is a crown or a branch.

    Grown from the ground: a cell whose minimum lies more than ``max_step`` + 1 m per metre
    of distance (a 45 degree slope) above a neighbour's ground (8-neighbourhood) holds none;
    it is filled from the nearest ground cell and the test is repeated until no cell
    changes, so a strip of overhanging canopy several cells wide is found from its ground
    side. The median test of :meth:`GroundAccumulator.model` cannot see it: along a plot edge
    most of an edge cell's 3 x 3 neighbourhood is canopy. Lone low noise points (fewer than 3
    points within 0.1 m above them, more than ``max_step`` below every neighbour's minimum,
    as in :meth:`GroundAccumulator.stem_base`) are never the ground others are compared
    with. On the real clouds of ../shared/datasets as shipped no cell is found
    (docs/algorithms/cloud.md, "Robustness to user exports").
    """
    observed = ~np.isnan(z)
    zi = np.where(observed, z, np.inf)
    ring = np.ones((3, 3), dtype=bool)
    ring[1, 1] = False
    nbr = ndimage.grey_erosion(zi, footprint=ring, mode="constant", cval=np.inf)
    lone = observed & (support < 3) & (zi < nbr - max_step)
    ground = observed & ~lone
    # 1 m per metre of distance to each of the 8 neighbours, 0 at the centre
    d = cell * np.hypot(*np.mgrid[-1:2, -1:2])
    for _ in range(z.shape[0] + z.shape[1]):
        if not ground.any():
            break
        zf = z
        if not ground.all():
            _, (fi, fj) = ndimage.distance_transform_edt(~ground, return_indices=True)
            zf = z[fi, fj]
        env = ndimage.grey_erosion(zf, structure=-d, mode="nearest")
        high = ground & (z > env + max_step)
        if not high.any():
            break
        ground &= ~high
    return np.asarray(observed & ~ground & ~lone, dtype=bool)


def fit_ground(
    xyz: ArrayLike,
    cell: float = 1.0,
    *,
    max_step: float = 0.5,
    max_memory: float = DEFAULT_MAX_MEMORY,
) -> GroundModel:
    """Ground model of an in-memory cloud (see :class:`GroundAccumulator`)."""
    acc = GroundAccumulator(cell, max_memory)
    acc.update(xyz)
    return acc.model(max_step=max_step)


def normalize_heights(xyz: ArrayLike, ground: GroundModel) -> NDArray[np.float64]:
    """Copy of ``xyz`` with z replaced by the height above ``ground``."""
    p = np.array(xyz, dtype=np.float64).reshape(-1, 3)
    p[:, 2] = ground.height_of(p)
    return p
