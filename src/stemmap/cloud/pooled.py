"""The pooled band fit (ours, docs/algorithms/cloud.md "Ours" step 8, "Pooled band fit"): one
tilted circular cylinder over the whole slice band for trunks with too few points per slice
for a circle per slice (a trunk partly hidden behind a nearer one, a sparse cloud)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.config import StemConfig
from stemmap.cloud.slicefit import _damped_normal_equations, _normal_matrices, _segment_arcs
from stemmap.scan.circle import fit_circles_batch
from stemmap.types import FloatArray

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
    * vertical consistency: >= ``cfg.min_slices`` + 1 slices holding >= 3 inliers (all of
      them when a sparse band has fewer, :func:`_pooled_slices_needed`), spanning
      ``cfg.min_vertical_extent``, and in every one of them the median residual within 3
      standard errors (1.25 x noise floor / sqrt(n)) or 5 % of r: stacked leaf blobs or a
      bush change radius from slice to slice.

    Steps: :func:`_pooled_candidates`, :func:`_fit_cylinders` (with
    :func:`_cylinder_statistics`), :func:`_pooled_row` per fitted cluster.

    Returns rows like the band's ``(x, y, dbh, n_points, quality, arc, rms, n_slices, taper,
    dbh_std, cov_xx, cov_xy, cov_yy, dbh_height)`` (taper NaN: not estimated). Pinned by
    ``test_pooled_fit_finds_sparse_trunks``.
    """
    cnt_cs, ok_c = _pooled_candidates(cid, sli, todo, cfg, centers_h)
    if not ok_c.any():
        return []
    sel = ok_c[cid]
    cl, ids = np.unique(cid[sel], return_inverse=True)
    fit = _fit_cylinders(
        pts[sel],
        hts[sel] - cfg.breast_height,
        ids.astype(np.int64),
        sli[sel],
        centers_h.shape[0],
        noise_floor,
    )
    rows: list[tuple[float, ...]] = []
    for j in np.flatnonzero(fit.alive):
        row = _pooled_row(fit, int(j), cnt_cs[cl[j]], cfg, centers_h, noise_floor)
        if row is not None:
            rows.append(row)
    return rows


def _pooled_candidates(
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    centers_h: FloatArray,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Points per (cluster, slice) (K, S), and the clusters worth a cylinder fit: in ``todo``,
    >= 3 points in at least ``cfg.min_slices`` slices spanning ``cfg.min_vertical_extent``,
    and >= 2 x ``cfg.min_slice_points`` points in all."""
    ns = centers_h.shape[0]
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
    return cnt_cs, ok_c


@dataclass(frozen=True)
class _CylinderFit:
    """Tilted-cylinder fits of K clusters from their points (cluster ``ids``, slice ``s_i``).

    ``params`` (K, 5): centre x, y at breast height, lean dx/dh, dy/dh, radius; ``alive``:
    the start (a Kasa circle) succeeded; ``inlier`` (N,): kept by the MAD trimming;
    ``resid`` (N,): signed distance to the surface; ``n_in``, ``rms``: inliers and their RMS;
    ``cov`` (K, 5, 5): ``s^2 (J^T J)^-1`` over the inliers; ``arcs``: arc coverage (degrees)
    seen from the axis; ``slice_inliers`` (K, S): inliers per slice."""

    params: FloatArray
    alive: NDArray[np.bool_]
    ids: NDArray[np.int64]
    s_i: NDArray[np.int64]
    inlier: NDArray[np.bool_]
    resid: FloatArray
    n_in: NDArray[np.int64]
    rms: FloatArray
    cov: FloatArray
    arcs: FloatArray
    slice_inliers: NDArray[np.int64]


def _cylinder_residuals(
    t: FloatArray, p: FloatArray, hh: FloatArray, ids: NDArray[np.int64]
) -> tuple[FloatArray, FloatArray]:
    """Signed distance of each point (xy ``p``, height ``hh`` above breast height) to its
    cluster's tilted cylinder ``t[ids]``, and the unit direction (N, 2) from the axis."""
    cx = t[ids, 0] + t[ids, 2] * hh
    cy = t[ids, 1] + t[ids, 3] * hh
    v = np.column_stack((p[:, 0] - cx, p[:, 1] - cy))
    dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-9)
    return dist - t[ids, 4], v / dist[:, None]


def _cylinder_jacobian(n: FloatArray, hh: FloatArray) -> FloatArray:
    """(N, 5) derivative of the residuals by (cx, cy, lean x, lean y, r)."""
    return np.column_stack((-n[:, 0], -n[:, 1], -n[:, 0] * hh, -n[:, 1] * hh, -np.ones_like(hh)))


def _fit_cylinders(
    p: FloatArray,
    hh: FloatArray,
    ids: NDArray[np.int64],
    s_i: NDArray[np.int64],
    ns: int,
    noise_floor: float,
) -> _CylinderFit:
    """Batched tilted-cylinder fits: a Kasa circle start per cluster, then
    :func:`_robust_gauss_newton` (Huber weights, MAD trimming, refit)."""
    k = int(ids.max()) + 1
    first = fit_circles_batch(p, ids, "kasa")
    th = np.zeros((k, 5))
    th[:, 4] = np.nan
    th[first.segment_ids, :2] = first.centers
    th[first.segment_ids, 4] = first.radii
    alive = np.isfinite(th[:, 4]) & (th[:, 4] > 0)
    th[~alive, 4] = 0.1
    th, keep = _robust_gauss_newton(
        th, alive, p, hh, ids, noise_floor, _cylinder_residuals, _cylinder_jacobian
    )
    return _cylinder_statistics(th, alive, p, hh, ids, s_i, ns, keep)


def _robust_gauss_newton(
    th: FloatArray,
    alive: NDArray[np.bool_],
    p: FloatArray,
    hh: FloatArray,
    ids: NDArray[np.int64],
    noise_floor: float,
    residuals: Callable[
        [FloatArray, FloatArray, FloatArray, NDArray[np.int64]], tuple[FloatArray, FloatArray]
    ],
    jacobian: Callable[[FloatArray, FloatArray], FloatArray],
    prior: Callable[[FloatArray, FloatArray, FloatArray], None] | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The robust batched fit of the band's axis models (this module's tilted cylinder, the
    ring stack of :mod:`~stemmap.cloud.axisfit`) from the start ``th`` (K, P): 10 damped
    Gauss-Newton steps (Levenberg damping 1e-3 x the diagonal) with Huber weights at 2 x the
    noise floor, trimming of |residual| > 3 x 1.4826 MAD (the median |residual|), 10 more
    steps. ``residuals(th, p, hh, ids)`` gives the signed residuals and the unit directions
    from the axis, ``jacobian(n, hh)`` their derivative; ``prior(A, g, th)`` may add a
    prior's information to the normal equations in place. Returns the parameters and the
    inlier mask."""
    k = th.shape[0]
    keep = alive[ids]
    f_scale = max(2.0 * noise_floor, 1e-3)
    for rnd in range(2):
        for _ in range(10):
            d, n = residuals(th, p, hh, ids)
            w = np.where(keep, np.minimum(1.0, f_scale / np.maximum(np.abs(d), 1e-12)), 0.0)
            A, g = _damped_normal_equations(jacobian(n, hh), w, d, ids, k)
            if prior is not None:
                prior(A, g, th)
            step = np.linalg.solve(A, -g[:, :, None])[:, :, 0]
            th = np.where(alive[:, None] & np.isfinite(step).all(axis=1)[:, None], th + step, th)
        if rnd == 0:
            d, _ = residuals(th, p, hh, ids)
            ad = np.abs(d)
            mad = np.full(k, np.inf)
            order = np.lexsort((ad, ids))
            s_ids = ids[order]
            starts = np.flatnonzero(np.r_[True, s_ids[1:] != s_ids[:-1]])
            cnts = np.diff(np.r_[starts, s_ids.size])
            mad[s_ids[starts]] = ad[order][starts + cnts // 2]
            keep = alive[ids] & (ad <= np.maximum(3.0 * 1.4826 * mad, 0.001)[ids])
    return th, keep


def _cylinder_statistics(
    th: FloatArray,
    alive: NDArray[np.bool_],
    p: FloatArray,
    hh: FloatArray,
    ids: NDArray[np.int64],
    s_i: NDArray[np.int64],
    ns: int,
    keep: NDArray[np.bool_],
) -> _CylinderFit:
    """Residuals, inlier counts and RMS, the parameter covariance ``s^2 (J^T J)^-1`` over the
    inliers (Gauss-Newton, as for the slice circles: Chernov 2010, §6.4), arc coverage and
    inliers per slice of the fitted cylinders ``th``."""
    k = th.shape[0]
    d, n = _cylinder_residuals(th, p, hh, ids)
    nin = np.bincount(ids[keep], minlength=k)
    rms = np.sqrt(np.bincount(ids[keep], d[keep] ** 2, minlength=k) / np.maximum(nin, 1))
    # covariance of (cx, cy, lean x, lean y, r): s^2 (J^T J)^-1 over the inliers
    AJ = _normal_matrices(_cylinder_jacobian(n, hh)[keep], ids[keep], k)
    pcov = np.full((k, 5, 5), np.nan)
    inv_ok = np.abs(np.linalg.det(AJ)) > 1e-30
    if inv_ok.any():
        pcov[inv_ok] = np.linalg.inv(AJ[inv_ok]) * (rms[inv_ok] ** 2)[:, None, None]
    # arc: the directions of the points seen from the axis at their heights
    arcs = _segment_arcs(n[keep], ids[keep], k, np.zeros((k, 2)))
    seg = ids * ns + s_i
    n_sl = np.bincount(seg[keep], minlength=k * ns).reshape(k, ns)
    return _CylinderFit(th, alive, ids, s_i, keep, d, nin, rms, pcov, arcs, n_sl)


def _pooled_slices_needed(cfg: StemConfig, ns: int) -> int:
    """Slices that must hold >= 3 inliers of a pooled cylinder: one more than the per-slice
    path needs (``cfg.min_slices`` + 1), but never more than the band has.

    A sparse cloud's band is cut into fewer, thicker slices (:func:`~stemmap.cloud.band.
    _adapt_slices`: at least ``slices_per_spacing`` spacings thick, never fewer than 3): from
    a 90th-percentile spacing of 0.075 m on, 3 slices of 0.4 m. ``min_slices + 1`` = 4 of
    them cannot exist, so no pooled fit could pass where it is most needed (treels pine_plot
    at 10 %: 5 stems of 5-18 points per slice lost although their cylinders fit at 5-8 mm
    RMS). Then every slice must hold inliers: 3 of 3 slices of 0.4 m cover the whole 1.2 m
    band, more height than 4 of the default 6 slices of 0.2 m (0.8 m), so the test stays at
    least as strict in height as on a dense cloud.
    """
    return min(ns, cfg.min_slices + 1)


def _pooled_row(
    fit: _CylinderFit,
    j: int,
    cnt: NDArray[np.int64],
    cfg: StemConfig,
    centers_h: FloatArray,
    noise_floor: float,
) -> tuple[float, ...] | None:
    """The stem row of cylinder ``j`` (``cnt``: its cluster's points per slice), or None when
    it fails a test of :func:`_pooled_stems` (radius window and RMS, lean and arc, inliers,
    top slice, slices and span, per-slice median residual)."""
    th, r, rms, nin, arcs, pcov = fit.params, fit.params[:, 4], fit.rms, fit.n_in, fit.arcs, fit.cov
    rj = float(r[j])
    tol_r = POOL_RESIDUAL_FACTOR * noise_floor
    if not (cfg.min_diameter / 2 <= rj <= cfg.max_diameter / 2 and rms[j] <= tol_r):
        return None
    if math.hypot(th[j, 2], th[j, 3]) > POOL_MAX_LEAN or arcs[j] < cfg.min_arc_deg:
        return None
    n_all = int(cnt.sum())
    if nin[j] < 2 * cfg.min_slice_points or nin[j] < 0.5 * n_all:
        return None
    hs = fit.slice_inliers[j] >= 3
    if not hs[-1]:
        return None  # a stem goes on above the band; a shrub or a stack of leaf blobs ends
    if hs.sum() < _pooled_slices_needed(cfg, centers_h.shape[0]):
        return None
    if np.ptp(centers_h[hs]) < cfg.min_vertical_extent - 1e-9:
        return None
    mine = fit.inlier & (fit.ids == j)
    # each slice's median residual must vanish within its standard error (1.25 sigma /
    # sqrt(n) for a median) x 3, or 5 % of r (taper over the band)
    bad = False
    for s in np.flatnonzero(hs):
        rs = fit.resid[mine & (fit.s_i == s)]
        tol_s = max(3.0 * 1.25 * noise_floor / math.sqrt(rs.size), 0.05 * rj)
        bad |= abs(float(np.median(rs))) > tol_s
    if bad:
        return None
    frac = float(hs.sum()) / max(int((cnt > 0).sum()), 1)
    q = frac * min(1.0, arcs[j] / 120.0) * min(1.0, noise_floor / max(rms[j], 1e-6))
    return (
        float(th[j, 0]),
        float(th[j, 1]),
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
        cfg.breast_height,
    )
