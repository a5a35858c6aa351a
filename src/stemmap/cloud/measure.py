"""Per-stem measurement from the slice band (ours): the band of points around breast height,
vertical-consistency filter, grid clustering, per-slice fits and their consistency tests, the
taper/lean line at breast height, the pooled tilted-cylinder fallback, and stem heights from a
canopy raster."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud._grid_kernel import max_per_cell
from stemmap.cloud.config import StemConfig
from stemmap.cloud.ground import BASE_GROUND, cell_index, core_cells, raster_guard
from stemmap.cloud.result import RULE_BH, CloudStems
from stemmap.cloud.slicefit import (
    _band_spacing,
    _fit_segments,
    _normal_matrices,
    _segment_arcs,
    _segment_covariances,
    _theil_sen,
)
from stemmap.scan.circle import fit_circles_batch
from stemmap.types import FloatArray

log = logging.getLogger(__name__)


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


_CANOPY_CELL = 0.25
#: clusters within this many maximum diameters of a requested region are fitted (a stem's
#: centre lies within half a diameter of its cluster, a duplicate within half a diameter of
#: the stem it suppresses: 2 diameters leave a margin for chains of both)
REGION_MARGIN = 2.0
_CLUSTER_BYTES_PER_CELL = 16  # occupancy + dilation (bool), labels (int32), temporaries
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


BUTTRESS_CLEARANCE = 0.3  # m above the top of a buttress where the diameter is taken
BUTTRESS_OUTSIDE = 0.1  # fraction of a slice's points on fins outside the fitted circle


def _outside_fraction(
    band: _Band,
    tree: Any,
    sl: NDArray[np.int64],
    c: FloatArray,
    r: FloatArray,
    rms: FloatArray,
) -> FloatArray:
    """Per slice of one stem: the fraction of the band's points within two radii of the
    slice circle's centre that lie outside it by more than max(3 RMS, 2 cm) and less than one
    radius -- buttress fins and root flare, which the robust fit trims as outliers (it
    measures the round core between the fins). All band points, before the vertical filter
    (a fin shrinks with height, so the filter removes much of it)."""
    ns = r.shape[0]
    out = np.zeros(ns)
    if tree is None or not np.isfinite(r).any():
        return out
    k = int(np.nanargmax(r))
    idx = np.asarray(tree.query_ball_point(c[k], 2.0 * float(np.nanmax(r))), dtype=np.int64)
    if idx.size == 0:
        return out
    for s in range(ns):
        if not np.isfinite(r[s]):
            continue
        q = idx[sl[idx] == s]
        d = np.hypot(*(band.xy[q] - c[s]).T)
        q_in = d <= 2 * r[s]
        if q_in.sum() < 8:
            continue
        res = d[q_in] - r[s]
        thr = max(3 * float(rms[s]) if np.isfinite(rms[s]) else 0.0, 0.02)
        out[s] = float(np.mean((res > thr) & (res < r[s])))
    return out


def _line_uncertainty(
    hh: FloatArray,
    r: FloatArray,
    c: FloatArray,
    coefs: tuple[tuple[float, float], ...],
    cov_i: FloatArray,
) -> tuple[float, FloatArray]:
    """Variance of the radius and covariance of the centre at ``hh = 0`` of the slice lines.

    Two estimates, the larger kept: the slices' fit covariances
    (:func:`~stemmap.cloud.slicefit._segment_covariances`) averaged and divided by the number
    of slices (independent slices, intercept at the band's middle), and the scatter of the
    slice values about the Theil-Sen lines (1.4826 MAD, squared, over the number of slices):
    bark roughness and branch stubs move whole slices, which no single fit's covariance sees.
    """
    n = hh.shape[0]
    coef_r, coef_x, coef_y = coefs
    fit_r = float(np.nanmean(cov_i[:, 2, 2])) / n
    fit_xy = np.nanmean(cov_i[:, :2, :2], axis=0) / n
    res_r = r - (coef_r[0] + coef_r[1] * hh)
    res_c = c - np.column_stack((coef_x[0] + coef_x[1] * hh, coef_y[0] + coef_y[1] * hh))
    dof = max(n - 2, 1)
    sc_r = (1.4826 * float(np.median(np.abs(res_r)))) ** 2 * n / dof / n
    sc_xy = (res_c.T @ res_c) / dof / n
    var_r = max(fit_r, sc_r) if math.isfinite(fit_r) else sc_r
    cov_xy = (
        sc_xy if not np.isfinite(fit_xy).all() or np.trace(sc_xy) > np.trace(fit_xy) else fit_xy
    )
    return var_r, np.asarray(cov_xy, dtype=np.float64)


def _mean_uncertainty(cov_i: FloatArray) -> tuple[float, FloatArray]:
    """Inverse-variance combination of the slices' fit covariances (fewer than 3 slices)."""
    good = np.isfinite(cov_i).all(axis=(1, 2))
    if not good.any():
        return math.nan, np.full((2, 2), np.nan)
    info_r = float(np.sum(1.0 / np.maximum(cov_i[good, 2, 2], 1e-12)))
    info_xy = np.sum(np.linalg.inv(cov_i[good, :2, :2] + 1e-12 * np.eye(2)), axis=0)
    return 1.0 / info_r, np.asarray(np.linalg.inv(info_xy), dtype=np.float64)


def _radius_consensus(
    r: FloatArray, m: NDArray[np.bool_], tol: float, sig_r: float
) -> tuple[float, NDArray[np.bool_]]:
    """Radius most slices agree on, and the slices that agree.

    The median of all passing slices is right when most slices see the stem. In a spruce
    whose whorls hide the stem in some slices, those slices fit large circles through the
    branches and the median lands between stem and clutter, rejecting both. The consensus is
    the slice radius with the most slices within its tolerance (15 % of it, or 5 sigma of a
    slice radius); when every slice agrees with the median, the median is kept (the common
    case, unchanged).
    """
    idx = np.flatnonzero(m)
    r_med = float(np.median(r[idx]))
    if np.all(np.abs(r[idx] - r_med) <= tol):
        return r_med, m
    tols = np.maximum(0.15 * r[idx], 5.0 * sig_r)
    support = (np.abs(r[idx][None, :] - r[idx][:, None]) <= tols[:, None]).sum(axis=1)
    best = support == support.max()
    # among equally supported radii, the smallest: clutter makes circles larger, not smaller
    j = idx[best][int(np.argmin(r[idx][best]))]
    agree = m & (np.abs(r - r[j]) <= max(0.15 * r[j], 5.0 * sig_r))
    return float(np.median(r[agree])), agree


def _stems_from_band(
    band: _Band,
    cfg: StemConfig,
    *,
    slice_cloud: bool = False,
    statistics_only: bool = False,
    region: tuple[float, float, float, float] | None = None,
) -> CloudStems:
    """Stems of the slice band. With ``statistics_only`` stop once the point spacing and the
    slice noise floor are measured: an empty CloudStems carrying both (the steps before them
    are exactly the full run's, so the values are the ones the full run measures).

    ``region`` (xmin, ymin, xmax, ymax; infinite sides allowed): only the stems near it are
    wanted (a tile engine's chunk keeps the stems its owned area holds). Clusters farther
    than :data:`REGION_MARGIN` diameters from it are not fitted. Every step before the fits
    (spacing, slices, vertical filter, clustering) still sees the whole band, the slice fits
    are seeded per slice, and each stem's tests read only its own cluster; what crosses
    clusters -- duplicate suppression, within half a diameter -- stays inside the margin, so
    the stems inside the region are the ones a run without it finds. It applies only with
    a given ``noise_floor`` (measured, it is the median over every cluster's fits)."""
    xy, h = band.xy, band.h
    n = xy.shape[0]
    if n < cfg.min_slice_points:
        return CloudStems.empty(
            "ours", reason=f"fewer than {cfg.min_slice_points} points in the slice band"
        )
    # --- spacing -> clustering cell (measured, not tuned)
    sp2d = cfg.spacing if cfg.spacing is not None else _band_spacing(xy, h)
    if not math.isfinite(sp2d):
        return CloudStems.empty(
            "ours", reason="point spacing could not be measured (duplicate points only?)"
        )
    cell = float(np.clip(cfg.cluster_cell_factor * sp2d, 0.01, 0.25))
    if not slice_cloud and cfg.slices_per_spacing > 0:
        cfg = _adapt_slices(cfg, sp2d)
    centers_h = np.asarray(cfg.slice_centers, dtype=np.float64)
    ns = centers_h.shape[0]
    # --- slice of each point: the nearest slice centre within half a thickness
    near = np.argmin(np.abs(h[:, None] - centers_h[None, :]), axis=1)
    sl_all = np.where(np.abs(h - centers_h[near]) <= cfg.slice_thickness / 2, near, -1)
    keep = sl_all >= 0
    if not slice_cloud and ns >= 3:
        keep &= _vertical_filter(xy, sl_all, ns, float(np.clip(cell, 0.03, 0.1)), cfg.grid_origin)
    xy, h = xy[keep], h[keep]
    sl_all = sl_all[keep]
    orig = None if band.origins is None else band.origins[keep]
    if xy.shape[0] < cfg.min_slice_points:
        return CloudStems.empty(
            "ours", spacing=sp2d, reason="no points left after the vertical-consistency filter"
        )
    # --- grid components with one-cell gap bridging (dilated occupancy)
    from scipy import ndimage

    # stray band points far outside the cloud cannot hold a stem and must not stretch the grid
    core = core_cells(np.floor(xy / 1.0).astype(np.int64))
    if not core.all():
        log.warning("%d stray band point(s) far outside the cloud ignored", int((~core).sum()))
        xy, h, sl_all = xy[core], h[core], sl_all[core]
        orig = None if orig is None else orig[core]
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
    lab = lab_img.ravel()[flat].astype(np.int64) - 1
    # --- candidate clusters: enough points, plausible footprint
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
    if region is not None and cfg.noise_floor is not None and not statistics_only:
        d = REGION_MARGIN * cfg.max_diameter
        cand &= (xmax >= region[0] - d) & (xmin <= region[2] + d)
        cand &= (ymax >= region[1] - d) & (ymin <= region[3] + d)
    sl = sl_all
    use = cand[lab] & (sl >= 0)
    if not use.any():
        return CloudStems.empty(
            "ours", spacing=sp2d, reason="no cluster has enough points in any slice"
        )
    cl_ids, cl_inv = np.unique(lab[use], return_inverse=True)
    kc = cl_ids.shape[0]
    seg = cl_inv.astype(np.int64) * ns + sl[use]
    pts = xy[use]
    kseg = kc * ns
    seg_n = np.bincount(seg, minlength=kseg)
    fitmask = seg_n[seg] >= cfg.min_slice_points
    pts_f, seg_f = pts[fitmask], seg[fitmask]
    centers, radii, rms, ok, nin = _fit_segments(
        pts_f,
        seg_f,
        kseg,
        cfg.fit_method,
        ransac_tol=max(0.5 * sp2d, 0.005),
        radius_window=(cfg.min_diameter / 2, cfg.max_diameter / 2),
        ray_origins=None if orig is None else orig[use][fitmask],
    )
    seg_cov = _segment_covariances(pts_f, seg_f, kseg, centers, radii, rms)
    arcs = np.zeros(kseg)
    if ok.any():
        good = ok[seg_f]
        arcs = _segment_arcs(pts_f[good], seg_f[good], kseg, np.where(ok[:, None], centers, 0))
    # --- quality tests; noise floor measured from the data
    plausible = (
        ok
        & (nin >= cfg.min_slice_points)
        & (radii >= cfg.min_diameter / 2)
        & (radii <= cfg.max_diameter / 2)
        & (arcs >= cfg.min_arc_deg)
    )
    if not plausible.any():
        return CloudStems.empty(
            "ours",
            spacing=sp2d,
            reason="no slice fit passed the quality tests (points, radius, arc)",
        )
    noise_floor = (
        cfg.noise_floor if cfg.noise_floor is not None else float(np.median(rms[plausible]))
    )
    if statistics_only:
        return replace(
            CloudStems.empty("ours", spacing=sp2d, reason="statistics only"),
            noise_floor=noise_floor,
        )
    rms_max = cfg.residual_factor * max(noise_floor, 0.5 * sp2d / 10, 1e-4)
    passed = plausible & (rms <= np.maximum(rms_max, 0.02 * radii))
    log.debug(
        "slice fits: %d ok, %d enough points, %d radius window, %d arc, %d residual of %d",
        ok.sum(),
        (ok & (nin >= cfg.min_slice_points)).sum(),
        (ok & (radii >= cfg.min_diameter / 2) & (radii <= cfg.max_diameter / 2)).sum(),
        (ok & (arcs >= cfg.min_arc_deg)).sum(),
        passed.sum(),
        ok.size,
    )
    P = passed.reshape(kc, ns)
    C = centers.reshape(kc, ns, 2)
    R = radii.reshape(kc, ns)
    W = (nin / np.maximum(rms, 1e-4) ** 2).reshape(kc, ns)
    A = arcs.reshape(kc, ns)
    RMS = rms.reshape(kc, ns)
    NIN = nin.reshape(kc, ns)
    COV = seg_cov.reshape(kc, ns, 3, 3)
    from scipy.spatial import cKDTree

    # the band before the vertical filter (which removes fins: they shrink with height)
    band_tree = cKDTree(band.xy) if not slice_cloud else None
    near_all = np.argmin(np.abs(band.h[:, None] - centers_h[None, :]), axis=1)
    band_sl = np.where(
        np.abs(band.h - centers_h[near_all]) <= cfg.slice_thickness / 2, near_all, -1
    )
    FIT = (ok & (radii > 0)).reshape(kc, ns)
    present = (seg_n.reshape(kc, ns) >= cfg.min_slice_points).sum(axis=1)
    rows: list[tuple[float, ...]] = []
    rules: list[str] = []
    accepted = np.zeros(kc, dtype=bool)
    for c in np.flatnonzero(P.sum(axis=1) >= cfg.min_slices):
        m = P[c]
        # consistency: drop slices whose radius or centre is far from the median
        r_med = float(np.median(R[c, m]))
        # tolerance: 15 % of the radius, or 5 sigma of a slice radius, whichever is larger.
        # sigma_r is the fit's parameter noise, not the points': ~2 rms / sqrt(n) on a half
        # arc, growing like (180 deg / arc)^2 on shorter arcs (partly occluded trunks)
        short = np.maximum(1.0, 180.0 / np.maximum(A[c, m], 1.0)) ** 2
        sig_r = float(np.median(2.0 * RMS[c, m] / np.sqrt(np.maximum(NIN[c, m], 1)) * short))
        tol = max(0.15 * r_med, 5.0 * sig_r)
        r_med, m = _radius_consensus(R[c], m, tol, sig_r)
        tol = max(0.15 * r_med, 5.0 * sig_r)
        c_med = np.median(C[c, m], axis=0)
        # centres are compared with a robust line through them (a leaning stem's centre
        # moves with height), radii with their median
        if m.sum() >= 3:
            hm = centers_h[m]
            lx, ly = _theil_sen(hm, C[c, m, 0]), _theil_sen(hm, C[c, m, 1])
            pred = np.column_stack((lx[0] + lx[1] * centers_h, ly[0] + ly[1] * centers_h))
        else:
            pred = np.broadcast_to(c_med, C[c].shape)
        m = (
            m
            & (np.abs(R[c] - r_med) <= tol)
            & (np.hypot(*(C[c] - pred).T) <= max(tol, 0.3 * r_med))
        )
        if m.sum() < cfg.min_slices:
            continue
        if not slice_cloud and np.ptp(centers_h[m]) < cfg.min_vertical_extent - 1e-9:
            continue  # not a vertical structure (a bush, a boulder, a branch stub)
        # buttress / root flare: slices below breast height, centred on the stem, fitted with
        # a radius above the stem's tolerance. Forestry convention: the diameter is taken
        # 0.3 m above the top of the swelling when it reaches above 1.0 m
        out_f = _outside_fraction(band, band_tree, band_sl, C[c], R[c], RMS[c])
        flare = (
            FIT[c]
            & (centers_h < cfg.breast_height)
            & (np.hypot(*(C[c] - pred).T) <= r_med + R[c])
            & ((~m & (R[c] > r_med + tol)) | (out_f > BUTTRESS_OUTSIDE))
        )
        # a buttress starts at the ground: only the run of flared slices from the lowest up;
        # and above it the stem is clean (a spruce's whorls put branch points around the
        # stem at every height, which is not a buttress)
        flare &= np.cumprod(flare | (centers_h < centers_h[FIT[c]].min())).astype(bool)
        above = FIT[c] & ~flare & (centers_h > centers_h[flare].max() if flare.any() else False)
        if flare.any() and (not above.any() or out_f[above].max() > BUTTRESS_OUTSIDE / 2):
            flare[:] = False
        h_meas = cfg.breast_height
        rule = RULE_BH
        if flare.any() and not slice_cloud:
            top = float(centers_h[flare].max() + cfg.slice_thickness / 2)
            if top + BUTTRESS_CLEARANCE > cfg.breast_height:
                h_meas = top + BUTTRESS_CLEARANCE
                rule = f"above buttress (swelling to {top:.2f} m)"
        hh = centers_h[m] - h_meas
        w = W[c, m]
        cov_i = COV[c, m]
        if m.sum() >= 3 and np.ptp(hh) >= 0.3:
            # robust (Theil-Sen) line through the slices (taper, lean), at breast height: one
            # slice spoilt by a branch or a shrub does not tilt it
            coef_r = _theil_sen(hh, R[c, m])
            coef_x = _theil_sen(hh, C[c, m, 0])
            coef_y = _theil_sen(hh, C[c, m, 1])
            taper = float(coef_r[1])
            if abs(taper) > cfg.max_taper:
                continue  # radius changes too fast with height for a stem (bush, boulder)
            r_bh = float(coef_r[0])
            cxy = np.array([coef_x[0], coef_y[0]])
            var_r, cov_xy = _line_uncertainty(hh, R[c, m], C[c, m], (coef_r, coef_x, coef_y), cov_i)
            # lean: the horizontal slice of a stem leaning by theta is an ellipse with axes
            # d / cos(theta) and d; a circle fit returns about their mean, so the diameter
            # across the axis is 2 cos(theta) / (1 + cos(theta)) of it (first order)
            cos_t = 1.0 / math.sqrt(1.0 + coef_x[1] ** 2 + coef_y[1] ** 2)
            r_bh *= 2 * cos_t / (1 + cos_t)
        else:
            r_bh = float(np.average(R[c, m], weights=w))
            cxy = np.average(C[c, m], axis=0, weights=w)
            taper = math.nan
            var_r, cov_xy = _mean_uncertainty(cov_i)
        frac = float(m.sum()) / max(int(present[c]), 1)
        arc = float(np.mean(A[c, m]))
        rr = float(np.mean(RMS[c, m]))
        q = frac * min(1.0, arc / 120.0) * min(1.0, noise_floor / max(rr, 1e-6))
        rows.append(
            (
                cxy[0],
                cxy[1],
                2 * r_bh,
                int(NIN[c, m].sum()),
                q,
                arc,
                rr,
                int(m.sum()),
                taper,
                2 * math.sqrt(var_r),
                cov_xy[0, 0],
                cov_xy[0, 1],
                cov_xy[1, 1],
                h_meas,
            )
        )
        rules.append(rule)
        accepted[c] = True
    if cfg.pooled_fallback and not slice_cloud:
        pooled = _pooled_stems(
            pts,
            h[use],
            cl_inv.astype(np.int64),
            sl[use],
            ~accepted & (present < cfg.min_slices),  # too few points per slice
            cfg,
            centers_h,
            noise_floor,
        )
        if pooled:
            log.info("%d stem(s) from the pooled band fit", len(pooled))
            rows.extend(pooled)
            rules.extend([RULE_BH] * len(pooled))
    if not rows:
        return replace(
            CloudStems.empty(
                "ours",
                spacing=sp2d,
                reason="no cluster passed the per-stem tests (slices, vertical extent, taper)",
            ),
            noise_floor=noise_floor,
        )
    arr = np.array(rows, dtype=np.float64)
    # suppress duplicates (a trunk split into two clusters): keep the better supported one
    order = np.argsort(-arr[:, 3])
    kept: list[int] = []
    for i in order:
        if all(
            math.hypot(arr[i, 0] - arr[j, 0], arr[i, 1] - arr[j, 1])
            > 0.5 * max(arr[i, 2], arr[j, 2])
            for j in kept
        ):
            kept.append(int(i))
    kept = sorted(kept)
    arr = arr[kept]
    rule_arr = np.array([rules[i] for i in kept], dtype=object)
    # absolute z of breast height at each stem: median z - h offset of nearby band points
    zbh = _breast_height_z(band, arr[:, :2], cfg.breast_height, band_tree)
    heights = _stem_heights(band.canopy, arr[:, :2]) if band.canopy else np.full(len(arr), np.nan)
    return CloudStems.from_columns(
        xy=arr[:, :2],
        z=zbh,
        diameter=arr[:, 2],
        n_points=arr[:, 3].astype(np.int64),
        quality=np.clip(arr[:, 4], 0.0, 1.0),
        arc_deg=arr[:, 5],
        rms=arr[:, 6],
        n_slices=arr[:, 7].astype(np.int64),
        taper=arr[:, 8],
        height=heights,
        diameter_std=arr[:, 9],
        xy_cov=np.stack(
            (np.stack((arr[:, 10], arr[:, 11]), -1), np.stack((arr[:, 11], arr[:, 12]), -1)), -2
        ),
        dbh_height=arr[:, 13],
        dbh_rule=rule_arr,
        method="ours" if cfg.fit_method == "ours" else f"ours_{cfg.fit_method}",
        frame="cloud",
        spacing=sp2d,
        noise_floor=noise_floor,
        base=band.base,
    )


POOL_MAX_LEAN = math.tan(math.radians(10.0))
POOL_RESIDUAL_FACTOR = 1.5


def _pooled_stems(
    pts: FloatArray,
    hts: FloatArray,
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    centers_h: FloatArray,
    noise_floor: float,
) -> list[tuple[float, ...]]:
    """One tilted-cylinder fit over the whole band for trunks with too few points per slice.

    A trunk partly hidden behind a nearer one, or in a sparse cloud, shows a few returns per
    slice: too few (< ``cfg.min_slice_points``) for a circle per slice, but together dozens
    of points on one cylinder. Candidates (``todo``) are the clusters the per-slice path
    could not judge: fewer than ``cfg.min_slices`` slices with ``cfg.min_slice_points``
    points (clusters with enough points per slice that failed the slice tests failed on
    shape and get no second chance). Those with >= 3 points in at least ``cfg.min_slices``
    slices spanning ``cfg.min_vertical_extent`` and >= 2 x ``cfg.min_slice_points`` points
    are fitted at once by a tilted circular cylinder (centre at breast height, lean,
    radius; taper ignored: over the 1.2 m band a taper of 1 cm/m moves the radius by < 6 mm
    at the band's ends and ~1 mm at its centre): damped Gauss-Newton batched over the
    candidates, Huber weights (scale 2 x the noise floor), trimming of |res| > 3 x 1.4826
    MAD, refit. One fit replaces the per-slice consistency checks, so the tests are
    stricter, all on the inliers:

    * RMS <= ``POOL_RESIDUAL_FACTOR`` (1.5) x the band's noise floor (a cylinder through
      many points must fit as well as the median slice circle), DBH in the window;
    * lean <= 10 degrees (a branch is >= 50 degrees from vertical); arc >=
      ``cfg.min_arc_deg``;
    * >= 2 x ``cfg.min_slice_points`` inliers, at least half of the cluster's points;
    * vertical consistency: >= ``cfg.min_slices`` + 1 slices holding >= 3 inliers, spanning
      ``cfg.min_vertical_extent``, and in every one of them the median residual within 3
      standard errors (1.25 x noise floor / sqrt(n)) or 5 % of r: stacked leaf blobs or a
      bush change radius from slice to slice.

    Returns rows like the band's ``(x, y, dbh, n_points, quality, arc, rms, n_slices, taper)``
    (taper NaN: not estimated). Pinned by ``test_pooled_fit_finds_sparse_trunks``.
    """
    ns = centers_h.shape[0]
    bh = cfg.breast_height
    kc = todo.shape[0]
    cnt_cs = np.bincount(cid * ns + sli, minlength=kc * ns).reshape(kc, ns)
    has = cnt_cs >= 3
    span = np.where(has, centers_h[None, :], -np.inf).max(axis=1) - np.where(
        has, centers_h[None, :], np.inf
    ).min(axis=1)
    ok_c = (
        todo
        & (has.sum(axis=1) >= cfg.min_slices)
        & (span >= cfg.min_vertical_extent - 1e-9)
        & (cnt_cs.sum(axis=1) >= 2 * cfg.min_slice_points)
    )
    if not ok_c.any():
        return []
    sel = ok_c[cid]
    p, hh, ids_old = pts[sel], hts[sel] - bh, cid[sel]
    cl, ids = np.unique(ids_old, return_inverse=True)
    ids = ids.astype(np.int64)
    k = cl.shape[0]
    s_i = sli[sel]
    first = fit_circles_batch(p, ids, "kasa")
    th = np.zeros((k, 5))
    th[:, 4] = np.nan
    th[first.segment_ids, :2] = first.centers
    th[first.segment_ids, 4] = first.radii
    alive = np.isfinite(th[:, 4]) & (th[:, 4] > 0)
    th[~alive, 4] = 0.1
    keep = alive[ids]
    f_scale = max(2.0 * noise_floor, 1e-3)

    def resid(t: FloatArray) -> tuple[FloatArray, FloatArray]:
        cx = t[ids, 0] + t[ids, 2] * hh
        cy = t[ids, 1] + t[ids, 3] * hh
        v = np.column_stack((p[:, 0] - cx, p[:, 1] - cy))
        dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-9)
        return dist - t[ids, 4], v / dist[:, None]

    for rnd in range(2):
        for _ in range(10):
            d, n = resid(th)
            w = np.where(keep, np.minimum(1.0, f_scale / np.maximum(np.abs(d), 1e-12)), 0.0)
            J = np.column_stack(
                (-n[:, 0], -n[:, 1], -n[:, 0] * hh, -n[:, 1] * hh, -np.ones_like(d))
            )
            A = np.zeros((k, 5, 5))
            g = np.zeros((k, 5))
            for a in range(5):
                g[:, a] = np.bincount(ids, w * J[:, a] * d, minlength=k)
                for b in range(a, 5):
                    A[:, a, b] = A[:, b, a] = np.bincount(ids, w * J[:, a] * J[:, b], minlength=k)
            A += 1e-3 * np.einsum("kii->ki", A)[:, :, None] * np.eye(5)[None] + 1e-12 * np.eye(5)
            step = np.linalg.solve(A, -g[:, :, None])[:, :, 0]
            th = np.where(alive[:, None] & np.isfinite(step).all(axis=1)[:, None], th + step, th)
        if rnd == 0:
            d, _ = resid(th)
            ad = np.abs(d)
            mad = np.full(k, np.inf)
            order = np.lexsort((ad, ids))
            s_ids = ids[order]
            starts = np.flatnonzero(np.r_[True, s_ids[1:] != s_ids[:-1]])
            cnts = np.diff(np.r_[starts, s_ids.size])
            mad[s_ids[starts]] = ad[order][starts + cnts // 2]
            keep = alive[ids] & (ad <= np.maximum(3.0 * 1.4826 * mad, 0.001)[ids])
    d, n = resid(th)
    r = th[:, 4]
    nin = np.bincount(ids[keep], minlength=k)
    rms = np.sqrt(np.bincount(ids[keep], d[keep] ** 2, minlength=k) / np.maximum(nin, 1))
    # covariance of (cx, cy, lean x, lean y, r): s^2 (J^T J)^-1 over the inliers
    Jk = np.column_stack((-n[:, 0], -n[:, 1], -n[:, 0] * hh, -n[:, 1] * hh, -np.ones_like(d)))
    AJ = _normal_matrices(Jk[keep], ids[keep], k)
    pcov = np.full((k, 5, 5), np.nan)
    inv_ok = np.abs(np.linalg.det(AJ)) > 1e-30
    if inv_ok.any():
        pcov[inv_ok] = np.linalg.inv(AJ[inv_ok]) * (rms[inv_ok] ** 2)[:, None, None]
    cxy = th[:, :2]
    # arc: the directions of the points seen from the axis at their heights
    arcs = _segment_arcs(n[keep], ids[keep], k, np.zeros((k, 2)))
    seg = ids * ns + s_i
    n_sl = np.bincount(seg[keep], minlength=k * ns).reshape(k, ns)
    has_in = n_sl >= 3
    rows: list[tuple[float, ...]] = []
    for j in np.flatnonzero(alive):
        rj = float(r[j])
        tol_r = POOL_RESIDUAL_FACTOR * noise_floor
        if not (cfg.min_diameter / 2 <= rj <= cfg.max_diameter / 2 and rms[j] <= tol_r):
            continue
        if math.hypot(th[j, 2], th[j, 3]) > POOL_MAX_LEAN or arcs[j] < cfg.min_arc_deg:
            continue
        n_all = int(cnt_cs[cl[j]].sum())
        if nin[j] < 2 * cfg.min_slice_points or nin[j] < 0.5 * n_all:
            continue
        hs = has_in[j]
        if not hs[-1]:
            continue  # a stem goes on above the band; a shrub or a stack of leaf blobs ends
        if hs.sum() < cfg.min_slices + 1 or np.ptp(centers_h[hs]) < cfg.min_vertical_extent - 1e-9:
            continue
        mine = keep & (ids == j)
        # each slice's median residual must vanish within its standard error (1.25 sigma /
        # sqrt(n) for a median) x 3, or 5 % of r (taper over the band)
        bad = False
        for s in np.flatnonzero(hs):
            rs = d[mine & (s_i == s)]
            tol_s = max(3.0 * 1.25 * noise_floor / math.sqrt(rs.size), 0.05 * rj)
            bad |= abs(float(np.median(rs))) > tol_s
        if bad:
            continue
        frac = float(hs.sum()) / max(int((cnt_cs[cl[j]] > 0).sum()), 1)
        q = frac * min(1.0, arcs[j] / 120.0) * min(1.0, noise_floor / max(rms[j], 1e-6))
        rows.append(
            (
                float(cxy[j, 0]),
                float(cxy[j, 1]),
                2 * rj,
                int(nin[j]),
                q,
                float(arcs[j]),
                float(rms[j]),
                int(hs.sum()),
                math.nan,
                2 * math.sqrt(pcov[j, 4, 4]) if np.isfinite(pcov[j, 4, 4]) else math.nan,
                float(pcov[j, 0, 0]),
                float(pcov[j, 0, 1]),
                float(pcov[j, 1, 1]),
                bh,
            )
        )
    return rows


def _breast_height_z(band: _Band, xy: FloatArray, bh: float, tree: Any = None) -> FloatArray:
    """Absolute z of breast height at ``xy``; ``tree``: a cKDTree of ``band.xy`` if built."""
    from scipy.spatial import cKDTree

    if band.xy.shape[0] == 0 or xy.shape[0] == 0:
        return np.full(xy.shape[0], np.nan)
    off = band.z - band.h  # ground z under each band point
    tree = cKDTree(band.xy) if tree is None else tree
    _, idx = tree.query(xy, k=min(16, band.xy.shape[0]))
    idx = np.atleast_2d(idx)
    return np.asarray(np.median(off[idx], axis=1) + bh, dtype=np.float64)
