"""The slice band (ours, docs/algorithms/cloud.md "Ours" steps 3-5): the points around breast
height, their slices (thicker for sparse clouds), the vertical-consistency filter that removes
branches and foliage, and the grid clustering of what is left into stem candidates."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.config import StemConfig
from stemmap.cloud.ground import BASE_GROUND, core_cells, raster_guard
from stemmap.types import FloatArray

log = logging.getLogger(__name__)

#: clusters within this many maximum diameters of a requested region are fitted (a stem's
#: centre lies within half a diameter of its cluster, a duplicate within half a diameter of
#: the stem it suppresses: 2 diameters leave a margin for chains of both)
REGION_MARGIN = 2.0
_CLUSTER_BYTES_PER_CELL = 16  # occupancy + dilation (bool), labels (int32), temporaries


@dataclass
class _Band:
    """Points of the slice band: xy, height above ground, absolute z; a canopy raster; and
    optionally each point's sensor position (xy)."""

    xy: FloatArray
    h: FloatArray
    z: FloatArray
    canopy: dict[str, Any] = field(default_factory=dict)
    origins: FloatArray | None = None  # (N, 2) horizontal sensor position of each point
    base: str = BASE_GROUND  # what the heights h are measured from (GroundModel.base)
    base_z: float = math.nan  # z of a flat base (GroundModel.flat_z), NaN for a ground raster
    # xy and heights of the returns in the shared-axis fit's range outside the band (only
    # with StemConfig.axis_fallback and axis_reach: :mod:`~stemmap.cloud.axisfit`)
    reach: tuple[FloatArray, FloatArray] | None = None


@dataclass(frozen=True)
class _BandPoints:
    """Band points on their way to the clusters: xy, height, slice index (-1: between
    slices), and each point's sensor position (xy) when known."""

    xy: FloatArray
    h: FloatArray
    sl: NDArray[np.int64]
    origins: FloatArray | None

    def take(self, mask: NDArray[np.bool_]) -> _BandPoints:
        """The points where ``mask`` is true."""
        o = None if self.origins is None else self.origins[mask]
        return _BandPoints(self.xy[mask], self.h[mask], self.sl[mask], o)


def _adapt_slices(cfg: StemConfig, spacing: float) -> StemConfig:
    """Thicker, fewer slices over the same band when the cloud is sparse.

    A slice must be at least ``slices_per_spacing`` point spacings thick so that a trunk side
    holds enough points for a fit; the band (first to last slice edge) is kept and cut into as
    many equal slices of at least that thickness as fit, never fewer than 3.
    """
    lo, hi = cfg.band
    need = max(cfg.slice_thickness, cfg.slices_per_spacing * spacing)
    if need <= cfg.slice_thickness + 1e-12:
        return cfg
    n = max(3, int((hi - lo) // need))
    th = (hi - lo) / n
    centers = tuple(float(lo + th * (k + 0.5)) for k in range(n))
    log.info("sparse cloud (spacing %.3f m): %d slices of %.2f m", spacing, n, th)
    return replace(cfg, slice_centers=centers, slice_thickness=th)


#: the fewest inliers of a guided refit held to the density's count (three circle parameters
#: and two degrees of freedom for the residual; slicestem.MIN_ANNULUS_POINTS)
MIN_DENSITY_POINTS = 5


def density_slice_points(cfg: StemConfig, thickness: float, spacing: float) -> int:
    """Inliers a slice ``thickness`` thick can be asked to hold on a stem's side in a cloud
    of measured ``spacing`` (StemConfig.density_slice_points).

    :func:`_adapt_slices` makes a slice ``cfg.slices_per_spacing`` spacings thick so that a
    stem's side in it holds the ``cfg.min_slice_points`` returns a circle fit needs among the
    clutter. A slice thinner than that -- the default 0.2 m slices of a thickened band, or a
    band held at three slices where the spacing asks for more than 0.4 m -- holds about
    thickness / (``slices_per_spacing`` x spacing) of that count on the same stem:
    ``ceil(min_slice_points x thickness / (slices_per_spacing x spacing))``, at least
    :data:`MIN_DENSITY_POINTS`, never above ``min_slice_points`` (a dense cloud keeps its
    count)."""
    design = cfg.slices_per_spacing * spacing
    if not (design > thickness and math.isfinite(design)):
        return cfg.min_slice_points
    scaled = math.ceil(cfg.min_slice_points * thickness / design - 1e-9)
    return min(cfg.min_slice_points, max(MIN_DENSITY_POINTS, scaled))


def _slice_of(h: FloatArray, centers_h: FloatArray, thickness: float) -> NDArray[np.int64]:
    """Slice of each point: the index of the nearest slice centre within half a
    ``thickness`` of its height ``h``, -1 for a point between or outside the slices."""
    near = np.argmin(np.abs(h[:, None] - centers_h[None, :]), axis=1)
    return np.where(np.abs(h - centers_h[near]) <= thickness / 2, near, -1)


def _grid_cells(
    xy: FloatArray, cell: float, origin: tuple[float, float] | None
) -> NDArray[np.int64]:
    """(N, 2) cell indices of ``xy`` on a grid of ``cell`` metres, offset to start at 0.

    Without ``origin`` the grid is anchored at the points' minimum (a shifted copy of a cloud
    gets the same cells: georeferenced and local coordinates give the same stems). With
    ``origin`` (``StemConfig.grid_origin``) cell edges lie at ``origin + k * cell``: a point
    falls in the same cell whatever part of the cloud is processed -- the tile engine passes
    one origin for the whole catalog, so a chunk sees the cells of a single process.
    """
    lo = xy.min(axis=0) if origin is None else np.asarray(origin, dtype=np.float64)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    if origin is not None:
        ij -= ij.min(axis=0)
    return ij


def _vertical_filter(
    xy: FloatArray,
    sl: NDArray[np.int64],
    ns: int,
    cell: float,
    origin: tuple[float, float] | None = None,
) -> NDArray[np.bool_]:
    """Keep points whose 2D cell is occupied in at least half of the slices (>= 2).

    A trunk's surface projects onto the same cells at every height of the band; branches,
    needles and leaves occupy a cell at one or two heights only. Removing them before
    clustering keeps them out of the circle fits (a spruce whorl otherwise swamps its stem).
    The cell (3-10 cm) tolerates the lean of a stem between adjacent slices. Cells are those
    of :func:`_grid_cells` (anchored at ``origin``, or at the points' minimum).
    """
    ij = _grid_cells(xy, cell, origin)
    ny = int(ij[:, 1].max()) + 1
    key = ij[:, 0] * ny + ij[:, 1]
    ok = sl >= 0
    pair = np.unique(key[ok] * ns + sl[ok])
    cell_keys, n_sl = np.unique(pair // ns, return_counts=True)
    need = max(2, (ns + 1) // 2)
    good_cells = cell_keys[n_sl >= need]
    return np.asarray(ok & np.isin(key, good_cells), dtype=bool)


def _sliced_points(
    band: _Band, cfg: StemConfig, centers_h: FloatArray, cell: float, slice_cloud: bool
) -> _BandPoints:
    """Step 3-4: the band points inside a slice that pass the vertical-consistency filter
    (:func:`_vertical_filter` on a grid of ``cell`` clipped to 3-10 cm; not for a pre-cut
    slice cloud, nor with fewer than 3 slices)."""
    ns = centers_h.shape[0]
    sl_all = _slice_of(band.h, centers_h, cfg.slice_thickness)
    keep = sl_all >= 0
    if not slice_cloud and ns >= 3:
        origin = cfg.filter_origin if cfg.filter_origin is not None else cfg.grid_origin
        keep &= _vertical_filter(band.xy, sl_all, ns, float(np.clip(cell, 0.03, 0.1)), origin)
    return _BandPoints(band.xy, band.h, sl_all, band.origins).take(keep)


def _drop_strays(pts: _BandPoints, *, quiet: bool = False) -> _BandPoints:
    """Stray band points far outside the cloud (outside :func:`~stemmap.cloud.ground.
    core_cells` of 1 m cells) cannot hold a stem and must not stretch the clustering grid."""
    core = core_cells(np.floor(pts.xy / 1.0).astype(np.int64))
    if core.all():
        return pts
    if not quiet:
        log.warning("%d stray band point(s) far outside the cloud ignored", int((~core).sum()))
    return pts.take(core)


def _grid_anchors(
    band: _Band, cfg: StemConfig, spacing: float, slice_cloud: bool
) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The points a run without ``grid_origin`` anchors its grids at (:func:`_grid_cells`):
    the vertical filter's at the band's minimum, the clustering grid's at the minimum of
    the points the filter keeps (strays dropped) -- the steps of
    :func:`~stemmap.cloud.measure._stems_from_band` up to the clustering, with the measured
    ``spacing``. None when no point is left. Passed as ``StemConfig.filter_origin`` and
    ``grid_origin`` of a part of the cloud (a tile engine's chunk) they give it the whole
    cloud's cells (:func:`stemmap.engine.pilot_statistics`)."""
    if band.xy.shape[0] == 0 or not math.isfinite(spacing):
        return None
    cell = float(np.clip(cfg.cluster_cell_factor * spacing, 0.01, 0.25))
    if not slice_cloud and cfg.slices_per_spacing > 0:
        cfg = _adapt_slices(cfg, spacing)
    cfg = replace(cfg, grid_origin=None, filter_origin=None)
    centers_h = np.asarray(cfg.slice_centers, dtype=np.float64)
    pts = _drop_strays(_sliced_points(band, cfg, centers_h, cell, slice_cloud), quiet=True)
    if pts.xy.shape[0] == 0:
        return None
    lo_f, lo_c = band.xy.min(axis=0), pts.xy.min(axis=0)
    return (float(lo_f[0]), float(lo_f[1])), (float(lo_c[0]), float(lo_c[1]))


def _label_clusters(xy: FloatArray, cell: float, cfg: StemConfig) -> tuple[NDArray[np.int64], int]:
    """Step 5, stem clustering: 8-connected components of the occupancy grid of ``cell``
    metres dilated by one cell (bridges one empty cell, like DBSCAN with eps of two cells;
    linear time, no neighbour lists). Returns each point's component and their number. The
    grid's memory is checked against ``cfg.max_memory`` first."""
    from scipy import ndimage

    ij = _grid_cells(xy, cell, cfg.grid_origin)
    shape = ij.max(axis=0) + 1
    raster_guard(
        int(shape[0]) * int(shape[1]),
        _CLUSTER_BYTES_PER_CELL,
        cfg.max_memory,
        f"the clustering grid of the slice band ({shape[0] * cell:.0f} x "
        f"{shape[1] * cell:.0f} m at {cell:.3f} m)",
        "tile the cloud into smaller plots, or raise --max-memory.",
    )
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    occ = np.zeros(int(shape[0]) * int(shape[1]), dtype=bool)
    occ[flat] = True
    occ2 = occ.reshape(int(shape[0]), int(shape[1]))
    dil = ndimage.binary_dilation(occ2, structure=np.ones((3, 3), bool))
    lab_img, n_lab = ndimage.label(dil, structure=np.ones((3, 3), bool))
    return lab_img.ravel()[flat].astype(np.int64) - 1, int(n_lab)


def _candidate_clusters(
    xy: FloatArray,
    lab: NDArray[np.int64],
    n_lab: int,
    cell: float,
    cfg: StemConfig,
    region: tuple[float, float, float, float] | None,
) -> NDArray[np.bool_]:
    """Clusters worth fitting: at least ``cfg.min_slice_points`` points and a footprint of
    at most 3 maximum diameters (+ 2 cells); with ``region``, only those whose bounding box
    comes within :data:`REGION_MARGIN` maximum diameters of it."""
    counts = np.bincount(lab, minlength=n_lab)
    xmin = np.full(n_lab, np.inf)
    xmax = np.full(n_lab, -np.inf)
    ymin = np.full(n_lab, np.inf)
    ymax = np.full(n_lab, -np.inf)
    np.minimum.at(xmin, lab, xy[:, 0])
    np.maximum.at(xmax, lab, xy[:, 0])
    np.minimum.at(ymin, lab, xy[:, 1])
    np.maximum.at(ymax, lab, xy[:, 1])
    extent = np.maximum(xmax - xmin, ymax - ymin)
    # a stem's footprint can be widened by an attached branch or shrub in some slices (the
    # per-slice robust fits and consistency tests deal with those), so only absurd ones go
    cand = (counts >= cfg.min_slice_points) & (extent <= 3.0 * cfg.max_diameter + 2 * cell)
    if region is not None:
        d = REGION_MARGIN * cfg.max_diameter
        cand &= (xmax >= region[0] - d) & (xmin <= region[2] + d)
        cand &= (ymax >= region[1] - d) & (ymin <= region[3] + d)
    return np.asarray(cand, dtype=bool)
