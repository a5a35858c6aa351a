"""Circle fits of horizontal slices (ours): point spacing, arc coverage, RANSAC start, robust
batched geometric fits with outlier trimming, refinement along the rays, Theil-Sen lines."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from stemmap import _numba_cache
from stemmap.cloud.stubtrim import STUB_TRIM_ROUNDS, trim_keep
from stemmap.scan import _fit_geometric, _fit_lm
from stemmap.scan._fit_geometric import kasa_start
from stemmap.scan._fit_lm import levenberg_marquardt
from stemmap.scan.circle import fit_circles_batch
from stemmap.types import FloatArray


def _band_spacing(xy: FloatArray, h: FloatArray, rng: int = 0) -> float:
    """90th percentile of the 3D nearest-neighbour distance of band points (sampled).

    3D, not in the xy projection: a scanner's rows stack on a trunk, so projected neighbours
    are much closer than neighbours along the arc, which is what clustering must bridge. The
    90th percentile (not the median) speaks for the sparse, far trunks. Coincident points
    (an export that wrote every point twice, merged scans, coordinates quantised to 1 cm)
    are one point: the distance is to the nearest of 8 neighbours that is not at the same
    place, so duplicates do not make the spacing unmeasurable.
    """
    from scipy.spatial import cKDTree

    n = xy.shape[0]
    if n < 3:
        return math.nan
    p = np.column_stack((xy, h))
    gen = np.random.default_rng(rng)
    q = p if n <= 20_000 else p[gen.choice(n, 20_000, replace=False)]
    d, _ = cKDTree(p).query(q, k=min(8, n))
    d = np.where(d[:, 1:] > 1e-9, d[:, 1:], np.inf).min(axis=1)
    d = d[np.isfinite(d)]
    return float(np.quantile(d, 0.9)) if d.size else math.nan


def _far_origins(
    pts: FloatArray, ids: NDArray[np.int64], k: int, centers: FloatArray
) -> FloatArray:
    """A viewpoint far out on the visible side of each segment (for the geometric fit's
    'centre behind the arc' test): centre + 1 km along (points' centroid - centre)."""
    cnt = np.maximum(np.bincount(ids, minlength=k), 1)
    cen = np.column_stack([np.bincount(ids, pts[:, j], k) / cnt for j in range(2)])
    d = cen - centers
    norm = np.hypot(d[:, 0], d[:, 1])
    d = np.where(norm[:, None] > 1e-6, d / np.maximum(norm, 1e-12)[:, None], [1.0, 0.0])
    c = np.where(np.isfinite(centers), centers, cen)
    return np.asarray(c + 1000.0 * d, dtype=np.float64)


def _segment_arcs(
    pts: FloatArray, ids: NDArray[np.int64], k: int, centers: FloatArray
) -> FloatArray:
    """Arc coverage (degrees) of every segment around its centre, vectorised."""
    a = np.arctan2(pts[:, 1] - centers[ids, 1], pts[:, 0] - centers[ids, 0])
    order = np.lexsort((a, ids))
    a, s = a[order], ids[order]
    nxt = np.roll(a, -1)
    first = np.ones(s.shape[0], dtype=bool)
    first[1:] = s[1:] != s[:-1]
    last = np.roll(first, -1)
    # wrap: the gap after a segment's last angle goes to its first angle + 2 pi
    first_angle = a[first]
    seg_of_first = s[first]
    wrap_to = np.empty(k)
    wrap_to[seg_of_first] = first_angle + 2 * np.pi
    gap = np.where(last, wrap_to[s] - a, nxt - a)
    maxgap = np.zeros(k)
    np.maximum.at(maxgap, s, gap)
    cnt = np.bincount(ids, minlength=k)
    arc = np.degrees(2 * np.pi - maxgap)
    return np.asarray(np.where(cnt >= 2, arc, 0.0), dtype=np.float64)


def _segment_rng(n: int, seed: int = 0) -> np.random.Generator:
    """The random generator of one segment of ``n`` points: ``seed`` 0 (the default,
    ``StemConfig.ransac_seed``) seeds it by the point count alone, another value draws
    ``default_rng((seed, n))`` -- other, equally valid draws (benchmarks measure the spread of
    the results over seeds with it: benchmarks/cloud_ransac_seeds.py)."""
    return np.random.default_rng(n if seed == 0 else (seed, n))


def _circle_scores(
    q: FloatArray, ux: FloatArray, uy: FloatArray, r: FloatArray, tol: float, msac: bool
) -> FloatArray:
    """Score of each circle (ux, uy, r) on the points ``q`` (higher is better).

    Inlier count (``msac`` False), or the MSAC score (Torr & Zisserman 2000): each point
    within ``tol`` counts ``1 - (d / tol)^2`` (the truncated quadratic cost, as a score),
    so among circles with the same support the tighter one wins instead of the luckier
    draw. Either way a trunk is opaque: returns more than ``3 tol`` inside a candidate
    circle (branches, needles, a neighbour's clutter) count -1 each. One compiled pass
    (:func:`_scores_kernel`; the counts are exact integers, the MSAC sums run in point order).
    """
    out = np.empty(ux.shape[0])
    _scores_kernel(
        np.ascontiguousarray(q[:, 0]),
        np.ascontiguousarray(q[:, 1]),
        np.ascontiguousarray(ux, dtype=np.float64),
        np.ascontiguousarray(uy, dtype=np.float64),
        np.ascontiguousarray(r, dtype=np.float64),
        float(tol),
        bool(msac),
        out,
    )
    return out


@njit(cache=True)
def _score_one(
    qx: FloatArray, qy: FloatArray, cx: float, cy: float, r: float, tol: float, msac: bool
) -> float:  # pragma: no cover - numba
    """:func:`_circle_scores` of one circle."""
    s = 0.0
    for i in range(qx.shape[0]):
        d = math.sqrt((qx[i] - cx) ** 2 + (qy[i] - cy) ** 2) - r
        if abs(d) <= tol:
            s += 1.0 - (d / tol) ** 2 if msac else 1.0
        elif d < -3.0 * tol:
            s -= 1.0
    return s


@njit(cache=True)
def _scores_kernel(
    qx: FloatArray,
    qy: FloatArray,
    ux: FloatArray,
    uy: FloatArray,
    r: FloatArray,
    tol: float,
    msac: bool,
    out: FloatArray,
) -> None:  # pragma: no cover - numba
    for k in range(ux.shape[0]):
        out[k] = _score_one(qx, qy, ux[k], uy[k], r[k], tol, msac)


#: rounds of the local optimisation of one hypothesis (refit to its inliers, re-score)
LO_ROUNDS = 4


def _local_optimisation(
    q: FloatArray,
    ux: FloatArray,
    uy: FloatArray,
    r: FloatArray,
    score: FloatArray,
    tol: float,
    radius_window: tuple[float, float],
    n_iter: int = LO_ROUNDS,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """LO-RANSAC's local optimisation (Chum, Matas & Kittler 2003, the iterated
    least-squares step) of K circles: each is refitted to the points within ``tol`` of it
    and re-scored (:func:`_circle_scores`, MSAC); a refit replaces its circle when its score
    is higher and its radius inside ``radius_window``, at most ``n_iter`` times. Returns the
    circles and their scores.

    The refit is the project's geometric circle fit of the scan detector: the algebraic
    start (Kasa 1976; :func:`stemmap.scan._fit_geometric.kasa_start`) and
    Levenberg-Marquardt on the orthogonal distances
    (:func:`stemmap.scan._fit_lm.levenberg_marquardt`, plain least squares, no silhouette
    terms; Chernov 2010, §4.4), compiled with the inlier selection and scoring into one pass
    over the K circles (:func:`_lo_kernel`).

    A minimal sample's circle is three noisy points: on a spruce slice a stem sample often
    scores below a circle through the branch clutter, and whether a draw close enough to the
    stem came up decided the fit (23.6-25.0 cm over 12 seeds). Its least-squares refit on
    its inliers is the stem's circle whichever of the stem's samples was drawn."""
    ux, uy, r, score = (np.array(a, dtype=np.float64) for a in (ux, uy, r, score))
    if ux.shape[0]:
        _lo_kernel(
            np.ascontiguousarray(q[:, 0]),
            np.ascontiguousarray(q[:, 1]),
            ux,
            uy,
            r,
            score,
            float(tol),
            float(radius_window[0]),
            float(radius_window[1]),
            int(n_iter),
        )
    return ux, uy, r, score


@njit(cache=True)
def _lo_kernel(
    qx: FloatArray,
    qy: FloatArray,
    ux: FloatArray,
    uy: FloatArray,
    r: FloatArray,
    score: FloatArray,
    tol: float,
    r_min: float,
    r_max: float,
    n_iter: int,
) -> None:  # pragma: no cover - numba
    """:func:`_local_optimisation` in place on (ux, uy, r, score)."""
    m = qx.shape[0]
    lx = np.empty(m)
    ly = np.empty(m)
    keep = np.ones(m)
    unused = np.zeros(m)  # ranges and ray directions: only the range model reads them
    ws3 = np.empty((3, 3, 3))
    wv = np.empty((8, 3))
    mdl = np.zeros(10)  # orthogonal distances, sigma 1, no silhouette (_fit_lm._cost_and_normal)
    mdl[0] = 1.0
    p = np.empty(3)
    for k in range(ux.shape[0]):
        for _ in range(n_iter):
            n = 0
            for i in range(m):
                d = math.sqrt((qx[i] - ux[k]) ** 2 + (qy[i] - uy[k]) ** 2) - r[k]
                if abs(d) <= tol:
                    lx[n] = qx[i]
                    ly[n] = qy[i]
                    n += 1
            if n < 3 or not kasa_start(lx[:n], ly[:n], p):
                break
            levenberg_marquardt(
                lx[:n],
                ly[:n],
                unused[:n],
                unused[:n],
                unused[:n],
                keep[:n],
                p,
                mdl,
                0.0,
                False,
                ws3,
                wv,
                1.0,
            )
            if not (math.isfinite(p[0]) and math.isfinite(p[1]) and r_min <= p[2] <= r_max):
                break
            s = _score_one(qx, qy, p[0], p[1], p[2], tol, True)
            if not s > score[k]:
                break
            ux[k], uy[k], r[k], score[k] = p[0], p[1], p[2], s


#: hypotheses of each RANSAC batch that are locally optimised (the highest-scoring ones)
LO_TOP = 8


def _ransac_circle(
    q: FloatArray,
    tol: float,
    radius_window: tuple[float, float],
    gen: np.random.Generator,
    n_hyp: int = 96,
    max_hyp: int = 1536,
    lo: bool = True,
) -> tuple[float, float, float] | None:
    """Circle through 3 random points with the best score (:func:`_circle_scores`) on the
    points within ``tol``; None if no hypothesis has a radius inside ``radius_window``.

    Hypotheses are drawn in vectorised batches of ``n_hyp`` until the standard RANSAC count
    for 99 % confidence, ``log(0.01) / log(1 - w^3)`` with ``w`` the best inlier fraction so
    far (Fischler & Bolles 1981), is reached, at most ``max_hyp``: a thin spruce stem is a
    quarter of the points of a slice full of branches, which one fixed batch of 96 misses
    about a time in four. With ``lo`` (``StemConfig.ransac_lo``) the scores are MSAC's and
    the :data:`LO_TOP` best hypotheses of every batch are locally optimised
    (:func:`_local_optimisation`; LO-RANSAC, Chum et al. 2003) before the best of them is
    compared with the best so far.
    """
    m = q.shape[0]
    if m < 3:
        return None
    # centred for the algebraic fits of the local optimisation (exact arithmetic at UTM
    # coordinates); the plain count keeps the points as given
    q0 = q.mean(axis=0) if lo else np.zeros(2)
    q = q - q0
    best: tuple[float, float, float] | None = None
    best_score = -m - 1.0
    drawn = 0
    need = n_hyp
    while drawn < min(need, max_hyp):
        drawn += n_hyp
        t = gen.integers(0, m, (n_hyp, 3))
        a, b, c = q[t[:, 0]], q[t[:, 1]], q[t[:, 2]]
        d = 2 * (
            a[:, 0] * (b[:, 1] - c[:, 1])
            + b[:, 0] * (c[:, 1] - a[:, 1])
            + c[:, 0] * (a[:, 1] - b[:, 1])
        )
        good = np.abs(d) > 1e-12
        if not good.any():
            continue
        a, b, c, d = a[good], b[good], c[good], d[good]
        a2, b2, c2 = (a * a).sum(1), (b * b).sum(1), (c * c).sum(1)
        ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
        uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
        r = np.hypot(a[:, 0] - ux, a[:, 1] - uy)
        inwin = (r >= radius_window[0]) & (r <= radius_window[1])
        if not inwin.any():
            continue
        ux, uy, r = ux[inwin], uy[inwin], r[inwin]
        score = _circle_scores(q, ux, uy, r, tol, lo)
        if lo:
            top = np.argsort(-score, kind="stable")[:LO_TOP]
            ux, uy, r, score = _local_optimisation(
                q, ux[top], uy[top], r[top], score[top], tol, radius_window
            )
        j = int(np.argmax(score))
        if score[j] > best_score:
            best_score = float(score[j])
            best = float(ux[j]) + q0[0], float(uy[j]) + q0[1], float(r[j])
            # w: the count score (inliers less the returns inside) as a fraction
            w = max(
                float(_circle_scores(q, ux[j : j + 1], uy[j : j + 1], r[j : j + 1], tol, False)[0]),
                0.0,
            )
            w3 = min((w / m) ** 3, 1 - 1e-12)
            need = math.ceil(math.log(0.01) / math.log1p(-w3)) if w3 > 0 else max_hyp
    return best


def _fit_segments(
    pts: FloatArray,
    ids: NDArray[np.int64],
    k: int,
    method: str,
    *,
    ransac_tol: float = 0.0,
    radius_window: tuple[float, float] = (0.0, np.inf),
    ray_origins: FloatArray | None = None,
    ransac_lo: bool = True,
    ransac_seed: int = 0,
    window: float = 3.0,
    stub_trim: float = 0.0,
    stub_surface: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.int64]]:
    """Robust batched circle fit of K segments: fit, trim |res| > 3 sigma (MAD), refit.

    With ``ray_origins`` (N, 2: each point's sensor position) the result is refined with
    residuals along the rays (:func:`_refine_along_rays`). Returns centres (K, 2), radii,
    rms, ok, inlier counts; rows for ids absent from ``ids`` are NaN / False. ``ransac_lo``:
    the RANSAC start is locally optimised (:func:`_ransac_circle`); ``ransac_seed``: its
    draws (:func:`_segment_rng`; ``StemConfig.ransac_seed``). ``window``
    (``StemConfig.slice_fit_window``, 3): the points kept after a RANSAC start are those
    within ``window`` tolerances of its circle, and the trim drops residuals beyond
    ``window x 1.4826 x MAD``. ``stub_trim`` (``StemConfig.slice_stub_trim``, 0: off): the
    MAD is taken over the residuals inside the circle only, the trim also drops residuals
    more than ``stub_trim x 1.4826 x MAD`` outside it, and the fit is trimmed and refitted
    :data:`~stemmap.cloud.stubtrim.STUB_TRIM_ROUNDS` times (docs/algorithms/cloud.md "The
    noisy spruce: a trim scaled by the inside half"); ``stub_surface``
    (``StemConfig.slice_stub_surface``): that outside bound is measured from the local surface
    (:func:`~stemmap.cloud.stubtrim.trim_keep`).
    """
    centers = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    rms = np.full(k, np.nan)
    ok = np.zeros(k, dtype=bool)
    nin = np.zeros(k, dtype=np.int64)
    if pts.shape[0] == 0:
        return centers, radii, rms, ok, nin
    first = fit_circles_batch(pts, ids, "kasa")
    c0 = np.full((k, 2), np.nan)
    c0[first.segment_ids] = first.centers
    keep = np.ones(pts.shape[0], dtype=bool)
    # segments the algebraic fit explains badly (a branch or a bush glued to the trunk): find
    # the dominant circle by RANSAC first and start from its inliers
    # (or whose circle is outside the radius window: a spruce's whorl of branches around a thin
    # stem gives a large circle through the clutter with a small *relative* residual)
    suspect = (
        ~first.ok
        | (first.rms > 0.05 * np.where(first.ok, first.radii, 1.0))
        | (first.radii < radius_window[0])
        | (first.radii > radius_window[1])
    )
    if suspect.any() and ransac_tol > 0:
        order = np.argsort(ids, kind="stable")
        starts = np.searchsorted(ids[order], first.segment_ids)
        stops = np.searchsorted(ids[order], first.segment_ids, side="right")
        for row in np.flatnonzero(suspect)[:2000]:
            idx = order[starts[row] : stops[row]]
            # seeded per segment (by its point count), not by a stream shared with the
            # segments before it: a segment gets the same draws in any chunk of a catalog as
            # in the whole cloud (docs/algorithms/engine.md), and in a shifted copy of it
            gen = _segment_rng(idx.size, ransac_seed)
            best = _ransac_circle(pts[idx], ransac_tol, radius_window, gen, lo=ransac_lo)
            if best is None:
                continue
            cx, cy, r = best
            res = np.abs(np.hypot(pts[idx, 0] - cx, pts[idx, 1] - cy) - r)
            keep[idx] = res <= window * ransac_tol
            c0[first.segment_ids[row]] = (cx, cy)
    rounds = 2 + (STUB_TRIM_ROUNDS - 1 if stub_trim > 0 else 0)
    todo = np.ones(k, dtype=bool)  # the segments (re)fitted this round
    for it in range(rounds):
        sel = keep & todo[ids]
        sel_ids = ids[sel]
        present = np.unique(sel_ids)
        if present.size == 0:
            break
        if method == "kasa":
            fits = fit_circles_batch(pts[sel], sel_ids, "kasa")
        else:
            origins = _far_origins(pts[sel], sel_ids, k, c0)[present]
            fits = fit_circles_batch(
                pts[sel],
                sel_ids,
                method,
                origin=origins,
                edges=np.zeros((present.size, 2), dtype=bool),
            )
        centers[todo] = np.nan
        radii[todo] = np.nan
        ok[todo] = False
        centers[fits.segment_ids] = fits.centers
        radii[fits.segment_ids] = fits.radii
        ok[fits.segment_ids] = fits.ok
        c0 = np.where(np.isfinite(centers), centers, c0)
        if it == rounds - 1:
            break
        # trim outliers (stubtrim.trim_keep: symmetric MAD trim, or the stub trim)
        kept = keep
        keep = trim_keep(pts, ids, k, centers, radii, ok, keep, window, stub_trim, stub_surface)
        if it >= 1:
            # the stub trim's further rounds refit only the segments whose points changed
            todo = np.bincount(ids[keep != kept], minlength=k) > 0
            if not todo.any():
                break
    if ray_origins is not None and method != "kasa":
        sel = ok[ids] & keep
        wide = ok & (
            _segment_arcs(pts[sel], ids[sel], k, np.where(ok[:, None], centers, 0))
            >= RAY_MIN_ARC_DEG
        )
        sel &= wide[ids]
        centers, radii = _refine_along_rays(
            pts[sel], ids[sel], ray_origins[sel], k, centers, radii, wide
        )
    res2 = np.full(pts.shape[0], np.nan)
    good = ok[ids] & keep
    res2[good] = np.hypot(*(pts[good] - centers[ids[good]]).T) - radii[ids[good]]
    nin = np.bincount(ids[good], minlength=k).astype(np.int64)
    ss = np.bincount(ids[good], res2[good] ** 2, minlength=k)
    rms = np.sqrt(ss / np.maximum(nin, 1))
    rms = np.where(nin > 0, rms, np.nan)
    return centers, radii, rms, ok, nin


RAY_MIN_COS = 0.5
RAY_MIN_ARC_DEG = 90.0


def _range_errors(
    pts: FloatArray, ids: NDArray[np.int64], u: FloatArray, c: FloatArray, r: FloatArray
) -> FloatArray:
    """Range error of each point along its (horizontal, unit) ray ``u`` for circles (c, r).

    The ray enters the circle at ``p - e u`` with ``|p - e u - c| = r``; the entry nearest the
    sensor is ``e = w.u + sqrt((w.u)^2 - |w|^2 + r^2)``, ``w = p - c`` (exact, any incidence).
    Rays that miss the circle (negative discriminant: grazing returns pushed outside by noise)
    get the orthogonal residual scaled as at a 60-degree incidence, ``d / RAY_MIN_COS`` (0.5;
    a heuristic: beyond the tangent no range error reaches the circle).
    """
    w = pts - c[ids]
    wu = np.sum(w * u, axis=1)
    ww = np.sum(w * w, axis=1)
    disc = wu * wu - ww + r[ids] ** 2
    d = np.sqrt(ww) - r[ids]
    return np.asarray(
        np.where(disc >= 0, wu + np.sqrt(np.maximum(disc, 0.0)), d / RAY_MIN_COS),
        dtype=np.float64,
    )


def _refine_along_rays(
    pts: FloatArray,
    ids: NDArray[np.int64],
    origins: FloatArray,
    k: int,
    centers: FloatArray,
    radii: FloatArray,
    ok: NDArray[np.bool_],
    n_iter: int = 10,
) -> tuple[FloatArray, FloatArray]:
    """Refine circle fits by minimising each point's range error along its ray.

    A lidar's range noise lies along the ray. The orthogonal distance of a point to the
    circle is then about ``eps cos(alpha)`` (alpha: incidence angle between the horizontal
    ray and the surface normal): full on the front of a one-sided arc, small on its flanks,
    where the noise moves returns along the surface and, at grazing incidence, outside it. An
    orthogonal-distance fit treats all returns alike and shrinks the radius of one-sided arcs
    (2D Monte Carlo, r = 14 cm, half arc, 3 cm noise along one view direction: -0.7 to -0.9 cm
    of DBH; radial noise: none; docs/algorithms/cloud.md, Known limits). The maximum-likelihood
    fit under range noise minimises the range errors themselves (:func:`_range_errors`,
    exact at any incidence). Batched damped Gauss-Newton over (cx, cy, r) of all segments,
    finite-difference Jacobian (the exact residual's derivative is singular at tangency),
    soft-L1 weights with a scale of 3 x the segment's orthogonal RMS (about 2.5 range-noise
    sigmas), 10 iterations from the orthogonal fit. Segments whose step fails keep their
    current fit. The caller refines only arcs of at least ``RAY_MIN_ARC_DEG`` (90): on
    narrower arcs the radius is ill-conditioned (sagitta < 30 % of r) and its random error,
    not this bias, dominates (a 28-56 degree trunk of the terrestrial benchmark moved by
    3.5 cm with the first-order variant).
    """
    c = centers.copy()
    r = radii.copy()
    if pts.shape[0] == 0:
        return c, r
    u = pts - origins
    u = u / np.maximum(np.hypot(u[:, 0], u[:, 1]), 1e-9)[:, None]
    cnt = np.bincount(ids, minlength=k)
    d0 = np.hypot(*(pts - c[ids]).T) - r[ids]
    rms0 = np.sqrt(np.bincount(ids, d0 * d0, minlength=k) / np.maximum(cnt, 1))
    f = np.maximum(3.0 * rms0, 1e-3)[ids]
    hstep = 1e-6
    for _ in range(n_iter):
        e = _range_errors(pts, ids, u, c, r)
        w = 1.0 / np.sqrt(1.0 + (e / f) ** 2)  # soft-L1 (IRLS)
        J = np.empty((pts.shape[0], 3))
        for j in range(3):
            cc, rr = c.copy(), r.copy()
            if j < 2:
                cc[:, j] += hstep
            else:
                rr += hstep
            J[:, j] = (_range_errors(pts, ids, u, cc, rr) - e) / hstep
        A, g = _damped_normal_equations(J, w, e, ids, k)
        good = ok & (cnt >= 3)
        if not good.any():
            break
        step = np.zeros((k, 3))
        step[good] = np.linalg.solve(A[good], -g[good][:, :, None])[:, :, 0]
        r_new = r + step[:, 2]
        good &= (
            np.isfinite(step).all(axis=1)
            & (r_new > 0)
            & (np.abs(step[:, 2]) < 0.5 * np.maximum(r, 1e-3))
        )
        c = np.where(good[:, None], c + step[:, :2], c)
        r = np.where(good, r_new, r)
    return c, r


def _theil_sen(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    """Theil-Sen line ``y = a + b x`` (Theil 1950, Sen 1968): b the median of the pairwise
    slopes ``(y_j - y_i) / (x_j - x_i)`` over the pairs with ``|x_j - x_i| > 1e-9`` (0 when
    there is none), a the median of ``y - b x``.

    One compiled pass over the float64 arrays (no index arrays, masks or copies; a stem's
    handful of slices made numpy's per-call overhead most of the cost) with numpy's median
    -- the middle value, or the mean of the two middle values, NaN when a value is NaN --,
    so the same values bit for bit as ``np.median`` over the same slopes (tested).
    """
    a, b = _theil_sen_kernel(
        np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(y, dtype=np.float64)
    )
    return float(a), float(b)


@njit(cache=True)
def _median_of(v: FloatArray) -> float:
    # numpy's median of a 1-D array: NaN if any value is NaN (np.median propagates it), the
    # middle order statistic, or (lower + upper) / 2 -- np.mean of the two, as np.median
    n = v.shape[0]
    if n == 0:
        return np.nan
    for k in range(n):
        if np.isnan(v[k]):
            return np.nan
    w = np.sort(v)
    h = n // 2
    if n % 2:
        return float(w[h])
    return float((w[h - 1] + w[h]) / 2.0)


@njit(cache=True)
def _theil_sen_kernel(x: FloatArray, y: FloatArray) -> tuple[float, float]:
    n = x.shape[0]
    slopes = np.empty(n * (n - 1) // 2)
    m = 0
    for i in range(n):
        for j in range(i + 1, n):
            dx = x[j] - x[i]
            if abs(dx) > 1e-9:
                slopes[m] = (y[j] - y[i]) / dx
                m += 1
    b = _median_of(slopes[:m]) if m > 0 else 0.0
    res = np.empty(n)
    for k in range(n):
        res[k] = y[k] - b * x[k]  # two roundings, as numpy (no fused multiply-add)
    return _median_of(res), b


def _damped_normal_equations(
    J: FloatArray, w: FloatArray, res: FloatArray, ids: NDArray[np.int64], k: int
) -> tuple[FloatArray, FloatArray]:
    """Per-segment weighted Gauss-Newton system of stacked rows (Jacobian ``J`` (N, P),
    weights ``w``, residuals ``res``): ``A = J^T W J`` with Levenberg damping (1e-3 x its
    diagonal, + 1e-12 I) (K, P, P) and the gradient ``g = J^T W res`` (K, P); the step is
    ``-A^-1 g``."""
    npar = J.shape[1]
    A = np.zeros((k, npar, npar))
    g = np.zeros((k, npar))
    for a in range(npar):
        g[:, a] = np.bincount(ids, w * J[:, a] * res, minlength=k)
        for b in range(a, npar):
            A[:, a, b] = A[:, b, a] = np.bincount(ids, w * J[:, a] * J[:, b], minlength=k)
    A += 1e-3 * np.einsum("kii->ki", A)[:, :, None] * np.eye(npar)[None] + 1e-12 * np.eye(npar)
    return A, g


def _normal_matrices(J: FloatArray, ids: NDArray[np.int64], k: int) -> FloatArray:
    """Per-segment normal matrices ``J^T J`` (K, P, P) of stacked Jacobian rows ``J`` (N, P)."""
    npar = J.shape[1]
    A = np.zeros((k, npar, npar))
    for a in range(npar):
        for b in range(a, npar):
            A[:, a, b] = A[:, b, a] = np.bincount(ids, J[:, a] * J[:, b], minlength=k)
    return A


def _segment_covariances(
    pts: FloatArray,
    ids: NDArray[np.int64],
    k: int,
    centers: FloatArray,
    radii: FloatArray,
    rms: FloatArray,
) -> FloatArray:
    """Covariance (K, 3, 3) of each segment's circle (cx, cy, r) from its fit.

    The Gauss-Newton covariance of an orthogonal-distance circle fit, ``s^2 (J^T J)^-1``
    with ``J_i = -[(x_i - cx) / d_i, (y_i - cy) / d_i, 1]`` (the derivative of the residual
    ``d_i - r``) and ``s`` the segment's residual RMS, over the points within 3 RMS of the
    circle (the fit's inliers; Chernov 2010, "Circular and linear regression", §6.4). Rows
    without a fit are NaN; an arc too short to fix all three parameters gives a huge or NaN
    covariance, as it should.
    """
    cov = np.full((k, 3, 3), np.nan)
    if pts.shape[0] == 0:
        return cov
    ok = np.isfinite(radii[ids]) & np.isfinite(rms[ids])
    v = pts[ok] - centers[ids[ok]]
    d = np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-12)
    res = d - radii[ids[ok]]
    s = np.maximum(rms[ids[ok]], 1e-4)
    inl = np.abs(res) <= 3 * s
    i = ids[ok][inl]
    J = np.column_stack((-v[inl, 0] / d[inl], -v[inl, 1] / d[inl], -np.ones(int(inl.sum()))))
    A = _normal_matrices(J, i, k)
    n = np.bincount(i, minlength=k)
    good = (n >= 3) & (np.abs(np.linalg.det(A)) > 1e-18)
    if good.any():
        cov[good] = np.linalg.inv(A[good]) * (np.maximum(rms[good], 1e-4) ** 2)[:, None, None]
    return cov


#: a slice circle is suspect when its disc holds at least this fraction of its inliers
CORE_INSIDE_FRACTION = 0.1
#: the smallest inside margin / RANSAC tolerance of a core refit (m), as MIN_RANSAC_TOL
MIN_CORE_TOL = 0.005

_Fits = tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.int64]]


def _opaque_core_refits(
    pts: FloatArray,
    ids: NDArray[np.int64],
    fit: _Fits,
    method: str,
    radius_window: tuple[float, float],
    min_points: int,
    ray_origins: FloatArray | None = None,
    ransac_lo: bool = True,
    ransac_seed: int = 0,
    window: float = 3.0,
    stub_trim: float = 0.0,
    stub_surface: bool = False,
) -> tuple[_Fits, int]:
    """Slice circles refitted to the stem inside them: a trunk is opaque.

    A circle through a stem and the clutter beside it (a spruce's branch stubs and needles,
    merged with the bark by 1 cm of noise) is larger than the stem and holds the stem's far
    side inside its disc. A real trunk's cross-section holds no returns beyond its surface
    noise. A segment whose fit (centre c, radius r, residual RMS s) has at least
    ``min_points`` and at least :data:`CORE_INSIDE_FRACTION` of its inlier count more than
    ``3 t`` inside the circle (``t = max(s, 5 mm)``: the inside margin of
    :func:`_ransac_circle` at tolerance t) -- enough returns inside for a circle of their own
    -- is fitted again (:func:`_fit_segments`, RANSAC tolerance t) on its points within
    ``r + t`` of c, radius at most r. The refit replaces the fit when it has ``min_points``
    inliers, a residual RMS no larger than s, lies within the old circle
    (``|c' - c| + r' <= r + 3 t``), and leaves fewer than half as many points inside its
    own disc (margin ``3 max(s', 5 mm)``), at most :data:`CORE_INSIDE_FRACTION` of its
    inliers. ``ray_origins``, ``ransac_lo``, ``ransac_seed``, ``window``, ``stub_trim``,
    ``stub_surface`` as in :func:`_fit_segments`.
    Returns the fits (copies; centres, radii, RMS, ok, inliers) and the number of segments
    replaced."""
    centers, radii, rms = (np.array(a, dtype=np.float64) for a in fit[:3])
    ok, nin = np.array(fit[3], dtype=bool), np.array(fit[4], dtype=np.int64)
    if pts.shape[0] == 0 or not ok.any():
        return (centers, radii, rms, ok, nin), 0
    k = radii.shape[0]
    good = ok[ids] & np.isfinite(radii[ids])
    res = np.full(pts.shape[0], np.inf)
    res[good] = np.hypot(*(pts[good] - centers[ids[good]]).T) - radii[ids[good]]
    t = np.maximum(np.nan_to_num(rms, nan=0.0), MIN_CORE_TOL)
    inside = np.bincount(ids[res < -3.0 * t[ids]], minlength=k)
    need = np.maximum(min_points, CORE_INSIDE_FRACTION * nin)
    flagged = np.flatnonzero(ok & (nin > 0) & (inside >= need))
    replaced = 0
    if flagged.size == 0:
        return (centers, radii, rms, ok, nin), 0
    order = np.argsort(ids, kind="stable")
    starts = np.searchsorted(ids[order], flagged)
    stops = np.searchsorted(ids[order], flagged, side="right")
    for s, a, b in zip(flagged, starts, stops, strict=True):
        seg = order[a:b]
        sel = seg[res[seg] <= t[s]]
        if sel.size < min_points:
            continue
        q = pts[sel]
        c2, r2, s2, ok2, n2 = _fit_segments(
            q,
            np.zeros(q.shape[0], dtype=np.int64),
            1,
            method,
            ransac_tol=float(t[s]),
            radius_window=(radius_window[0], float(radii[s])),
            ray_origins=None if ray_origins is None else ray_origins[sel],
            ransac_lo=ransac_lo,
            ransac_seed=ransac_seed,
            window=window,
            stub_trim=stub_trim,
            stub_surface=stub_surface,
        )
        if not (ok2[0] and n2[0] >= min_points and s2[0] <= rms[s] and r2[0] <= radii[s]):
            continue
        if math.hypot(*(c2[0] - centers[s])) + r2[0] > radii[s] + 3.0 * t[s]:
            continue
        d2 = np.hypot(*(pts[seg] - c2[0]).T) - r2[0]
        in2 = int((d2 < -3.0 * max(float(s2[0]), MIN_CORE_TOL)).sum())
        if in2 >= 0.5 * inside[s] or in2 > CORE_INSIDE_FRACTION * n2[0]:
            continue
        centers[s], radii[s], rms[s], nin[s] = c2[0], r2[0], s2[0], n2[0]
        replaced += 1
    return (centers, radii, rms, ok, nin), replaced


# after every kernel is defined, before the first call loads the cache: the local
# optimisation compiles in the scan fits' Kasa start and Levenberg-Marquardt core
# (stemmap._numba_cache)
_numba_cache.drop_stale_cache(_lo_kernel, __file__, _fit_geometric.__file__, _fit_lm.__file__)
