"""Per-stem measurement from the slice band (ours, docs/algorithms/cloud.md "Ours" steps 1 and
3-9): :func:`_stems_from_band` runs the steps in order, each in the module of its concept --

* :mod:`~stemmap.cloud.band`: slices, vertical-consistency filter, grid clustering;
* :mod:`~stemmap.cloud.slicefit`: the circle fit of every (cluster, slice);
* :mod:`~stemmap.cloud._ladder`: those fits at a RANSAC tolerance, the ladder of tighter
  tolerances for rejected clusters (``tighter_refits``) and the single-tree choice between
  the stems it gives;
* :mod:`~stemmap.cloud.slicestem`: one stem from its slice fits (consistency, buttress, the
  taper/lean line at breast height), with :mod:`~stemmap.cloud.uncertainty`;
* :mod:`~stemmap.cloud.pooled`: the pooled tilted-cylinder fallback;
* :mod:`~stemmap.cloud.axisfit`: the shared-axis ring-stack fit of sparse failed clusters
  (option ``axis_fallback``, off);
* :mod:`~stemmap.cloud.heights`: canopy raster, stem heights, breast-height z.

The band's names are re-exported here (``from stemmap.cloud.measure import _Band`` keeps
working), as are the ladder's constants. :func:`_stems_from_band` calls the ladder's
functions by their names here (a tracer wrapping ``measure._single_tree_stem`` or
``measure._slice_stem`` sees every call); the tighter refits' own slice fits go through
``_ladder._fit_slices``, so a wrap of ``measure._fit_slices`` sees the first round's only."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud._ladder import (
    MIN_RANSAC_TOL,
    SINGLE_TREE_SHRINK,
    _fit_slices,
    _MaybeStem,
    _ransac_tolerance,
    _section_sd,
    _single_tree_stem,
    _Stem,
    _tighter_refits,
)
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
from stemmap.cloud.slicefit import _band_spacing
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
    "MIN_RANSAC_TOL",
    "REGION_MARGIN",
    "SINGLE_TREE_SHRINK",
    "_CANOPY_CELL",
    "_Band",
    "_adapt_slices",
    "_canopy_update",
    "_grid_cells",
    "_stems_from_band",
    "_vertical_filter",
]

log = logging.getLogger(__name__)


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
    _candidate_clusters`); 6 slice fits (:func:`~stemmap.cloud._ladder._fit_slices`); 7
    per-slice quality tests and the noise floor; 8 per stem
    (:func:`~stemmap.cloud.slicestem._slice_stem`), the pooled fit
    (:func:`~stemmap.cloud.pooled._pooled_stems`), duplicate suppression; 9 heights
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
            """:func:`~stemmap.cloud._ladder._tighter_refits` of the clusters ``todo`` on the
            band's slices (stems by ``stem_of``), or on the default 20 cm slices (``thin``)."""
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
