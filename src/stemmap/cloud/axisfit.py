"""The shared-axis band fit for sparse stems (ours, docs/algorithms/cloud.md "Sparse stems: one
fit over the band"): the slices of a sparse trunk measured together, as a stack of rings on
one straight axis whose radius follows a taper line with a prior, instead of one circle per
slice. Used only for the clusters the per-slice path (and the pooled fit of
:mod:`~stemmap.cloud.pooled`) could not make a stem of, and only where they are sparse.

Model (per cluster; ``h`` height above breast height): the axis passes through (cx, cy) at
breast height with lean (ax, ay) per metre; the ring at height h has radius ``r + k h``. The
residual of a return p is its horizontal distance to the axis at its height minus that
radius -- the tilted cylinder of :func:`~stemmap.cloud.pooled._fit_cylinders` plus the taper
``k``. With the band's 1.2 m and one-sided arcs, ``k`` and ``r`` are nearly collinear, so ``k``
gets a Gaussian prior (maximum a posteriori; :data:`TAPER_PRIOR` = -0.005 +- 0.01 m/m, i.e.
a stem narrowing 1 cm in diameter per metre, +-2 cm/m: Larson 1963's butt-log taper of
conifers and broadleaves lies inside): a pseudo-observation ``(k - k0) s / sigma_k`` with
``s`` the noise floor, added to the Gauss-Newton normal equations. The covariance is the
posterior one, ``(J^T J / rms^2 + e_k e_k^T / sigma_k^2)^-1`` (Chernov 2010, §6.4 for the
data term; the prior adds its information): honest for independent residuals. The standard
error used is the larger of it and a delete-one-slice jackknife (:func:`_jackknife_var_r`),
which sees bark and one-sided arcs that fit different radii at different heights. A stem
whose DBH standard error exceeds :data:`AXIS_MAX_DBH_STD` is not reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.config import StemConfig
from stemmap.cloud.pooled import (
    POOL_MAX_LEAN,
    POOL_RESIDUAL_FACTOR,
    _pooled_slices_needed,
    _robust_gauss_newton,
)
from stemmap.cloud.slicefit import _normal_matrices, _segment_arcs
from stemmap.scan.circle import fit_circles_batch
from stemmap.types import FloatArray

#: taper prior (d radius / d height, m/m): mean and standard deviation
TAPER_PRIOR = (-0.005, 0.01)
#: largest DBH standard error accepted (m): the issue-11 tolerance of a single tree's DBH
#: (1.5 cm), held at one standard error
AXIS_MAX_DBH_STD = 0.015
#: a cluster is sparse when its fullest slice holds fewer than this many times
#: ``cfg.min_slice_points`` points (the switching rule, docs "Sparse stems")
AXIS_SPARSE_FACTOR = 3.0
#: heights (m above the ground) whose returns the fit may use with ``reach``: below and above
#: the band, where a sparse trunk still shows (docs "Sparse stems")
AXIS_RANGE = (0.5, 3.0)
#: test bins over ``AXIS_RANGE`` (m; the sparse band's slice thickness)
AXIS_BIN = 0.4
_NPAR = 6  # cx, cy, lean x, lean y, r at breast height, taper


@dataclass(frozen=True)
class _AxisFit:
    """Shared-axis fits of K clusters: ``params`` (K, 6) = cx, cy at breast height, lean
    x, y (per metre), radius at breast height, taper; ``alive``: the start succeeded;
    ``pts``, ``hh``, ``ids``, ``s_i`` the returns fitted (xy, height above breast height,
    cluster, slice); ``inlier``, ``resid`` (N,); ``n_in``, ``rms`` (K,); ``cov`` (K, 6, 6) posterior
    covariance; ``arcs`` (K,) degrees seen from the axis; ``slice_inliers`` (K, S)."""

    params: FloatArray
    alive: NDArray[np.bool_]
    pts: FloatArray
    hh: FloatArray
    ids: NDArray[np.int64]
    s_i: NDArray[np.int64]
    inlier: NDArray[np.bool_]
    resid: FloatArray
    n_in: NDArray[np.int64]
    rms: FloatArray
    cov: FloatArray
    arcs: FloatArray
    slice_inliers: NDArray[np.int64]


def _sparse_clusters(
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    ns: int,
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Points per (cluster, slice) (K, S) and the clusters the shared-axis fit takes: in
    ``todo`` (not made a stem by the per-slice path or the pooled fit), sparse (fullest slice
    < :data:`AXIS_SPARSE_FACTOR` x ``cfg.min_slice_points``), >= 3 points in
    :func:`~stemmap.cloud.pooled._pooled_slices_needed` slices and >= 2 x
    ``cfg.min_slice_points`` points in all."""
    kc = todo.shape[0]
    cnt = np.bincount(cid * ns + sli, minlength=kc * ns).reshape(kc, ns)
    ok = (
        todo
        & (cnt.max(axis=1) < AXIS_SPARSE_FACTOR * cfg.min_slice_points)
        & ((cnt >= 3).sum(axis=1) >= _pooled_slices_needed(cfg, ns))
        & (cnt.sum(axis=1) >= 2 * cfg.min_slice_points)
    )
    return cnt, ok


def _axis_residuals(
    t: FloatArray, p: FloatArray, hh: FloatArray, ids: NDArray[np.int64]
) -> tuple[FloatArray, FloatArray]:
    """Signed distance of each return to its cluster's ring at its height, and the unit
    direction (N, 2) from the axis."""
    cx = t[ids, 0] + t[ids, 2] * hh
    cy = t[ids, 1] + t[ids, 3] * hh
    v = np.column_stack((p[:, 0] - cx, p[:, 1] - cy))
    dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-9)
    return dist - (t[ids, 4] + t[ids, 5] * hh), v / dist[:, None]


def _axis_jacobian(n: FloatArray, hh: FloatArray) -> FloatArray:
    """(N, 6) derivative of the residuals by (cx, cy, lean x, lean y, r, taper)."""
    return np.column_stack(
        (-n[:, 0], -n[:, 1], -n[:, 0] * hh, -n[:, 1] * hh, -np.ones_like(hh), -hh)
    )


def _fit_axes(
    p: FloatArray,
    hh: FloatArray,
    ids: NDArray[np.int64],
    s_i: NDArray[np.int64],
    ns: int,
    noise_floor: float,
) -> _AxisFit:
    """Batched MAP fits of the ring stacks: a Kasa circle start per cluster (taper at the
    prior mean), 10 damped Gauss-Newton steps with Huber weights at 2 x the noise floor and
    the taper prior, trimming of |residual| > 3 x 1.4826 MAD, 10 more steps."""
    k = int(ids.max()) + 1
    k0, sk = TAPER_PRIOR
    first = fit_circles_batch(p, ids, "kasa")
    th = np.zeros((k, _NPAR))
    th[:, 4] = np.nan
    th[:, 5] = k0
    th[first.segment_ids, :2] = first.centers
    th[first.segment_ids, 4] = first.radii
    alive = np.isfinite(th[:, 4]) & (th[:, 4] > 0)
    th[~alive, 4] = 0.1
    w_prior = (max(noise_floor, 1e-4) / sk) ** 2  # information of the prior, in data units

    def taper_prior(A: FloatArray, g: FloatArray, t: FloatArray) -> None:
        A[:, 5, 5] += w_prior
        g[:, 5] += w_prior * (t[:, 5] - k0)

    th, keep = _robust_gauss_newton(
        th, alive, p, hh, ids, noise_floor, _axis_residuals, _axis_jacobian, taper_prior
    )
    d, n = _axis_residuals(th, p, hh, ids)
    nin = np.bincount(ids[keep], minlength=k)
    rms = np.sqrt(np.bincount(ids[keep], d[keep] ** 2, minlength=k) / np.maximum(nin, 1))
    # posterior covariance: data information J^T J / rms^2 plus the prior's on the taper
    info = _normal_matrices(_axis_jacobian(n, hh)[keep], ids[keep], k)
    info = info / np.maximum(rms, 1e-6)[:, None, None] ** 2
    info[:, 5, 5] += 1.0 / sk**2
    cov = np.full((k, _NPAR, _NPAR), np.nan)
    inv_ok = alive & (np.abs(np.linalg.det(info)) > 1e-300)
    if inv_ok.any():
        cov[inv_ok] = np.linalg.inv(info[inv_ok])
    arcs = _segment_arcs(n[keep], ids[keep], k, np.zeros((k, 2)))
    n_sl = np.bincount((ids * ns + s_i)[keep], minlength=k * ns).reshape(k, ns)
    return _AxisFit(th, alive, p, hh, ids, s_i, keep, d, nin, rms, cov, arcs, n_sl)


def _jackknife_var_r(fit: _AxisFit, j: int, noise_floor: float) -> float:
    """Delete-one-slice jackknife variance of fit ``j``'s breast-height radius (Efron & Stein
    1981): the stack refitted without each slice holding inliers in turn,
    ``(m - 1) / m sum (r_s - mean r)^2``. The posterior covariance assumes independent
    residuals; bark, a branch stub or a one-sided arc that fits different radii at
    different heights violates that, and the slices' disagreement is what shows it."""
    mine = fit.inlier & (fit.ids == j)
    s_j = fit.s_i[mine]
    held = np.unique(s_j)
    if held.size < 3:
        return math.inf
    p_all = np.flatnonzero(mine)
    parts = [p_all[s_j != s] for s in held]
    idx = np.concatenate(parts)
    ids = np.repeat(np.arange(held.size), [q.size for q in parts]).astype(np.int64)
    ns = int(fit.slice_inliers.shape[1])
    sub = _fit_axes(fit.pts[idx], fit.hh[idx], ids, fit.s_i[idx], ns, noise_floor)
    r = sub.params[:, 4]
    if not sub.alive.all() or not np.isfinite(r).all():
        return math.inf
    m = r.size
    return float((m - 1) / m * np.sum((r - r.mean()) ** 2))


def _axis_stems(
    pts: FloatArray,
    hts: FloatArray,
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    centers_h: FloatArray,
    noise_floor: float,
    reach: tuple[FloatArray, FloatArray] | None = None,
) -> list[tuple[float, ...]]:
    """Stems of the sparse clusters ``todo`` from one shared-axis fit each
    (:func:`_sparse_clusters`, :func:`_fit_axes`, :func:`_axis_row`).

    ``pts`` (N, 2), ``hts`` heights, ``cid`` cluster and ``sli`` slice of each clustered band
    point (as for :func:`~stemmap.cloud.pooled._pooled_stems`). With ``reach`` (xy, heights
    of the returns in :data:`AXIS_RANGE` outside the band) each candidate also takes the
    returns of the reach about its cluster (:func:`_with_reach`) and the tests read bins of
    :data:`AXIS_BIN` m over the whole range instead of the band's slices. Returns the band's
    stem rows ``(x, y, dbh, n_points, quality, arc, rms, n_slices, taper, dbh_std, cov_xx,
    cov_xy, cov_yy, dbh_height)``."""
    ns = centers_h.shape[0]
    if reach is not None and reach[0].shape[0]:
        return _axis_stems_reach(pts, hts, cid, sli, todo, cfg, centers_h, noise_floor, reach)
    cnt, ok = _sparse_clusters(cid, sli, todo, cfg, ns)
    if not ok.any():
        return []
    sel = ok[cid]
    cl, ids = np.unique(cid[sel], return_inverse=True)
    fit = _fit_axes(
        pts[sel], hts[sel] - cfg.breast_height, ids.astype(np.int64), sli[sel], ns, noise_floor
    )
    rows: list[tuple[float, ...]] = []
    for j in np.flatnonzero(fit.alive):
        row = _axis_row(fit, int(j), cnt[cl[j]], cfg, centers_h, noise_floor)
        if row is not None:
            rows.append(row)
    return rows


def _axis_stems_reach(
    pts: FloatArray,
    hts: FloatArray,
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    centers_h: FloatArray,
    noise_floor: float,
    reach: tuple[FloatArray, FloatArray],
) -> list[tuple[float, ...]]:
    """:func:`_axis_stems` over :data:`AXIS_RANGE`, in two stages. 1: the sparse clusters
    of ``todo`` with >= 2 x ``cfg.min_slice_points`` band points (no per-slice count) are
    fitted on the band alone (:func:`_fit_axes`): a provisional axis, radius and taper.
    2: each takes the reach's returns within :func:`_reach_tolerance` of its provisional
    ring at their height (the reach was not through the vertical filter: branches, crowns
    and understory are there, so only returns about the predicted ring are taken) and the
    whole stack is fitted again; the tests read the bins (:func:`_bins`) as slices."""
    ns = centers_h.shape[0]
    kc = todo.shape[0]
    cnt_b = np.bincount(cid * ns + sli, minlength=kc * ns).reshape(kc, ns)
    ok_c = (
        todo
        & (cnt_b.max(axis=1) < AXIS_SPARSE_FACTOR * cfg.min_slice_points)
        & (cnt_b.sum(axis=1) >= 2 * cfg.min_slice_points)
    )
    if not ok_c.any():
        return []
    sel = ok_c[cid]
    cand, ids0 = np.unique(cid[sel], return_inverse=True)
    hh0 = hts[sel] - cfg.breast_height
    first = _fit_axes(pts[sel], hh0, ids0.astype(np.int64), sli[sel], ns, noise_floor)
    lo_b, hi_b = cfg.band
    lo, hi = min(AXIS_RANGE[0], lo_b), max(AXIS_RANGE[1], hi_b)
    bc, th_b = _bins(lo, hi)
    nb = bc.size
    from scipy.spatial import cKDTree

    rxy, rh = reach
    tree = cKDTree(rxy)
    far = max(lo_b - lo, hi - hi_b)
    ps, hs_, idl = [pts[sel]], [hts[sel]], [ids0.astype(np.int64)]
    for j in np.flatnonzero(first.alive):
        t = first.params[j]
        if not (0 < t[4] <= cfg.max_diameter / 2):
            continue
        tol_far = _reach_tolerance(float(t[4]), noise_floor, far)
        near = np.asarray(
            tree.query_ball_point(t[:2], t[4] + POOL_MAX_LEAN * far + tol_far), dtype=np.int64
        )
        if near.size == 0:
            continue
        dh = np.maximum(lo_b - rh[near], rh[near] - hi_b).clip(min=0.0)
        d, _ = _axis_residuals(
            t[None, :], rxy[near], rh[near] - cfg.breast_height, np.zeros(near.size, np.int64)
        )
        near = near[np.abs(d) <= _reach_tolerance(float(t[4]), noise_floor, dh)]
        ps.append(rxy[near])
        hs_.append(rh[near])
        idl.append(np.full(near.size, j, dtype=np.int64))
    p_all, h_all, ids = np.vstack(ps), np.concatenate(hs_), np.concatenate(idl)
    b_all = np.clip(((h_all - lo) // th_b).astype(np.int64), 0, nb - 1)
    cnt = np.bincount(ids * nb + b_all, minlength=cand.size * nb).reshape(cand.size, nb)
    ok = first.alive & ((cnt >= 3).sum(axis=1) >= _bins_needed(nb))
    if not ok.any():
        return []
    sel2 = ok[ids]
    kk, ids2 = np.unique(ids[sel2], return_inverse=True)
    fit = _fit_axes(
        p_all[sel2],
        h_all[sel2] - cfg.breast_height,
        ids2.astype(np.int64),
        b_all[sel2],
        nb,
        noise_floor,
    )
    rows: list[tuple[float, ...]] = []
    for j in np.flatnonzero(fit.alive):
        row = _axis_row(fit, int(j), cnt[kk[j]], cfg, bc, noise_floor, _bins_needed(nb))
        if row is not None:
            rows.append(row)
    return rows


def _reach_tolerance(r: float, noise_floor: float, dh: FloatArray | float) -> FloatArray:
    """Largest |distance to the provisional ring| of a reach return ``dh`` m beyond the
    band: max(3 noise floors, 10 % of r) -- the band's own spread -- plus 3 degrees of lean
    error and :data:`TAPER_PRIOR`'s 2 standard deviations of taper error over ``dh``."""
    base = max(3.0 * noise_floor, 0.1 * r)
    return np.asarray(base + (math.tan(math.radians(3.0)) + 2 * TAPER_PRIOR[1]) * np.asarray(dh))


def _bins(lo: float, hi: float) -> tuple[FloatArray, float]:
    """Centres and thickness of the equal bins of about :data:`AXIS_BIN` m (at least 3)
    over [``lo``, ``hi``]."""
    nb = max(3, round((hi - lo) / AXIS_BIN))
    th = (hi - lo) / nb
    return np.asarray(lo + th * (np.arange(nb) + 0.5), dtype=np.float64), th


def _bins_needed(nb: int) -> int:
    """Bins of the reach that must hold >= 3 inliers: three quarters of them, rounded up
    (3 of 3 as the pooled fit on a sparse band; 5 of 6 over 0.5-3.0 m)."""
    return max(3, math.ceil(0.75 * nb))


def _axis_row(
    fit: _AxisFit,
    j: int,
    cnt: NDArray[np.int64],
    cfg: StemConfig,
    centers_h: FloatArray,
    noise_floor: float,
    needed: int | None = None,
) -> tuple[float, ...] | None:
    """The stem row of fit ``j`` (``cnt``: its cluster's points per slice), or None.

    The pooled fit's tests (radius window, RMS <= 1.5 noise floors, lean <= 10 degrees, arc,
    >= 2 x ``min_slice_points`` inliers and half the cluster, >= 3 inliers in the top slice
    and in :func:`~stemmap.cloud.pooled._pooled_slices_needed` slices spanning
    ``min_vertical_extent``, each slice's median residual within 3 standard errors or 5 % of
    r), the taper within ``cfg.max_taper``, and the one this fit adds: the DBH standard
    error (the larger of the posterior's and the slice jackknife's) <=
    :data:`AXIS_MAX_DBH_STD`; that standard error is the row's ``dbh_std``."""
    th, fr = fit.params[j], fit.params[j, 4]
    rj = float(fr)
    if not (cfg.min_diameter / 2 <= rj <= cfg.max_diameter / 2):
        return None
    if fit.rms[j] > POOL_RESIDUAL_FACTOR * noise_floor or abs(th[5]) > cfg.max_taper:
        return None
    if math.hypot(th[2], th[3]) > POOL_MAX_LEAN or fit.arcs[j] < cfg.min_arc_deg:
        return None
    if fit.n_in[j] < 2 * cfg.min_slice_points or fit.n_in[j] < 0.5 * int(cnt.sum()):
        return None
    var_r = max(float(fit.cov[j, 4, 4]), _jackknife_var_r(fit, j, noise_floor))
    if not (math.isfinite(var_r) and 2 * math.sqrt(var_r) <= AXIS_MAX_DBH_STD):
        return None
    hs = fit.slice_inliers[j] >= 3
    if needed is None:
        needed = _pooled_slices_needed(cfg, centers_h.shape[0])
    if not hs[-1] or hs.sum() < needed:
        return None
    if np.ptp(centers_h[hs]) < cfg.min_vertical_extent - 1e-9:
        return None
    mine = fit.inlier & (fit.ids == j)
    hh = centers_h - cfg.breast_height
    for s in np.flatnonzero(hs):
        rs = fit.resid[mine & (fit.s_i == s)]
        tol_s = max(3.0 * 1.25 * noise_floor / math.sqrt(rs.size), 0.05 * (rj + th[5] * hh[s]))
        if abs(float(np.median(rs))) > tol_s:
            return None
    frac = float(hs.sum()) / max(int((cnt > 0).sum()), 1)
    q = frac * min(1.0, fit.arcs[j] / 120.0) * min(1.0, noise_floor / max(fit.rms[j], 1e-6))
    c = fit.cov[j]
    return (
        float(th[0]),
        float(th[1]),
        2 * rj,
        int(fit.n_in[j]),
        q,
        float(fit.arcs[j]),
        float(fit.rms[j]),
        int(hs.sum()),
        float(th[5]),
        2 * math.sqrt(var_r),
        float(c[0, 0]),
        float(c[0, 1]),
        float(c[1, 1]),
        cfg.breast_height,
    )


def _reach_range(cfg: StemConfig) -> tuple[float, float]:
    """Heights the band is read over: the band, widened to :data:`AXIS_RANGE` when the
    shared-axis fit will use the reach (``cfg.axis_fallback`` and ``cfg.axis_reach``) or
    the taller-band fit of sparse stems (``cfg.sparse_tall_fit``, same range)."""
    lo, hi = cfg.band
    if not ((cfg.axis_fallback and cfg.axis_reach) or cfg.sparse_tall_fit):
        return lo, hi
    return min(lo, AXIS_RANGE[0]), max(hi, AXIS_RANGE[1])


def _split_reach(
    xyz: FloatArray, h: FloatArray, m: NDArray[np.int64], lo: float, hi: float
) -> tuple[NDArray[np.int64], tuple[FloatArray, FloatArray] | None]:
    """The indices ``m`` (points read with heights ``h``) split into the band's, those with
    ``lo <= h <= hi`` in point order (the same as reading the band alone), and the reach's
    (xy, heights), None when nothing was read outside the band."""
    hm = h[m]
    inb = (hm >= lo) & (hm <= hi)
    if inb.all():
        return m, None
    out = m[~inb]
    return m[inb], (np.ascontiguousarray(xyz[out, :2]), hm[~inb])
