"""Vectorised (numpy) batch versions of the closed-form circle fits.

Each function fits K segments of one sorted point array at once (segment k is
``p[starts[k]:stops[k]]``) and reproduces the single-segment function of
:mod:`stemmap.scan.circle` to round-off: same centring/scaling, same failure rules. They return
``centers (K, 2)``, ``radii (K,)`` and ``reasons`` (K,) of str ("" where the fit succeeded);
failed rows are NaN. ``fit_circles_batch`` dispatches here so that the detector pays a few
dozen numpy calls per batch instead of one Python call per segment.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray

__all__ = [
    "bearing_order",
    "chord_width_batch",
    "eig_ratio_sym3",
    "fletcher_reeves_batch",
    "kasa_batch",
    "rms_batch",
    "three_point_batch",
]

IntArray = NDArray[np.int64]

AT_ORIGIN = "a point coincides with the sensor origin, so its bearing is undefined"
COLLINEAR_EIG = 1e-14


def _seg_index(starts: IntArray, counts: IntArray) -> IntArray:
    return np.repeat(np.arange(starts.shape[0]), counts)


def _seg_sum(values: FloatArray, starts: IntArray, counts: IntArray) -> FloatArray:
    """Per-segment sums of ``values`` (N,) or (N, m); empty segments give 0."""
    out = np.add.reduceat(values, starts, axis=0) if values.shape[0] else values[:0]
    return np.where((counts > 0).reshape((-1,) + (1,) * (values.ndim - 1)), out, 0.0)


def _centred_scaled(
    p: FloatArray, starts: IntArray, counts: IntArray
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray]:
    """Points centred on their segment mean and scaled to unit RMS radius."""
    seg = _seg_index(starts, counts)
    n = np.maximum(counts, 1).astype(np.float64)
    mean = _seg_sum(p, starts, counts) / n[:, None]
    q = p - mean[seg]
    scale = np.sqrt(_seg_sum(np.sum(q * q, axis=1), starts, counts) / n)
    safe = np.where(scale > 0, scale, 1.0)
    return q / safe[seg][:, None], mean, scale, seg


def _normal_equations(
    q: FloatArray, starts: IntArray, counts: IntArray
) -> tuple[FloatArray, FloatArray]:
    """A^T A (K, 3, 3) and A^T z (K, 3) for rows a = [x, y, 1], z = x^2 + y^2."""
    x, y = q[:, 0], q[:, 1]
    z = x * x + y * y
    cols = np.column_stack((x * x, x * y, x, y * y, y, x * z, y * z, z))
    s = _seg_sum(cols, starts, counts)
    k = counts.shape[0]
    M = np.empty((k, 3, 3))
    M[:, 0, 0], M[:, 0, 1], M[:, 0, 2] = s[:, 0], s[:, 1], s[:, 2]
    M[:, 1, 0], M[:, 1, 1], M[:, 1, 2] = s[:, 1], s[:, 3], s[:, 4]
    M[:, 2, 0], M[:, 2, 1], M[:, 2, 2] = s[:, 2], s[:, 4], counts
    return M, s[:, 5:8]


def eig_ratio_sym3(M: FloatArray) -> FloatArray:
    """Smallest / largest eigenvalue of symmetric positive semi-definite 3x3 matrices (K, 3, 3),
    in closed form (trigonometric solution of the characteristic cubic; Smith 1961) -- one
    vectorised pass instead of one LAPACK call per matrix. Absolute accuracy ~1e-15 of the
    largest eigenvalue, like any eigen-solver."""
    a00, a11, a22 = M[:, 0, 0], M[:, 1, 1], M[:, 2, 2]
    a01, a02, a12 = M[:, 0, 1], M[:, 0, 2], M[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    pp = np.sqrt(p2 / 6.0)
    safe = np.where(pp > 0, pp, 1.0)
    b00, b11, b22 = (a00 - q) / safe, (a11 - q) / safe, (a22 - q) / safe
    b01, b02, b12 = a01 / safe, a02 / safe, a12 / safe
    det_b = (
        b00 * (b11 * b22 - b12 * b12)
        - b01 * (b01 * b22 - b12 * b02)
        + b02 * (b01 * b12 - b11 * b02)
    )
    phi = np.arccos(np.clip(det_b / 2.0, -1.0, 1.0)) / 3.0
    lam_max = np.where(pp > 0, q + 2.0 * pp * np.cos(phi), q)
    lam_min = np.where(pp > 0, q + 2.0 * pp * np.cos(phi + 2.0 * np.pi / 3.0), q)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(lam_max > 0, lam_min / np.where(lam_max > 0, lam_max, 1.0), 0.0)


def _collinear(M: FloatArray) -> NDArray[np.bool_]:
    """Rank test shared with the single fits: smallest / largest eigenvalue of A^T A below
    ``COLLINEAR_EIG`` (a singular-value ratio of 1e-7; eigenvalues of A^T A carry ~1e-16
    relative round-off, so a tighter test could not tell collinear points from round-off)."""
    return ~(eig_ratio_sym3(M) >= COLLINEAR_EIG)


def _reasons(k: int) -> NDArray[np.object_]:
    return np.full(k, "", dtype=object)


def kasa_batch(
    p: FloatArray, starts: IntArray, counts: IntArray
) -> tuple[FloatArray, FloatArray, NDArray[np.object_]]:
    """Kasa fit of every segment (see ``fit_circle_kasa``)."""
    k = counts.shape[0]
    reasons = _reasons(k)
    q, mean, scale, _ = _centred_scaled(p, starts, counts)
    M, Az = _normal_equations(q, starts, counts)
    few = counts < 3
    coincide = ~few & (scale == 0)
    coll = ~few & ~coincide & _collinear(M)
    good = ~(few | coincide | coll)
    sol = np.full((k, 3), np.nan)
    if good.any():
        # Kasa: minimise |[x y 1] [D E F]^T + z|^2  ->  M [D E F] = -A^T z
        sol[good] = np.linalg.solve(M[good], -Az[good][:, :, None])[:, :, 0]
    cx, cy = -sol[:, 0] / 2.0, -sol[:, 1] / 2.0
    with np.errstate(invalid="ignore"):
        r2 = cx * cx + cy * cy - sol[:, 2]
    bad_r = good & ~(r2 > 0)
    good &= r2 > 0
    reasons[few] = [f"need at least 3 points, got {int(c)}" for c in counts[few]]
    reasons[coincide] = "all points coincide"
    reasons[coll] = "points are collinear"
    reasons[bad_r] = "degenerate algebraic solution (r^2 <= 0)"
    centers = np.where(good[:, None], np.column_stack((cx, cy)) * scale[:, None] + mean, np.nan)
    radii = np.where(good, np.sqrt(np.where(good, r2, 1.0)) * scale, np.nan)
    return centers, radii, reasons


def fletcher_reeves_batch(
    p: FloatArray, starts: IntArray, counts: IntArray, k_max: int, tol: float
) -> tuple[FloatArray, FloatArray, NDArray[np.object_]]:
    """Zheng (2012) §3.3 Fletcher-Reeves CG of every segment at once (see
    ``fit_circle_fletcher_reeves``); each segment stops on its own ``||d_k|| < tol``."""
    k = counts.shape[0]
    reasons = _reasons(k)
    q, mean, scale, _ = _centred_scaled(p, starts, counts)
    M0, Az0 = _normal_equations(q, starts, counts)
    # Zheng's rows are [2x, 2y, 1] with b = x^2 + y^2: A = A0 diag(2, 2, 1)
    Dg = np.array([2.0, 2.0, 1.0])
    M = M0 * Dg[None, :, None] * Dg[None, None, :]
    Atb = Az0 * Dg
    few = counts < 3
    coincide = ~few & (scale == 0)
    coll = ~few & ~coincide & _collinear(M)
    active = ~(few | coincide | coll)
    x = np.zeros((k, 3))
    g = -Atb.copy()  # g0 = M x0 - A^T b with x0 = 0
    d = -g
    converged = np.zeros(k, dtype=bool)
    for it in range(int(k_max)):
        dn = np.linalg.norm(d, axis=1)
        newly = active & (dn < tol)
        converged |= newly
        active &= ~newly
        if not active.any():
            break
        Md = np.einsum("kij,kj->ki", M, d)
        den = np.sum(d * Md, axis=1)
        stuck = active & ~(den > 0)
        if stuck.any():
            converged |= stuck & (np.linalg.norm(g, axis=1) < tol)
            active &= ~stuck
        a = np.where(active, -np.sum(g * d, axis=1) / np.where(active, den, 1.0), 0.0)
        x = x + a[:, None] * d
        g_new = np.einsum("kij,kj->ki", M, x) - Atb
        gg = np.sum(g * g, axis=1)
        beta = np.where(gg > 0, np.sum(g_new * g_new, axis=1) / np.where(gg > 0, gg, 1.0), 0.0)
        d_new = -g_new if (it + 1) % 3 == 0 else -g_new + beta[:, None] * d
        d = np.where(active[:, None], d_new, d)
        g = np.where(active[:, None], g_new, g)
    no_conv = ~(few | coincide | coll) & ~converged
    cx, cy, x3 = x[:, 0], x[:, 1], x[:, 2]
    r2 = cx * cx + cy * cy + x3
    good = converged & (r2 > 0)
    bad_r = converged & ~(r2 > 0)
    reasons[few] = [f"need at least 3 points, got {int(c)}" for c in counts[few]]
    reasons[coincide] = "all points coincide"
    reasons[coll] = "points are collinear"
    reasons[no_conv] = f"no convergence within k_max={k_max} iterations"
    reasons[bad_r] = "degenerate algebraic solution (R^2 <= 0)"
    centers = np.where(good[:, None], np.column_stack((cx, cy)) * scale[:, None] + mean, np.nan)
    radii = np.where(good, np.sqrt(np.where(good, r2, 1.0)) * scale, np.nan)
    return centers, radii, reasons


def bearing_order(
    p: FloatArray, starts: IntArray, counts: IntArray, origin: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """Order of the points by bearing from each segment's origin (K, 2), within segments.

    Returns ``order`` (N,), the bearings relative to the segment's mean direction (sorted,
    N,), the ranges (sorted, N,) and the mean direction per segment (K,).
    """
    seg = _seg_index(starts, counts)
    q = p - origin[seg]
    rho = np.hypot(q[:, 0], q[:, 1])
    safe = np.where(rho > 0, rho, 1.0)
    u = _seg_sum(q / safe[:, None], starts, counts)
    mean_dir = np.arctan2(u[:, 1], u[:, 0])
    c, s = np.cos(mean_dir)[seg], np.sin(mean_dir)[seg]
    th = np.arctan2(-s * q[:, 0] + c * q[:, 1], c * q[:, 0] + s * q[:, 1])
    # bearings quantised to 1e-12 rad, ties broken by range (as the single fits do)
    order = np.lexsort((rho, np.round(th * 1e12), seg))
    return order, th[order], rho[order], mean_dir


def _at_origin(
    p: FloatArray, starts: IntArray, counts: IntArray, origin: FloatArray
) -> NDArray[np.bool_]:
    seg = _seg_index(starts, counts)
    hit = np.all(p == origin[seg], axis=1).astype(np.float64)
    return _seg_sum(hit, starts, counts) > 0


def three_point_batch(
    p: FloatArray, starts: IntArray, counts: IntArray, origin: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.object_]]:
    """Munjer eqs. 5-8 for every segment (see ``fit_circle_three_point``)."""
    k = counts.shape[0]
    reasons = _reasons(k)
    few = counts < 3
    centers = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    reasons[few] = [f"need at least 3 points, got {int(c)}" for c in counts[few]]
    at0 = ~few & _at_origin(p, starts, counts, origin)
    reasons[at0] = AT_ORIGIN
    ok = ~few & ~at0
    if not ok.any():
        return centers, radii, reasons
    order, _, _, _ = bearing_order(p, starts, counts, origin)
    ps = p[order]
    n = np.maximum(counts, 1)
    ref = _seg_sum(ps, starts, counts) / n[:, None]
    i_a = starts[ok]
    i_c = starts[ok] + counts[ok] // 2
    i_b = starts[ok] + counts[ok] - 1
    a, c, b = ps[i_a] - ref[ok], ps[i_c] - ref[ok], ps[i_b] - ref[ok]
    M = 2.0 * np.stack((c - a, b - c), axis=1)  # (K', 2, 2)
    rhs = np.column_stack(
        (np.sum(c * c, 1) - np.sum(a * a, 1), np.sum(b * b, 1) - np.sum(c * c, 1))
    )
    scale = np.maximum(np.abs(M).reshape(-1, 4).max(axis=1), 1e-300)
    det = np.linalg.det(M / scale[:, None, None])
    sing = np.abs(det) < 1e-12
    idx = np.flatnonzero(ok)
    if sing.any():
        same = (
            np.all(np.isclose(a, c), 1) | np.all(np.isclose(b, c), 1) | np.all(np.isclose(a, b), 1)
        )
        reasons[idx[sing & same]] = "first, middle and last points coincide"
        reasons[idx[sing & ~same]] = "first, middle and last points are collinear"
    fine = ~sing
    if fine.any():
        cen = np.linalg.solve(M[fine], rhs[fine][:, :, None])[:, :, 0]
        tri = np.stack((a[fine], c[fine], b[fine]), axis=1) - cen[:, None, :]
        radii[idx[fine]] = np.mean(np.hypot(tri[..., 0], tri[..., 1]), axis=1)
        centers[idx[fine]] = cen + ref[idx[fine]]
    return centers, radii, reasons


def chord_width_batch(
    p: FloatArray, starts: IntArray, counts: IntArray, origin: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.object_]]:
    """Xue eq. 12 width as the diameter for every segment (see ``fit_circle_chord_width``)."""
    k = counts.shape[0]
    reasons = _reasons(k)
    few = counts < 2
    centers = np.full((k, 2), np.nan)
    radii = np.full(k, np.nan)
    reasons[few] = [f"need at least 2 points, got {int(c)}" for c in counts[few]]
    at0 = ~few & _at_origin(p, starts, counts, origin)
    reasons[at0] = AT_ORIGIN
    ok = ~few & ~at0
    if not ok.any():
        return centers, radii, reasons
    _, th, rho, mean_dir = bearing_order(p, starts, counts, origin)
    first = starts[ok]
    last = starts[ok] + counts[ok] - 1
    theta = th[last] - th[first]
    ra, rb = rho[first], rho[last]
    w = np.sqrt(np.maximum(ra * ra + rb * rb - 2.0 * ra * rb * np.cos(theta), 0.0))
    idx = np.flatnonzero(ok)
    zero = ~(w > 0)
    reasons[idx[zero]] = "edge returns coincide (zero chord width)"
    one_beam = ~zero & ~(theta > 1e-12)
    reasons[idx[one_beam]] = "all returns lie on one beam (zero angular width)"
    zero |= one_beam
    # front range along the bisector: linear interpolation between the returns either side
    # (np.interp per segment, done at once on a key that keeps segments apart). Returns on
    # one bearing (to bearing_order's 1e-12 rad) form a group sorted by range; the front
    # surface on that bearing is the group's nearest return, so j and j1 are the first
    # members of the group at or before the bisector and of the next group. The key uses the
    # same rounded bearings as the sort, so it is monotone whatever the segment's index.
    bis_rel = 0.5 * (th[first] + th[last])
    seg = _seg_index(starts, counts)
    key = seg * 8.0 + np.round(th * 1e12) * 1e-12  # bearings in (-pi, pi]: segments apart
    qk = idx * 8.0 + np.round(bis_rel * 1e12) * 1e-12
    j = np.clip(np.searchsorted(key, qk, side="right") - 1, first, last)
    j = np.searchsorted(key, key[j], side="left")  # nearest return of j's bearing
    j1 = np.minimum(np.searchsorted(key, key[j], side="right"), last)
    span = th[j1] - th[j]
    t = np.where(span > 0, (bis_rel - th[j]) / np.where(span > 0, span, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    front = rho[j] + t * (rho[j1] - rho[j])
    r = 0.5 * w
    bis = mean_dir[ok] + bis_rel
    cen = origin[ok] + (front + r)[:, None] * np.column_stack((np.cos(bis), np.sin(bis)))
    good = ~zero
    radii[idx[good]] = r[good]
    centers[idx[good]] = cen[good]
    return centers, radii, reasons


def rms_batch(
    p: FloatArray, starts: IntArray, counts: IntArray, centers: FloatArray, radii: FloatArray
) -> FloatArray:
    """RMS orthogonal distance of each segment's points to its circle (NaN where failed)."""
    seg = _seg_index(starts, counts)
    d = np.hypot(*(p - centers[seg]).T) - radii[seg]
    n = np.maximum(counts, 1)
    with np.errstate(invalid="ignore"):
        return np.sqrt(_seg_sum(d * d, starts, counts) / n)
