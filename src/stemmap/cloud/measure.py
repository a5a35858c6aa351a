"""Per-stem measurement from the slice band (ours, docs/algorithms/cloud.md "Ours" steps 1 and
3-9): :func:`_stems_from_band` runs the steps in order, each in the module of its concept --

* :mod:`~stemmap.cloud.band`: slices, vertical-consistency filter, grid clustering;
* :mod:`~stemmap.cloud.slicefit`: the circle fit of every (cluster, slice);
* :mod:`~stemmap.cloud.slicestem`: one stem from its slice fits (consistency, buttress, the
  taper/lean line at breast height), with :mod:`~stemmap.cloud.uncertainty`;
* :mod:`~stemmap.cloud.pooled`: the pooled tilted-cylinder fallback;
* :mod:`~stemmap.cloud.axisfit`: the shared-axis ring-stack fit of sparse failed clusters
  (option ``axis_fallback``, off);
* :mod:`~stemmap.cloud.heights`: canopy raster, stem heights, breast-height z.

The band's names are re-exported here (``from stemmap.cloud.measure import _Band`` keeps
working)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.axisfit import _axis_stems
from stemmap.cloud.band import (
    REGION_MARGIN,
    _adapt_slices,
    _Band,
    _candidate_clusters,
    _drop_strays,
    _grid_cells,
    _label_clusters,
    _slice_of,
    _sliced_points,
    _vertical_filter,
    density_slice_points,
)
from stemmap.cloud.canonical import canonical_band
from stemmap.cloud.config import StemConfig
from stemmap.cloud.heights import _CANOPY_CELL, _breast_height_z, _canopy_update, _stem_heights
from stemmap.cloud.pooled import _pooled_stems
from stemmap.cloud.quantisation import check_coordinate_step
from stemmap.cloud.result import RULE_BH, CloudStems
from stemmap.cloud.slicefit import (
    _band_spacing,
    _fit_segments,
    _opaque_core_refits,
    _segment_arcs,
    _segment_covariances,
)
from stemmap.cloud.slicestem import (
    _BandContext,
    _slice_stem,
    _SliceFits,
    _thin_slice_stem,
    thin_slice_points,
)
from stemmap.cloud.sparsereach import RULE_TALL, _sparse_tall_stems, _sparse_todo
from stemmap.types import FloatArray

__all__ = [
    "REGION_MARGIN",
    "_CANOPY_CELL",
    "_Band",
    "_adapt_slices",
    "_canopy_update",
    "_grid_cells",
    "_stems_from_band",
    "_vertical_filter",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _SegmentFits:
    """Step 6: the circle fit of every segment (cluster k, slice s: segment ``k * S + s``):
    centre (2,), radius, residual RMS, success, inliers, covariance (3, 3) over (cx, cy, r),
    arc coverage (degrees; 0 for a failed fit), and the segment's number of points."""

    centers: FloatArray
    radii: FloatArray
    rms: FloatArray
    ok: NDArray[np.bool_]
    n_in: NDArray[np.int64]
    cov: FloatArray
    arcs: FloatArray
    n_points: NDArray[np.int64]

    def plausible(self, cfg: StemConfig) -> NDArray[np.bool_]:
        """Step 7 without the residual test: enough inliers, radius in the DBH window, arc
        coverage of at least ``cfg.min_arc_deg``."""
        return np.asarray(
            self.ok
            & (self.n_in >= cfg.min_slice_points)
            & (self.radii >= cfg.min_diameter / 2)
            & (self.radii <= cfg.max_diameter / 2)
            & (self.arcs >= cfg.min_arc_deg),
            dtype=bool,
        )

    def per_cluster(
        self, passed: NDArray[np.bool_], kc: int, ns: int, cfg: StemConfig
    ) -> _SliceFits:
        """The fits as (cluster, slice) arrays for the per-stem tests."""
        return _SliceFits(
            passed=passed.reshape(kc, ns),
            fitted=(self.ok & (self.radii > 0)).reshape(kc, ns),
            centers=self.centers.reshape(kc, ns, 2),
            radii=self.radii.reshape(kc, ns),
            rms=self.rms.reshape(kc, ns),
            arcs=self.arcs.reshape(kc, ns),
            n_in=self.n_in.reshape(kc, ns),
            weights=(self.n_in / np.maximum(self.rms, 1e-4) ** 2).reshape(kc, ns),
            cov=self.cov.reshape(kc, ns, 3, 3),
            present=(self.n_points.reshape(kc, ns) >= cfg.min_slice_points).sum(axis=1),
        )


def _fit_slices(
    pts: FloatArray,
    seg: NDArray[np.int64],
    kseg: int,
    cfg: StemConfig,
    spacing: float,
    origins: FloatArray | None,
    ransac_tol: float | None = None,
) -> _SegmentFits:
    """Step 6: a robust circle fit (:func:`~stemmap.cloud.slicefit._fit_segments`: algebraic
    start, RANSAC (Fischler & Bolles 1981) where it explains the points badly, geometric fit
    with Huber loss and MAD trimming; along the rays when ``origins`` are given) of every
    segment with at least ``cfg.min_slice_points`` points, their covariances
    (:func:`~stemmap.cloud.slicefit._segment_covariances`) and arc coverage. The RANSAC
    tolerance is ``ransac_tol``, by default :func:`_ransac_tolerance` of the spacing."""
    seg_n = np.bincount(seg, minlength=kseg)
    fitmask = seg_n[seg] >= cfg.min_slice_points
    pts_f, seg_f = pts[fitmask], seg[fitmask]
    centers, radii, rms, ok, nin = _fit_segments(
        pts_f,
        seg_f,
        kseg,
        cfg.fit_method,
        ransac_tol=_ransac_tolerance(spacing) if ransac_tol is None else ransac_tol,
        radius_window=(cfg.min_diameter / 2, cfg.max_diameter / 2),
        ray_origins=None if origins is None else origins[fitmask],
        ransac_lo=cfg.ransac_lo,
        ransac_seed=cfg.ransac_seed,
        window=cfg.slice_fit_window,
        stub_trim=cfg.slice_stub_trim,
        stub_surface=cfg.slice_stub_surface,
    )
    if cfg.core_refits:
        (centers, radii, rms, ok, nin), n_core = _opaque_core_refits(
            pts_f,
            seg_f,
            (centers, radii, rms, ok, nin),
            cfg.fit_method,
            (cfg.min_diameter / 2, cfg.max_diameter / 2),
            cfg.min_slice_points,
            None if origins is None else origins[fitmask],
            ransac_lo=cfg.ransac_lo,
            ransac_seed=cfg.ransac_seed,
            window=cfg.slice_fit_window,
            stub_trim=cfg.slice_stub_trim,
            stub_surface=cfg.slice_stub_surface,
        )
        if n_core:
            log.debug("%d slice fit(s) refitted to the stem inside them", n_core)
    seg_cov = _segment_covariances(pts_f, seg_f, kseg, centers, radii, rms)
    arcs = np.zeros(kseg)
    if ok.any():
        good = ok[seg_f]
        arcs = _segment_arcs(pts_f[good], seg_f[good], kseg, np.where(ok[:, None], centers, 0))
    return _SegmentFits(centers, radii, rms, ok, nin, seg_cov, arcs, seg_n)


#: the smallest RANSAC inlier tolerance (m): bark roughness and range noise of a good TLS scan
MIN_RANSAC_TOL = 0.005


def _ransac_tolerance(spacing: float) -> float:
    """The first RANSAC inlier tolerance of a slice fit: half the point spacing, at least
    :data:`MIN_RANSAC_TOL`."""
    return max(0.5 * spacing, MIN_RANSAC_TOL)


def _tighter_refits(
    pts: FloatArray,
    seg: NDArray[np.int64],
    failed: NDArray[np.int64],
    shape: tuple[int, int],
    cfg: StemConfig,
    spacing: float,
    origins: FloatArray | None,
    rms_max: float,
    stem_of: Callable[[_SliceFits, int], tuple[tuple[float, ...], str] | None],
    first: float = 0.5,
    floor: float = MIN_RANSAC_TOL,
) -> dict[int, tuple[tuple[float, ...], str]]:
    """Stems of the clusters ``failed`` (rejected by the per-stem tests) from their slices
    refitted with ever tighter RANSAC tolerances: half the first one, halved again down to
    :data:`MIN_RANSAC_TOL`; a cluster is done at its first tolerance that gives a stem.

    The tolerance is a distance *across* the surface (range noise, bark roughness), the
    spacing one *along* it: a thinner cloud has a larger spacing but no noisier bark. On a
    tree whose band is mostly needles (treels spruce.laz: 90th-percentile spacing 45 mm as
    shipped, 66 / 100 / 153 mm at 50 / 20 / 10 %) half the spacing is an annulus 3-8 cm wide,
    and a circle through the branch whorls (r 0.3-0.7 m) holds more points in it than the
    12 cm stem: every slice fits a whorl, and no slice is left for the consistency tests or
    the guided refits. A slice passes step 7 as in the first round (``rms_max``, from the
    first round's noise floor). The first tolerance that gives a stem wins; ``stem_of``
    (fits, cluster) is the per-stem test (:func:`~stemmap.cloud.slicestem._slice_stem`),
    unchanged. Clusters that pass at the first tolerance never get here, so the stems found
    before are unchanged. The tolerance is not taken below ``floor``, the residual scale of
    the stems the cloud already gave (their median slice RMS): points scattered by more than
    that cannot be told from clutter with a tighter tolerance (the simulated mobile scan,
    3 cm range noise, stems' RMS ~2 cm: a 6 mm tolerance made a 6 cm stem of a shrub's
    clump). ``first``: the first tolerance as a fraction of the default one
    (:func:`_ransac_tolerance`; 1 when the slices themselves changed, see below).

    The caller runs it twice: with the band's slices, then -- for clusters still rejected, when
    the band's slices were thickened for a sparse cloud (:func:`~stemmap.cloud.band.
    _adapt_slices`) -- with the default 20 cm slices, since the needles' spacing that
    thickened them is not the stem's (treels spruce at 10 %: 0.4 m slices, the middle one
    1.2-1.6 m all whorl, leaving 2 of 3 slices on the stem).
    """
    kc, ns = shape
    out: dict[int, tuple[tuple[float, ...], str]] = {}
    todo = np.asarray(failed, dtype=np.int64)
    tol = first * _ransac_tolerance(spacing)
    while todo.size and tol >= max(floor, MIN_RANSAC_TOL) - 1e-12:
        sub = np.isin(seg // ns, todo)
        o_sub = None if origins is None else origins[sub]
        fits = _fit_slices(pts[sub], seg[sub], kc * ns, cfg, spacing, o_sub, tol)
        passed = fits.plausible(cfg) & (fits.rms <= np.maximum(rms_max, 0.02 * fits.radii))
        per = fits.per_cluster(passed, kc, ns, cfg)
        for c in todo:
            if per.passed[c].sum() >= min(2, cfg.min_slices):
                stem = stem_of(per, int(c))
                if stem is not None:
                    out[int(c)] = stem
        todo = np.array([c for c in todo if int(c) not in out], dtype=np.int64)
        tol /= 2
    return out


#: a stem row and the rule that gave its DBH
_Stem = tuple[tuple[float, ...], str]
_MaybeStem = TypeVar("_MaybeStem", bound="_Stem | None")

#: a single tree's refit replaces its stem only below this fraction of its diameter
SINGLE_TREE_SHRINK = 0.5


def _stem_weight(row: tuple[float, ...]) -> float:
    """A stem row's support: its inliers over its mean slice RMS squared (the slices' fit
    weights, :class:`~stemmap.cloud.slicestem._SliceFits`, pooled)."""
    return float(row[3]) / max(float(row[6]), 1e-4) ** 2


def _single_tree_stem(
    first_round: tuple[tuple[float, ...], str] | None,
    refit: Callable[[bool, float, float], tuple[tuple[float, ...], str] | None],
    tol0: float,
    thickened: bool,
    found_rms: float | None = None,
    error: Callable[[tuple[tuple[float, ...], str]], float] | None = None,
    agree_z: float = 2.0,
) -> tuple[tuple[float, ...], str] | None:
    """The stem of a cloud with a single candidate cluster: of its first-round stem
    (``first_round``, or None) and the stems its tighter refits give at every tolerance of
    the ladder (``refit(thin, first, tol)``: half of ``tol0``, halved down to
    :data:`MIN_RANSAC_TOL`, on the band's slices; and from ``tol0`` down on the default
    20 cm slices when the band's were ``thickened``), the first round's, unless a smaller
    one has more support (below).

    In a cloud of many stems the noise floor (the median slice RMS) comes from all of them
    and the residual test rejects circles through clutter; with one candidate it is that
    candidate's own median RMS, so the test passes whatever its slices fitted. On treels
    spruce.laz randomly thinned to 10 % (seed 3) the first round took three circles of
    r 31-72 cm through the branch whorls at RMS 61-97 mm as a 1.41 m stem, while the
    ladder's tighter tolerances fit its 12 cm bark at RMS 3-8 mm. The first tolerance that
    gives a stem (what :func:`_tighter_refits` stops at in a plot) is the loosest, the one
    clutter wins. Clutter makes circles larger and rougher, but a tighter tolerance also
    trims any fit to a lower RMS and carves a smaller, smoother arc out of rough bark (archi
    Tree_1, 54 cm, slice RMS 19 mm: 39-44 cm at 7 mm with twice the support). So the
    first-round stem (or without one, the first the ladder gives, as in a plot) is kept
    unless a smaller ladder stem has more support (:func:`_stem_weight`) and either is below
    :data:`SINGLE_TREE_SHRINK` (half) its diameter -- a circle of half the radius is not the
    same surface however rough its bark -- or was fitted at a tolerance not below the kept
    stem's RMS, where the support comparison is fair.

    ``found_rms`` (``StemConfig.ladder_found_rms``): the kept stem's RMS in that test, when the
    first-round stem was measured again on thin slices: the RMS of the slice fits it was
    found with. The re-measure's annulus fits about a known circle have an RMS that is no
    RANSAC residual (aRchi Tree_1 at 20 %, seed 0: 7.1 mm against 18.3 mm found), so a
    14.6 mm rung's 40.4 cm stem carved from its rough 54 cm bark passed as a fair
    comparison and won on support (docs/algorithms/cloud.md "aRchi Tree_1 at 20 %: where
    its DBH moves").

    ``error`` (``StemConfig.ladder_by = "error"``): a stem's DBH standard deviation with the
    section term (:func:`_section_sd`). A smaller ladder stem fitted below the kept stem's
    RMS may then also win on support when it is the better measurement of the same surface:
    its error smaller than the kept stem's, and the two DBHs within ``agree_z``
    (``StemConfig.ladder_agree_z``) standard deviations of their difference. treels spruce
    with 1 cm noise (seed 0) kept a line across a gap at 1.3 m (25.25 cm, ring + 1.88, sd
    2.6 cm) against a 6 mm rung that holds a slice there (23.67, sd 0.5). The error alone
    does not refuse a carved circle: its slices are a consistent inner surface, not scatter
    (Tree_1 at 20 %, seed 0: 40.4 cm at sd 1.2 cm against 53.6 at 1.5), but it is 13 cm from
    the kept stem, 7 sd of the difference (docs/algorithms/cloud.md "The single-tree ladder
    by its error")."""
    cands: list[tuple[tuple[float, ...], str]] = []
    tols: list[float] = []
    ladders = [(False, 0.5)] + ([(True, 1.0)] if thickened else [])
    for thin, f in ladders:
        while f * tol0 >= MIN_RANSAC_TOL - 1e-12:
            got = refit(thin, f, f * tol0)
            if got is not None:
                cands.append(got)
                tols.append(f * tol0)
            f /= 2
    incumbent = first_round if first_round is not None else (cands[0] if cands else None)
    if incumbent is None:
        return None
    d0, rms0 = incumbent[0][2], incumbent[0][6]
    if found_rms is not None and incumbent is first_round:
        rms0 = found_rms
    if error is not None:
        e0 = error(incumbent)
        log.debug("ladder: kept D %.4f rms %.4f sd %.4f", d0, rms0, e0)

    def fair(c: tuple[tuple[float, ...], str], t: float) -> bool:
        if t >= rms0 or error is None:
            return t >= rms0
        e = error(c)
        log.debug("ladder: rung %.4f D %.4f w %.0f sd %.4f", t, c[0][2], _stem_weight(c[0]), e)
        return e < e0 and abs(c[0][2] - d0) <= agree_z * math.hypot(e, e0)

    other = [
        c
        for c, t in zip(cands, tols, strict=True)
        if c[0][2] < SINGLE_TREE_SHRINK * d0 or (c[0][2] < d0 and fair(c, t))
    ]
    best = max(other, key=_stem_weight_of, default=None)
    if best is not None and _stem_weight(best[0]) > _stem_weight(incumbent[0]):
        return best
    return incumbent


def _section_sd(
    measure: Callable[[StemConfig], tuple[tuple[float, ...], str] | None], cfg: StemConfig
) -> float:
    """The DBH standard deviation of the stem ``measure(cfg)`` gives, with the section term
    at its model weight (``dbh_sd_scatter`` = 1: fit noise plus the kept slices' scatter
    about the stem's local profile, :func:`~stemmap.cloud.dbhsd.dbh_variance`), whatever the
    configured weight; inf when it gives no stem. What ``thin_remeasure_by = "error"``
    compares: the DBH is the same at every weight, only its stated error changes."""
    got = measure(replace(cfg, dbh_sd_scatter=1.0))
    return math.inf if got is None else float(got[0][9])


def _stem_weight_of(stem: tuple[tuple[float, ...], str]) -> float:
    return _stem_weight(stem[0])


def _suppress_duplicates(arr: FloatArray) -> list[int]:
    """Rows to keep when a trunk is split into two clusters: in order of support (column 3,
    points), a stem is kept unless its centre lies within half the larger diameter (column 2)
    of a kept one. Returns the kept row indices, sorted."""
    order = np.argsort(-arr[:, 3])
    kept: list[int] = []
    for i in order:
        if all(
            math.hypot(arr[i, 0] - arr[j, 0], arr[i, 1] - arr[j, 1])
            > 0.5 * max(arr[i, 2], arr[j, 2])
            for j in kept
        ):
            kept.append(int(i))
    return sorted(kept)


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
    a given ``noise_floor`` (measured, it is the median over every cluster's fits).

    The steps (docs/algorithms/cloud.md "Ours"): 1 point spacing
    (:func:`~stemmap.cloud.slicefit._band_spacing`) -> clustering cell; 3 slices
    (:func:`~stemmap.cloud.band._adapt_slices`); 4 vertical-consistency filter
    (:func:`~stemmap.cloud.band._sliced_points`); 5 grid clustering
    (:func:`~stemmap.cloud.band._label_clusters`, :func:`~stemmap.cloud.band.
    _candidate_clusters`); 6 slice fits (:func:`_fit_slices`); 7 per-slice quality tests and
    the noise floor; 8 per stem (:func:`~stemmap.cloud.slicestem._slice_stem`), the pooled
    fit (:func:`~stemmap.cloud.pooled._pooled_stems`), duplicate suppression; 9 heights
    (:mod:`~stemmap.cloud.heights`)."""
    n = band.xy.shape[0]
    if n < cfg.min_slice_points:
        return CloudStems.empty(
            "ours", reason=f"fewer than {cfg.min_slice_points} points in the slice band"
        )
    # --- coordinates rounded too coarsely for a diameter (float32 at UTM values): refused
    check_coordinate_step(band.xy, cfg.max_coordinate_step)
    # --- the band in an order of its points alone: the same cloud in another point order
    # (a re-export, tiles) gives the same stems (:mod:`~stemmap.cloud.canonical`)
    band = canonical_band(band)
    # --- spacing -> clustering cell (measured, not tuned)
    sp2d = cfg.spacing if cfg.spacing is not None else _band_spacing(band.xy, band.h)
    if not math.isfinite(sp2d):
        return CloudStems.empty(
            "ours", reason="point spacing could not be measured (duplicate points only?)"
        )
    cell = float(np.clip(cfg.cluster_cell_factor * sp2d, 0.01, 0.25))
    cfg_thin = cfg
    if not slice_cloud and cfg.slices_per_spacing > 0:
        cfg = _adapt_slices(cfg, sp2d)
    # the dense count: the pooled fit's switching rule and its own counts keep it
    cfg_dense = cfg
    if cfg.density_slice_points and not slice_cloud:
        # slices thinner than the density's design (a band held at three slices) hold fewer
        # returns on a stem's side: their fits are held to that count (band.density_slice_points)
        cfg = replace(cfg, min_slice_points=density_slice_points(cfg, cfg.slice_thickness, sp2d))
    centers_h = np.asarray(cfg.slice_centers, dtype=np.float64)
    ns = centers_h.shape[0]
    # --- slice of each point, vertical-consistency filter
    pts_b = _sliced_points(band, cfg, centers_h, cell, slice_cloud)
    if pts_b.xy.shape[0] < cfg.min_slice_points:
        return CloudStems.empty(
            "ours", spacing=sp2d, reason="no points left after the vertical-consistency filter"
        )
    # --- grid components with one-cell gap bridging; candidate clusters
    pts_b = _drop_strays(pts_b)
    xy, sl = pts_b.xy, pts_b.sl
    lab, n_lab = _label_clusters(xy, cell, cfg)
    use_region = region is not None and cfg.noise_floor is not None and not statistics_only
    cand = _candidate_clusters(xy, lab, n_lab, cell, cfg, region if use_region else None)
    use = cand[lab] & (sl >= 0)
    if not use.any():
        return CloudStems.empty(
            "ours", spacing=sp2d, reason="no cluster has enough points in any slice"
        )
    cl_ids, cl_inv = np.unique(lab[use], return_inverse=True)
    kc = cl_ids.shape[0]
    seg = cl_inv.astype(np.int64) * ns + sl[use]
    pts = xy[use]
    fits = _fit_slices(
        pts, seg, kc * ns, cfg, sp2d, None if pts_b.origins is None else pts_b.origins[use]
    )
    # --- quality tests; noise floor measured from the data
    plausible = fits.plausible(cfg)
    if not plausible.any():
        return CloudStems.empty(
            "ours",
            spacing=sp2d,
            reason="no slice fit passed the quality tests (points, radius, arc)",
        )
    noise_floor = (
        cfg.noise_floor if cfg.noise_floor is not None else float(np.median(fits.rms[plausible]))
    )
    if statistics_only:
        return replace(
            CloudStems.empty("ours", spacing=sp2d, reason="statistics only"),
            noise_floor=noise_floor,
        )
    rms_max = cfg.residual_factor * max(noise_floor, 0.5 * sp2d / 10, 1e-4)
    passed = plausible & (fits.rms <= np.maximum(rms_max, 0.02 * fits.radii))
    ok, nin, radii = fits.ok, fits.n_in, fits.radii
    log.debug(
        "slice fits: %d ok, %d enough points, %d radius window, %d arc, %d residual of %d",
        ok.sum(),
        (ok & (nin >= cfg.min_slice_points)).sum(),
        (ok & (radii >= cfg.min_diameter / 2) & (radii <= cfg.max_diameter / 2)).sum(),
        (ok & (fits.arcs >= cfg.min_arc_deg)).sum(),
        passed.sum(),
        ok.size,
    )
    per = fits.per_cluster(passed, kc, ns, cfg)
    from scipy.spatial import cKDTree

    # the band before the vertical filter (which removes fins: they shrink with height)
    band_tree = cKDTree(band.xy) if not slice_cloud else None
    # a single candidate cluster: the noise floor is its own slices' RMS, not pooled
    only = np.unique(np.flatnonzero(plausible) // ns)
    ctx = _BandContext(
        band=band,
        tree=band_tree,
        band_sl=_slice_of(band.h, centers_h, cfg.slice_thickness),
        centers_h=centers_h,
        noise_floor=noise_floor,
        slice_cloud=slice_cloud,
        rms_max=rms_max,
        own_floor=only.size == 1 and cfg.noise_floor is None,
    )
    # the default thin slices, when the band's were thickened for a sparse cloud; a stem
    # found on at most thin_remeasure_max_slices (4) thick slices is measured again on them
    thickened = cfg_thin.slice_thickness < cfg.slice_thickness
    few_thick = thickened and ns <= cfg.thin_remeasure_max_slices
    # a slice's own radius at breast height is trusted where the residual test can reject a
    # slice fitted to clutter: with a noise floor pooled over several stems (_stem_at)
    ctx = replace(ctx, few_thick=few_thick and not ctx.own_floor)
    remeasure = few_thick and cfg.thin_remeasure
    ch0 = np.asarray(cfg_thin.slice_centers, dtype=np.float64)
    ctx0 = (
        replace(
            ctx,
            centers_h=ch0,
            band_sl=_slice_of(band.h, ch0, cfg_thin.slice_thickness),
            few_thick=False,
        )
        if thickened
        else ctx
    )
    # the thin slices of a plot's thickened band hold thin / thick of a thick slice's returns
    # on a stem: the thin ladder's guided refits (finding) need that many; the thin
    # re-measure of a stem already found keeps the dense count (StemConfig.thin_refit_points)
    ctx0_find = (
        replace(
            ctx0,
            annulus_points=thin_slice_points(
                cfg_thin.min_slice_points, cfg_thin.slice_thickness, cfg.slice_thickness
            ),
        )
        if thickened and cfg.thin_refit_points and not ctx.own_floor
        else ctx0
    )
    if cfg.density_slice_points and thickened and not ctx.own_floor:
        # the thin ladder's guided refits in a plot: the count the measured density gives a
        # thin slice (finding only: the thin re-measure of a found stem keeps ctx0's count)
        ctx0_find = replace(
            ctx0, annulus_points=density_slice_points(cfg_thin, cfg_thin.slice_thickness, sp2d)
        )

    def thin_again(
        f: _SliceFits, c: int, stem: tuple[tuple[float, ...], str]
    ) -> tuple[tuple[float, ...], str]:
        """Cluster ``c``'s ``stem``, found on at most ``thin_remeasure_max_slices`` thick
        slices (``f``), measured again on the thin ones where that measurement is the better
        one (``thin_remeasure_by``: its DBH error with the section term smaller, or more thin
        slices agree); else as found."""
        if remeasure:
            again = _thin_slice_stem(f, c, ctx, ctx0, cfg_thin)
            if again is None:
                return measured(stem, lambda k: _slice_stem(f, c, ctx, k), cfg)
            if cfg.thin_remeasure_by == "error":
                if _section_sd(lambda k: _thin_slice_stem(f, c, ctx, ctx0, k), cfg_thin) < (
                    _section_sd(lambda k: _slice_stem(f, c, ctx, k), cfg)
                ):
                    return measured(again, lambda k: _thin_slice_stem(f, c, ctx, ctx0, k), cfg_thin)
            elif again[0][7] > stem[0][7]:
                return measured(again, lambda k: _thin_slice_stem(f, c, ctx, ctx0, k), cfg_thin)
        return measured(stem, lambda k: _slice_stem(f, c, ctx, k), cfg)

    def band_stem(f: _SliceFits, c: int) -> tuple[tuple[float, ...], str] | None:
        """Step 8 on the band's slices, the stem measured again on thin ones
        (:func:`thin_again`): every stem found on thick slices, in the first round or by
        the tighter refits of a plot, which take the first tolerance that gives one."""
        stem = _slice_stem(f, c, ctx, cfg)
        if stem is None:
            return None
        found_rms[int(c)] = float(stem[0][6])
        return thin_again(f, c, stem)

    # the RMS of the slice fits each band stem was found with (before a thin re-measure)
    found_rms: dict[int, float] = {}
    # ladder_by = "error": how each stem row was measured, to measure it again with the
    # section term (_section_sd); its error once measured, by the row's id
    how: list[tuple[tuple[float, ...], Callable[[StemConfig], _Stem | None], StemConfig]] = []
    errors: dict[int, float] = {}

    def measured(
        stem: _MaybeStem, again: Callable[[StemConfig], _Stem | None], base: StemConfig
    ) -> _MaybeStem:
        if stem is not None and cfg.ladder_by == "error":
            how.append((stem[0], again, base))
        return stem

    def ladder_error(stem: _Stem) -> float:
        if id(stem[0]) not in errors:
            again, base = next((a, b) for row, a, b in how if row is stem[0])
            errors[id(stem[0])] = _section_sd(again, base)
        return errors[id(stem[0])]

    # the single-tree ladder's own thick-slice stems enter its choice as found (a re-measure
    # changes their support, and so the choice: archi Tree_1 at 10 %, seed 2, 52.7 -> 49.0
    # cm); the chosen one is measured again. The fits that gave each of them:
    found_on: list[tuple[tuple[float, ...], _SliceFits, int]] = []

    def ladder_stem(f: _SliceFits, c: int) -> tuple[tuple[float, ...], str] | None:
        stem = measured(_slice_stem(f, c, ctx, cfg), lambda k: _slice_stem(f, c, ctx, k), cfg)
        if stem is not None:
            found_on.append((stem[0], f, c))
        return stem

    def ladder_thin(f: _SliceFits, c: int) -> tuple[tuple[float, ...], str] | None:
        return measured(
            _slice_stem(f, c, ctx0_find, cfg_thin),
            lambda k: _slice_stem(f, c, ctx0_find, k),
            cfg_thin,
        )

    # --- per stem: slice consistency, buttress, taper/lean line at breast height
    rows: list[tuple[float, ...]] = []
    rules: list[str] = []
    accepted = np.zeros(kc, dtype=bool)
    # two passing slices may be enough: the others get a guided refit (_guided_refits)
    for c in np.flatnonzero(per.passed.sum(axis=1) >= min(2, cfg.min_slices)):
        stem = band_stem(per, int(c))
        if stem is None:
            continue
        rows.append(stem[0])
        rules.append(stem[1])
        accepted[c] = True
    # --- clusters whose slices all fitted clutter: tighter RANSAC tolerances. Counted are
    # the plausible slices (points, radius, arc), not those that also passed the residual
    # test: a tolerance too wide for the stem is what makes its slices fail that test
    n_plausible = plausible.reshape(kc, ns).sum(axis=1)
    failed = np.flatnonzero(~accepted & (n_plausible >= min(2, cfg.min_slices)))
    if cfg.tighter_refits:
        # the accepted stems' residual scale: no tighter tolerance than the bark shows
        floor = float(np.median([r[6] for r in rows])) if rows else MIN_RANSAC_TOL
        origins_use = None if pts_b.origins is None else pts_b.origins[use]
        sl0 = _slice_of(pts_b.h[use], ch0, cfg_thin.slice_thickness)

        def step(
            todo: NDArray[np.int64],
            thin: bool,
            first: float,
            floor: float,
            stem_of: Callable[[_SliceFits, int], tuple[tuple[float, ...], str] | None] = band_stem,
            thin_of: Callable[[_SliceFits, int], _Stem | None] | None = None,
        ) -> dict[int, tuple[tuple[float, ...], str]]:
            """:func:`_tighter_refits` of the clusters ``todo`` on the band's slices (stems
            by ``stem_of``), or on the default 20 cm slices (``thin``)."""
            if not thin:
                return _tighter_refits(
                    pts,
                    seg,
                    todo,
                    (kc, ns),
                    cfg,
                    sp2d,
                    origins_use,
                    rms_max,
                    stem_of,
                    first=first,
                    floor=floor,
                )
            in0 = sl0 >= 0
            return _tighter_refits(
                pts[in0],
                cl_inv.astype(np.int64)[in0] * ch0.shape[0] + sl0[in0],
                todo,
                (kc, ch0.shape[0]),
                cfg_thin,
                sp2d,
                None if origins_use is None else origins_use[in0],
                rms_max,
                thin_of or (lambda f, c: _slice_stem(f, c, ctx0_find, cfg_thin)),
                first=first,
                floor=floor,
            )

        # a single candidate's noise floor is its own slices' RMS: the residual test is void
        one = int(only[0]) if only.size == 1 else -1
        if cfg.single_tree_ladder and one >= 0 and (accepted[one] or one in failed):
            i_row = int(np.flatnonzero(np.flatnonzero(accepted) == one)[0]) if accepted[one] else -1
            best = _single_tree_stem(
                (rows[i_row], rules[i_row]) if i_row >= 0 else None,
                # one rung of the ladder: start at tolerance ``tol`` (= first x tol0), floor there
                lambda thin, first, tol: step(
                    np.array([one]), thin, first, tol, ladder_stem, ladder_thin
                ).get(one),
                _ransac_tolerance(sp2d),
                thickened,
                found_rms.get(one) if cfg.ladder_found_rms and i_row >= 0 else None,
                ladder_error if cfg.ladder_by == "error" else None,
                cfg.ladder_agree_z,
            )
            # the chosen stem, if the ladder found it on thick slices, measured on thin ones
            if best is not None:
                on = next(((f, c) for row, f, c in found_on if row is best[0]), None)
                if on is not None:
                    best = thin_again(on[0], on[1], best)
            if best is not None and i_row >= 0:
                rows[i_row], rules[i_row] = best
            elif best is not None:
                rows.append(best[0])
                rules.append(best[1])
                accepted[one] = True
            failed = failed[failed != one]
        tight = step(failed, False, 0.5, floor) if failed.size else {}
        failed = np.array([c for c in failed if int(c) not in tight], dtype=np.int64)
        if failed.size and thickened:
            tight.update(step(failed, True, 1.0, floor))
        for ci, stem in sorted(tight.items()):
            rows.append(stem[0])
            rules.append(stem[1])
            accepted[ci] = True
        if tight:
            log.info("%d stem(s) from slices refitted with a tighter RANSAC tolerance", len(tight))
    if cfg.pooled_fallback and not slice_cloud:
        # too few points per slice for the dense count (the per-slice path may have judged
        # such a cluster with StemConfig.density_slice_points; the pooled fit still gets it)
        present = (fits.n_points.reshape(kc, ns) >= cfg_dense.min_slice_points).sum(axis=1)
        pooled = _pooled_stems(
            pts,
            pts_b.h[use],
            cl_inv.astype(np.int64),
            sl[use],
            ~accepted & (present < cfg.min_slices),
            cfg_dense,
            centers_h,
            noise_floor,
        )
        if pooled:
            log.info("%d stem(s) from the pooled band fit", len(pooled))
            rows.extend(pooled)
            rules.extend([RULE_BH] * len(pooled))
    if cfg.axis_fallback and not slice_cloud:
        # judged by the per-slice path (enough points per slice for it) and failed, but sparse
        axis = _axis_stems(
            pts,
            pts_b.h[use],
            cl_inv.astype(np.int64),
            sl[use],
            ~accepted & (per.present >= cfg.min_slices),
            cfg_dense,
            centers_h,
            noise_floor,
            band.reach if cfg.axis_reach else None,
        )
        if axis:
            log.info("%d stem(s) from the shared-axis band fit", len(axis))
            rows.extend(axis)
            rules.extend([RULE_BH] * len(axis))
    if cfg.sparse_tall_fit and not slice_cloud:
        # sparse clusters no path made a stem: one ring stack over the taller range
        found = np.array([r[:3] for r in rows], dtype=np.float64).reshape(-1, 3)
        tall = _sparse_tall_stems(
            pts,
            pts_b.h[use],
            cl_inv.astype(np.int64),
            sl[use],
            _sparse_todo(cl_inv.astype(np.int64), sl[use], pts, kc, ns, cfg_dense, found),
            cfg_dense,
            ns,
            noise_floor,
            band.xy,
            band.h,
            band.reach,
        )
        if tall:
            log.info("%d stem(s) from the taller-band fit of sparse clusters", len(tall))
            rows.extend(tall)
            rules.extend([RULE_TALL] * len(tall))
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
    kept = _suppress_duplicates(arr)
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
