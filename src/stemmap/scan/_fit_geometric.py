"""Numba kernel of the "ours" circle fit: silhouette-constrained robust geometric fit.

One compiled routine fits every segment of a batch (points grouped by contiguous segment), so
the detector pays the Python/numpy dispatch cost once per batch, not once per segment. The
public wrappers live in :mod:`stemmap.scan.circle`; the model is documented there and in
docs/algorithms/scan-fits.md.

Why numba and not padded numpy: each segment runs a Levenberg-Marquardt loop whose number of
iterations and accepted/rejected steps depend on its data, plus a 3x3 solve per iteration.
A padded (K, Nmax) numpy version would run the worst-case iteration count for every segment and
pay ~40 array dispatches per iteration; the compiled loop fits a 10-point arc in a few
microseconds (numbers in docs/algorithms/scan-fits.md).

The detector's compiled pipeline (:mod:`stemmap.scan._detect_fast`) calls ``_fit_one``
directly; that module drops its numba cache when this file changes (see its docstring).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap.types import FloatArray

__all__ = ["STATUS_MESSAGES", "fit_ours_segments"]

#: Status codes of the kernel, mapped to full-sentence reasons by the Python wrapper.
OK = 0
TOO_FEW = 1
COINCIDENT = 2
COLLINEAR = 3
NOT_CONVERGED = 4
PARTIAL_TOO_FEW = 5

STATUS_MESSAGES = {
    OK: "",
    TOO_FEW: "need at least 3 points for a circle fit",
    COINCIDENT: "all points coincide",
    COLLINEAR: "points are collinear (no curvature and no usable silhouette)",
    NOT_CONVERGED: "the geometric fit did not reach a valid circle behind the arc",
    PARTIAL_TOO_FEW: (
        "a partial arc (one edge occluded) needs at least 4 returns: with 3 the circle through "
        "them is unconstrained and its linearised covariance is overconfident"
    ),
}

_HUBER_K = 1.5  # Huber threshold in units of sigma (95 % efficiency under Gaussian noise)
_REJECT = 4.0  # outlier rejection threshold, sigma units, after the Huber fit
_SIGMA_FLOOR = 2e-4  # metres: smallest noise scale used when sigma is estimated from residuals
_MAX_ITER = 40
_SQRT12 = math.sqrt(12.0)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)


@njit(cache=True, error_model="numpy")
def _solve3(H: FloatArray, g: FloatArray, out: FloatArray) -> bool:  # pragma: no cover - numba
    """Solve the 3x3 system H out = g by Cramer's rule; False if singular."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 0], H[1, 1], H[1, 2]
    gg, h, i = H[2, 0], H[2, 1], H[2, 2]
    det = a * (e * i - f * h) - b * (d * i - f * gg) + c * (d * h - e * gg)
    scale = abs(a * e * i) + abs(b * f * gg) + abs(c * d * h) + 1e-300
    if not abs(det) > 1e-14 * scale:
        return False
    inv = 1.0 / det
    out[0] = inv * (g[0] * (e * i - f * h) - b * (g[1] * i - f * g[2]) + c * (g[1] * h - e * g[2]))
    out[1] = inv * (
        a * (g[1] * i - f * g[2]) - g[0] * (d * i - f * gg) + c * (d * g[2] - g[1] * gg)
    )
    out[2] = inv * (
        a * (e * g[2] - g[1] * h) - b * (d * g[2] - g[1] * gg) + g[0] * (d * h - e * gg)
    )
    return True


@njit(cache=True, error_model="numpy")
def _inv3(H: FloatArray, out: FloatArray) -> bool:  # pragma: no cover - numba
    """Inverse of a 3x3 matrix by cofactors; False if singular."""
    a, b, c = H[0, 0], H[0, 1], H[0, 2]
    d, e, f = H[1, 0], H[1, 1], H[1, 2]
    g, h, i = H[2, 0], H[2, 1], H[2, 2]
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    scale = abs(a * e * i) + abs(b * f * g) + abs(c * d * h) + 1e-300
    if not abs(det) > 1e-14 * scale:
        return False
    inv = 1.0 / det
    out[0, 0] = (e * i - f * h) * inv
    out[0, 1] = (c * h - b * i) * inv
    out[0, 2] = (b * f - c * e) * inv
    out[1, 0] = (f * g - d * i) * inv
    out[1, 1] = (a * i - c * g) * inv
    out[1, 2] = (c * d - a * f) * inv
    out[2, 0] = (d * h - e * g) * inv
    out[2, 1] = (b * g - a * h) * inv
    out[2, 2] = (a * e - b * d) * inv
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _accumulate(
    acc: tuple[float, float, float, float, float, float, float, float, float],
    w: float,
    j0: float,
    j1: float,
    j2: float,
    e: float,
) -> tuple[float, float, float, float, float, float, float, float, float]:  # pragma: no cover
    """Add one weighted residual e with Jacobian row (j0, j1, j2) to the running sums
    ``acc`` = (H00, H01, H02, H11, H12, H22, g0, g1, g2) of the upper triangle of H and of g.

    The sums live in registers (a tuple) rather than in the H / g arrays: stores to an array
    that may alias the inputs forced a load and store of all nine per return. The additions
    happen in the same order, so the results are the same to the bit."""
    return (
        acc[0] + w * j0 * j0,
        acc[1] + w * j0 * j1,
        acc[2] + w * j0 * j2,
        acc[3] + w * j1 * j1,
        acc[4] + w * j1 * j2,
        acc[5] + w * j2 * j2,
        acc[6] + w * j0 * e,
        acc[7] + w * j1 * e,
        acc[8] + w * j2 * e,
    )


@njit(cache=True, error_model="numpy", inline="always")
def _huber(e: float, robust: bool) -> tuple[float, float]:  # pragma: no cover - numba
    """(cost, IRLS weight) of a normalised residual under the Huber loss (or plain LS)."""
    ae = abs(e)
    if robust and ae > _HUBER_K:
        return _HUBER_K * ae - 0.5 * _HUBER_K * _HUBER_K, _HUBER_K / ae
    return 0.5 * e * e, 1.0


@njit(cache=True, error_model="numpy", inline="always")
def _footprint_range(
    b: float, s0: float, r: float, foot: float, out: FloatArray
) -> bool:  # pragma: no cover - numba
    """Mean range over the part of a beam footprint that hits the circle, and its partials.

    The beam's centre ray has unit direction u; ``b = u . c`` and ``s0 = u x c`` (signed
    distance of the centre from the ray). A ray rotated by delta (|delta| <= foot / 2) sees the
    centre at ``b + s0 delta`` along it and ``s0 - b delta`` across it (first order in delta,
    error < 0.03 mm for foot = 0.25 deg), so its first hit is at
    ``b + s0 delta - sqrt(r^2 - (s0 - b delta)^2)``. Averaged over the hit part
    [da, db] of the footprint (|s0 - b delta| <= r) the square root integrates in closed form.

    A beam returns only if at least half its footprint hits (its centre ray hits). When the
    circle leaves less than that, the window is kept at the half footprint on the circle's
    side (rays past the tangent count at their closest approach, the square root being 0
    there): the prediction and its derivatives stay bounded and continuous where the model
    says the beam should not have returned; the silhouette term pulls the circle back.
    Writes (pred, d pred/d b, d pred/d s0, d pred/d r) to ``out``; False if b <= 0."""
    if not b > 0.0:
        return False
    half = 0.5 * foot
    lo_c = (s0 - r) / b
    hi_c = (s0 + r) / b
    da = max(-half, min(lo_c, 0.0))
    db = min(half, max(hi_c, 0.0))
    wd = db - da
    if not wd > 1e-12 * foot:
        return False
    sa = min(max(s0 - b * da, -r), r)
    sb = min(max(s0 - b * db, -r), r)
    fpa = math.sqrt(max(r * r - sa * sa, 0.0))
    fpb = math.sqrt(max(r * r - sb * sb, 0.0))
    # asin(+-1) = +-pi/2 where a limit is the circle's edge (the common case at a trunk edge)
    ta = math.copysign(0.5 * math.pi, sa) if abs(sa) >= r else math.asin(sa / r)
    tb = math.copysign(0.5 * math.pi, sb) if abs(sb) >= r else math.asin(sb / r)
    # S = F(sa) - F(sb), F(s) = int_0^s sqrt(r^2 - t^2) dt = (s sqrt(r^2 - s^2) + r^2 asin(s/r)) / 2
    S = 0.5 * (sa * fpa - sb * fpb + r * r * (ta - tb))
    bw = b * wd
    pred = b + 0.5 * s0 * (da + db) - S / bw
    # partials of S: dF/ds = sqrt(r^2 - s^2), dF/dr = r asin(s / r)
    ds_s0 = fpa - fpb
    ds_b = -da * fpa + db * fpb
    ds_r = r * (ta - tb)
    p_b = 1.0 - ds_b / bw + S / (b * bw)
    p_s = 0.5 * (da + db) - ds_s0 / bw
    p_r = -ds_r / bw
    if -half < lo_c < 0.0:  # the lower limit is the circle's edge: da = (s0 - r) / b
        p_da = 0.5 * s0 + b * fpa / bw - S / (bw * wd)
        p_b += p_da * (-lo_c / b)
        p_s += p_da / b
        p_r += -p_da / b
    if 0.0 < hi_c < half:  # the upper limit is the circle's edge: db = (s0 + r) / b
        p_db = 0.5 * s0 - b * fpb / bw + S / (bw * wd)
        p_b += p_db * (-hi_c / b)
        p_s += p_db / b
        p_r += p_db / b
    out[0] = pred
    out[1] = p_b
    out[2] = p_s
    out[3] = p_r
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _range_residual(
    i: int,
    uxs: FloatArray,
    uys: FloatArray,
    rho: FloatArray,
    cx: float,
    cy: float,
    r: float,
    foot: float,
    tmp: FloatArray,
) -> tuple[float, float, float, float, float, float, float, float]:  # pragma: no cover
    """Range residual of return i (metres) along its beam and its Jacobian over (cx, cy, r),
    plus a second "miss" residual (distance by which the beam passes the circle) and its
    Jacobian: (e, j0, j1, j2, m, k0, k1, k2). ``foot > 0``: footprint-averaged prediction.
    ``uxs``, ``uys``: unit beam directions of the returns."""
    ux = uxs[i]
    uy = uys[i]
    b = ux * cx + uy * cy
    s0 = ux * cy - uy * cx
    # d b / d(cx, cy) = u; d s0 / d(cx, cy) = (-uy, ux)
    if foot > 0.0:
        if _footprint_range(b, s0, r, foot, tmp):
            e = rho[i] - tmp[0]
            return (
                e,
                -(tmp[1] * ux - tmp[2] * uy),
                -(tmp[1] * uy + tmp[2] * ux),
                -tmp[3],
                0.0,
                0.0,
                0.0,
                0.0,
            )
    else:
        disc = r * r - s0 * s0
        if disc > 0.0 and b > 0.0:
            q = math.sqrt(disc)
            qj = max(q, 1e-2 * r)
            e = rho[i] - (b - q)
            p_s = s0 / qj
            return e, -(ux - p_s * uy), -(uy + p_s * ux), r / qj, 0.0, 0.0, 0.0, 0.0
    # the beam misses the circle: range to the closest approach + the miss distance
    sg = 1.0 if s0 >= 0.0 else -1.0
    m = max(abs(s0) - r, 0.0)
    return rho[i] - b, -ux, -uy, 0.0, m, -sg * uy, sg * ux, -1.0


@njit(cache=True, error_model="numpy")
def _cost_and_normal(
    lx: FloatArray,
    ly: FloatArray,
    rho: FloatArray,
    ux: FloatArray,
    uy: FloatArray,
    keep: FloatArray,
    cx: float,
    cy: float,
    r: float,
    mdl: FloatArray,
    robust: bool,
    H: FloatArray,
    g: FloatArray,
    tmp: FloatArray,
    cap: float,
) -> float:  # pragma: no cover - numba
    """Robust cost at (cx, cy, r) and the Gauss-Newton normal equations H, g (IRLS weights).

    Returns early, with H and g unset, as soon as the partial cost exceeds ``cap`` (the cost
    of the point a trial step would replace): every term is >= 0 and a rounded sum of
    non-negative terms never decreases, so the full cost would exceed ``cap`` too and the
    step is rejected either way (``cap = inf``: always the full evaluation).

    ``mdl`` = (1/sigma, t_lo, t_hi, 1/s_lo, 1/s_hi, footprint, i_lo, i_hi, range_model,
    use_sil): silhouette targets and inverse stds (0 = side unused), beam footprint (rad),
    indices of the lowest/highest-bearing returns (footprint-averaged in the range model) and
    whether residuals are ranges along the beams (1) or orthogonal distances (0). ``tmp``
    (>= 4) is scratch space."""
    acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    cost = 0.0
    n = lx.shape[0]
    inv_sigma = mdl[0]
    range_model = mdl[8] > 0.0
    foot = mdl[5]
    i_lo = int(mdl[6])
    i_hi = int(mdl[7])
    for i in range(n):
        if keep[i] == 0.0:
            continue
        if range_model:
            f_i = 0.0
            if (i == i_lo and mdl[3] > 0.0) or (i == i_hi and mdl[4] > 0.0):
                f_i = foot
            e, j0, j1, j2, m, k0, k1, k2 = _range_residual(i, ux, uy, rho, cx, cy, r, f_i, tmp)
            e *= inv_sigma
            c_e, w = _huber(e, robust)
            cost += c_e
            acc = _accumulate(acc, w, j0 * inv_sigma, j1 * inv_sigma, j2 * inv_sigma, e)
            if m > 0.0:
                m *= inv_sigma
                c_m, w = _huber(m, robust)
                cost += c_m
                acc = _accumulate(acc, w, k0 * inv_sigma, k1 * inv_sigma, k2 * inv_sigma, m)
            if cost > cap:
                return cost
            continue
        dx = lx[i] - cx
        dy = ly[i] - cy
        dist = math.sqrt(dx * dx + dy * dy)
        e = (dist - r) * inv_sigma
        if dist > 0.0:
            j0 = -dx / dist * inv_sigma
            j1 = -dy / dist * inv_sigma
        else:
            j0 = 0.0
            j1 = 0.0
        c_e, w = _huber(e, robust)
        cost += c_e
        acc = _accumulate(acc, w, j0, j1, -inv_sigma, e)
        if cost > cap:
            return cost
    if mdl[9] > 0.0:
        d2 = cx * cx + cy * cy
        dd = math.sqrt(d2)
        q = math.sqrt(max(d2 - r * r, 1e-300))
        alpha = math.asin(min(r / dd, 1.0))
        beta = math.atan2(cy, cx)
        # d beta / d(cx, cy); d alpha / d(cx, cy, r)
        b0 = -cy / d2
        b1 = cx / d2
        a0 = -r * cx / (d2 * q)
        a1 = -r * cy / (d2 * q)
        a2 = 1.0 / q
        for side in range(2):
            sgn = -1.0 if side == 0 else 1.0
            target = mdl[1] if side == 0 else mdl[2]
            inv_sang = mdl[3] if side == 0 else mdl[4]
            if inv_sang == 0.0:
                continue
            e = (beta + sgn * alpha - target) * inv_sang
            cost += 0.5 * e * e
            acc = _accumulate(
                acc,
                1.0,
                (b0 + sgn * a0) * inv_sang,
                (b1 + sgn * a1) * inv_sang,
                (sgn * a2) * inv_sang,
                e,
            )
    H[0, 0] = acc[0]
    H[0, 1] = acc[1]
    H[0, 2] = acc[2]
    H[1, 0] = acc[1]
    H[1, 1] = acc[3]
    H[1, 2] = acc[4]
    H[2, 0] = acc[2]
    H[2, 1] = acc[4]
    H[2, 2] = acc[5]
    g[0] = acc[6]
    g[1] = acc[7]
    g[2] = acc[8]
    return cost


@njit(cache=True, error_model="numpy")
def _valid(
    cx: float, cy: float, r: float, rho_min: float, use_sil: bool
) -> bool:  # pragma: no cover - numba
    """The centre lies behind the arc: sensor outside the circle, centre beyond the nearest
    return, positive radius."""
    if not (r > 0.0) or not math.isfinite(cx) or not math.isfinite(cy) or not math.isfinite(r):
        return False
    dd = math.sqrt(cx * cx + cy * cy)
    if not use_sil:
        return True
    return dd > r * (1.0 + 1e-12) and dd > rho_min


@njit(cache=True, error_model="numpy")
def _lm(
    lx: FloatArray,
    ly: FloatArray,
    rho: FloatArray,
    ux: FloatArray,
    uy: FloatArray,
    keep: FloatArray,
    p: FloatArray,
    mdl: FloatArray,
    rho_min: float,
    robust: bool,
    ws3: FloatArray,
    wv: FloatArray,
    tol: float,
) -> tuple[float, int]:  # pragma: no cover - numba
    """Levenberg-Marquardt on (cx, cy, r) in place; returns (cost, iterations).

    ``tol`` scales the stopping thresholds (step 1e-6 relative, decrease 1e-5 of the cost);
    ``tol < 1`` also allows 10x the iterations (a tight reference for tests, not for use).

    ``mdl``: see :func:`_cost_and_normal`. ``ws3`` (>= 3, 3, 3) and ``wv`` (>= 6, 3) are
    scratch space (no allocation per call). On return ``ws3[0]`` and ``wv[0]`` hold the
    normal equations H, g at the returned ``p`` (every exit leaves H paired with p)."""
    H = ws3[0]
    Hn = ws3[1]
    Ht = ws3[2]
    g = wv[0]
    gt = wv[1]
    step = wv[2]
    mg = wv[3]
    tmp = wv[6:8].reshape(-1)
    use_sil = mdl[9] > 0.0
    cost = _cost_and_normal(
        lx, ly, rho, ux, uy, keep, p[0], p[1], p[2], mdl, robust, H, g, tmp, math.inf
    )
    lam = 1e-3
    it = 0
    xtol = 1e-6 * tol
    ftol = 1e-5 * tol
    max_iter = _MAX_ITER if tol >= 1.0 else 10 * _MAX_ITER
    for it in range(max_iter):
        improved = False
        for _ in range(12):
            for a in range(3):
                for b in range(3):
                    Hn[a, b] = H[a, b]
                Hn[a, a] = H[a, a] * (1.0 + lam) + 1e-12
            for a in range(3):
                mg[a] = -g[a]
            if not _solve3(Hn, mg, step):
                lam *= 10.0
                continue
            # decrease predicted by the local quadratic model (gain ratio and stopping test)
            pred_red = 0.0
            for a in range(3):
                hs = 0.0
                for b in range(3):
                    hs += H[a, b] * step[b]
                pred_red -= g[a] * step[a] + 0.5 * step[a] * hs
            if pred_red <= 1e-10 * (1.0 + cost):
                return cost, it + 1
            cx = p[0] + step[0]
            cy = p[1] + step[1]
            r = p[2] + step[2]
            if not _valid(cx, cy, r, rho_min, use_sil):
                lam *= 10.0
                continue
            new_cost = _cost_and_normal(
                lx, ly, rho, ux, uy, keep, cx, cy, r, mdl, robust, Ht, gt, tmp, cost
            )
            if new_cost <= cost:
                dp = abs(step[0]) + abs(step[1]) + abs(step[2])
                scale = abs(p[0]) + abs(p[1]) + abs(p[2])
                p[0], p[1], p[2] = cx, cy, r
                rel = cost - new_cost
                cost = new_cost
                for a in range(3):
                    g[a] = gt[a]
                    for b in range(3):
                        H[a, b] = Ht[a, b]
                # trust-region style damping: shrink lambda only where the quadratic model
                # predicted the decrease well (edge returns make the cost far from quadratic)
                gain = rel / pred_red
                if gain > 0.75:
                    lam = max(lam * 0.3, 1e-9)
                elif gain < 0.25:
                    lam *= 2.0
                improved = True
                if dp <= xtol * (1.0 + scale) or rel <= ftol * (1.0 + cost):
                    return cost, it + 1
                break
            lam *= 10.0
        if not improved:
            return cost, it + 1
    return cost, it + 1


@njit(cache=True, error_model="numpy")
def _abs_residual(
    i: int,
    lx: FloatArray,
    ly: FloatArray,
    rho: FloatArray,
    ux: FloatArray,
    uy: FloatArray,
    p: FloatArray,
    mdl: FloatArray,
    tmp: FloatArray,
) -> float:  # pragma: no cover - numba
    """|residual| of return i in metres under the model ``mdl`` (range or orthogonal)."""
    if mdl[8] > 0.0:
        f_i = 0.0
        if (i == int(mdl[6]) and mdl[3] > 0.0) or (i == int(mdl[7]) and mdl[4] > 0.0):
            f_i = mdl[5]
        e, _, _, _, m, _, _, _ = _range_residual(i, ux, uy, rho, p[0], p[1], p[2], f_i, tmp)
        return math.sqrt(e * e + m * m)
    return abs(math.sqrt((lx[i] - p[0]) ** 2 + (ly[i] - p[1]) ** 2) - p[2])


@njit(cache=True, error_model="numpy")
def _truncated_moments(
    m: float, v: float, lo: float, hi: float
) -> tuple[float, float, bool]:  # pragma: no cover - numba
    """Mean and variance of N(m, v) restricted to [lo, hi]; False where the interval holds
    (numerically) no mass or the variance would not be positive."""
    s = math.sqrt(v)
    a = (lo - m) / s
    b = (hi - m) / s
    z = 0.5 * (math.erfc(-b * _INV_SQRT2) - math.erfc(-a * _INV_SQRT2))
    if not z > 1e-9:
        return m, v, False
    pa = _INV_SQRT2PI * math.exp(-0.5 * a * a)
    pb = _INV_SQRT2PI * math.exp(-0.5 * b * b)
    dm = (pa - pb) / z
    var = v * (1.0 + (a * pa - b * pb) / z - dm * dm)
    if not var > 0.0:
        return m, v, False
    return m + s * dm, var, True


@njit(cache=True, error_model="numpy")
def _box_tangents(
    p: FloatArray, C: FloatArray, mdl: FloatArray, work: FloatArray
) -> bool:  # pragma: no cover - numba
    """Replace the Gaussian tangent terms by the uniform intervals they stand for (EP).

    The fit's silhouette term is the Gaussian surrogate (same mean and variance) of a tangent
    bearing known only to lie in an interval (beam quantisation, scan-fits.md "Silhouette
    term"). Given the fit's Gaussian posterior (``p``, ``C`` = inverse Gauss-Newton Hessian),
    each side in turn (one sweep, assumed-density filtering; a second sweep moved the
    benchmark's diameters by < 1e-5 m): the cavity (posterior without that side's Gaussian
    term) is restricted to the uniform interval of width sqrt(12) x std around the same
    target, and the posterior takes the tilted moments (truncated normal) along the site's
    direction ``a = d t / d(cx, cy, r)`` (linearised at the current mean), keeping its
    conditional given t. Updates ``p`` and ``C`` in place (posterior mean and covariance) and
    returns True, or returns False (``p``, ``C`` then partly updated: the caller keeps copies)
    where a side cannot be matched (no mass in the interval, a non-positive cavity variance).
    ``mdl``: see :func:`_cost_and_normal`; ``work`` (>= 2, 3) scratch."""
    a = work[0]
    ca = work[1]
    for side in range(2):
        w_inv = mdl[3] if side == 0 else mdl[4]
        if not w_inv > 0.0:
            return False
        tau = mdl[1] if side == 0 else mdl[2]
        vs = 1.0 / (w_inv * w_inv)  # the Gaussian site: mean tau, variance vs
        half = 0.5 * _SQRT12 / w_inv
        sgn = -1.0 if side == 0 else 1.0
        cx = p[0]
        cy = p[1]
        r = p[2]
        d2 = cx * cx + cy * cy
        if not d2 > r * r:
            return False
        q = math.sqrt(d2 - r * r)
        a[0] = -cy / d2 - sgn * r * cx / (d2 * q)
        a[1] = cx / d2 - sgn * r * cy / (d2 * q)
        a[2] = sgn / q
        mt = math.atan2(cy, cx) + sgn * math.asin(r / math.sqrt(d2))
        vt = 0.0
        for i in range(3):
            acc = 0.0
            for j in range(3):
                acc += C[i, j] * a[j]
            ca[i] = acc
            vt += a[i] * acc
        if not vt > 0.0:
            return False
        pc = 1.0 / vt - 1.0 / vs
        if not pc > 0.0:
            return False
        vc = 1.0 / pc
        mc = vc * (mt / vt - tau / vs)
        mn, vn, good = _truncated_moments(mc, vc, tau - half, tau + half)
        if not good:
            return False
        g = (mn - mt) / vt
        shrink = (vt - vn) / (vt * vt)
        for i in range(3):
            p[i] += ca[i] * g
            for j in range(3):
                C[i, j] -= ca[i] * ca[j] * shrink
    return True


@njit(cache=True, error_model="numpy")
def _fit_one(
    px: FloatArray,
    py: FloatArray,
    ox: float,
    oy: float,
    sigma: float,
    dtheta: float,
    use_lo: bool,
    use_hi: bool,
    sil: FloatArray,
    foot: float,
    range_model: bool,
    out: FloatArray,
    buf: FloatArray,
    ws3: FloatArray,
    wv: FloatArray,
    mdl: FloatArray,
    tol: float,
    box: bool,
) -> int:  # pragma: no cover - numba
    """Fit one segment; write cx, cy, r, cov (9), rms, sigma_used into ``out``; return status.

    ``buf`` (8, >= N), ``ws3`` (6, 3, 3), ``wv`` (8, 3) and ``mdl`` (10,) are scratch space
    shared by all segments of a batch, so a fit allocates nothing on the common path.
    ``tol``: scale of the LM stopping thresholds (:func:`_lm`; 1.0 = the defaults). ``box``:
    refine arcs with both tangents by the uniform tangent intervals (:func:`_box_tangents`)."""
    n = px.shape[0]
    if n < 3:
        return TOO_FEW
    lx = buf[0, :n]
    ly = buf[1, :n]
    rho = buf[2, :n]
    th = buf[3, :n]
    keep = buf[4, :n]
    dabs = buf[5, :n]
    ux = buf[6, :n]
    uy = buf[7, :n]
    # ---- local frame: origin at the sensor, x axis along the mean bearing of the points ----
    sx = 0.0
    sy = 0.0
    spread = 0.0
    rho_min = math.inf
    for i in range(n):
        qx = px[i] - ox
        qy = py[i] - oy
        rr = math.sqrt(qx * qx + qy * qy)
        rho[i] = rr
        rho_min = min(rho_min, rr)
        spread += abs(px[i] - px[0]) + abs(py[i] - py[0])
        if rr > 0.0:
            sx += qx / rr
            sy += qy / rr
    if spread == 0.0:
        return COINCIDENT
    phi0 = math.atan2(sy, sx)
    c0 = math.cos(phi0)
    s0 = math.sin(phi0)
    th_min = math.inf
    th_max = -math.inf
    for i in range(n):
        qx = px[i] - ox
        qy = py[i] - oy
        lx[i] = c0 * qx + s0 * qy
        ly[i] = -s0 * qx + c0 * qy
        t = math.atan2(ly[i], lx[i])
        th[i] = t
        ux[i] = lx[i] / rho[i] if rho[i] > 0.0 else 0.0
        uy[i] = ly[i] / rho[i] if rho[i] > 0.0 else 0.0
        th_min = min(th_min, t)
        th_max = max(th_max, t)
        keep[i] = 1.0
    one_sided = th_min > -0.5 * math.pi + 1e-3 and th_max < 0.5 * math.pi - 1e-3
    if dtheta <= 0.0:
        diffs = np.diff(np.sort(th))
        dtheta = np.median(diffs)
        if not dtheta > 0.0:
            dtheta = (th_max - th_min) / (n - 1)
    # Points around the sensor (or on it) have no visible side: no silhouette terms then.
    use_sil = (use_lo or use_hi) and one_sided and rho_min > 0.0 and dtheta > 0.0
    if use_sil and use_lo != use_hi and n < 4:
        return PARTIAL_TOO_FEW
    # Silhouette targets: the lower tangent bearing lies uniformly in (th_min - dtheta, th_min],
    # the upper in [th_max, th_max + dtheta); an unused side gets its target from the fit itself
    # (weight zero is emulated by an infinite target std below).
    off_lo = sil[0] * dtheta if math.isfinite(sil[0]) else 0.5 * dtheta
    off_hi = sil[2] * dtheta if math.isfinite(sil[2]) else 0.5 * dtheta
    t_lo = th_min - off_lo
    t_hi = th_max + off_hi
    # ---- initial guess from the silhouette and the nearest return (always behind the arc) ----
    half = 0.5 * (t_hi - t_lo)
    sa = min(math.sin(min(half, 0.5 * math.pi - 1e-3)), 0.95)
    near = rho_min
    r0 = near * sa / (1.0 - sa)
    d0 = near + r0
    b0 = 0.5 * (t_lo + t_hi)
    p = wv[4]
    p[0] = d0 * math.cos(b0)
    p[1] = d0 * math.sin(b0)
    p[2] = r0
    if not use_sil:
        # No silhouette: start from the algebraic (Kasa) solution in the local frame.
        mx = np.mean(lx)
        my = np.mean(ly)
        ux = lx - mx
        uy = ly - my
        sc = math.sqrt(np.mean(ux * ux + uy * uy))
        ux = ux / sc
        uy = uy / sc
        A = np.zeros((3, 3))
        bb = np.zeros(3)
        for i in range(n):
            z = -(ux[i] * ux[i] + uy[i] * uy[i])
            row = (ux[i], uy[i], 1.0)
            for a in range(3):
                bb[a] += row[a] * z
                for b in range(3):
                    A[a, b] += row[a] * row[b]
        sol = np.zeros(3)
        if not _solve3(A, bb, sol):
            return COLLINEAR
        kcx = -0.5 * sol[0]
        kcy = -0.5 * sol[1]
        r2 = kcx * kcx + kcy * kcy - sol[2]
        if not r2 > 0.0:
            return COLLINEAR
        p[0] = kcx * sc + mx
        p[1] = kcy * sc + my
        p[2] = math.sqrt(r2) * sc
    # ---- noise scale: given, or estimated from a first (equal-weight) pass ----
    extent = max(th_max - th_min, dtheta) * near
    sang = dtheta / _SQRT12
    s_lo = sil[1] * dtheta if math.isfinite(sil[1]) else sang
    s_hi = sil[3] * dtheta if math.isfinite(sil[3]) else sang
    w_lo = 1.0 / s_lo if (use_sil and use_lo) else 0.0
    w_hi = 1.0 / s_hi if (use_sil and use_hi) else 0.0
    i_lo = 0
    i_hi = 0
    for i in range(n):
        if th[i] < th[i_lo]:
            i_lo = i
        if th[i] > th[i_hi]:
            i_hi = i
    # Range residuals need a view from outside the circle: only with a silhouette (one-sided
    # points, sensor kept outside by _valid); otherwise orthogonal distances, as before.
    use_range = range_model and use_sil
    mdl[1] = t_lo
    mdl[2] = t_hi
    mdl[3] = w_lo
    mdl[4] = w_hi
    mdl[5] = foot if use_range else 0.0
    mdl[6] = i_lo
    mdl[7] = i_hi
    mdl[8] = 1.0 if use_range else 0.0
    mdl[9] = 1.0 if use_sil else 0.0
    tmp = wv[6:8].reshape(-1)
    if sigma > 0.0:
        sig = sigma
    else:
        # first pass: points weighted like the silhouette (sigma ~ range * angular std)
        sig = max(near * sang, _SIGMA_FLOOR)
        mdl[0] = 1.0 / sig
        _lm(lx, ly, rho, ux, uy, keep, p, mdl, rho_min, True, ws3, wv, tol)
        ss = 0.0
        for i in range(n):
            d = _abs_residual(i, lx, ly, rho, ux, uy, p, mdl, tmp)
            ss += d * d
        dof = n - 3 if n > 3 else 1
        sig = max(math.sqrt(ss / dof), _SIGMA_FLOOR)
    mdl[0] = 1.0 / sig
    _lm(lx, ly, rho, ux, uy, keep, p, mdl, rho_min, True, ws3, wv, tol)
    # ---- outlier rejection (mixed pixels): drop up to N // 4 returns beyond 4 sigma ----
    if n >= 6:
        for i in range(n):
            dabs[i] = _abs_residual(i, lx, ly, rho, ux, uy, p, mdl, tmp)
        scale = sig
        if sigma <= 0.0:
            scale = max(1.4826 * np.median(dabs) * math.sqrt(n / (n - 3.0)), _SIGMA_FLOOR)
        n_rej = 0
        if np.max(dabs) > _REJECT * scale:
            order = np.argsort(-dabs)
            for j in range(n // 4):
                i = order[j]
                if dabs[i] > _REJECT * scale:
                    keep[i] = 0.0
                    n_rej += 1
        if n_rej > 0:
            if sigma <= 0.0:
                ss = 0.0
                for i in range(n):
                    ss += keep[i] * dabs[i] * dabs[i]
                sig = max(math.sqrt(ss / max(n - n_rej - 3, 1)), _SIGMA_FLOOR)
                mdl[0] = 1.0 / sig
            _lm(lx, ly, rho, ux, uy, keep, p, mdl, rho_min, True, ws3, wv, tol)
    if not _valid(p[0], p[1], p[2], rho_min, use_sil):
        return NOT_CONVERGED
    if not use_sil and p[2] > 1e3 * max(extent, 1e-9):
        return COLLINEAR
    # ---- covariance from the final (robustly weighted) Gauss-Newton Hessian ----
    # the last _lm left the normal equations at the returned p in ws3[0] (same p, mdl, keep,
    # robust weights as a fresh _cost_and_normal: the identical numbers, one pass saved)
    H = ws3[0]
    C = ws3[4]
    if not _inv3(H, C):
        C[:, :] = np.nan
    elif box and use_sil and use_lo and use_hi:
        # both tangents observed: the posterior is compact and the linearised moment match
        # holds; with one tangent it is curved along the "bigger circle further away" valley
        # (measured on separate seeds: EP made partial arcs slightly worse), so no EP there
        pe = wv[5]
        pe[0], pe[1], pe[2] = p[0], p[1], p[2]
        Ce = ws3[3]
        Ce[:, :] = C
        if _box_tangents(pe, Ce, mdl, wv[6:8]) and _valid(pe[0], pe[1], pe[2], rho_min, use_sil):
            p[0], p[1], p[2] = pe[0], pe[1], pe[2]
            C[:, :] = Ce
    ss = 0.0
    n_in = 0.0
    for i in range(n):
        d = math.sqrt((lx[i] - p[0]) ** 2 + (ly[i] - p[1]) ** 2) - p[2]
        ss += keep[i] * d * d
        n_in += keep[i]
    # rotate back to the input frame
    gx = ox + c0 * p[0] - s0 * p[1]
    gy = oy + s0 * p[0] + c0 * p[1]
    # Cg = R C R^T with R the rotation back to the input frame (written out: a 3x3 matmul
    # through BLAS costs more than the whole fit of a short arc)
    R = ws3[5]
    R[:, :] = 0.0
    R[0, 0], R[0, 1], R[1, 0], R[1, 1], R[2, 2] = c0, -s0, s0, c0, 1.0
    out[0] = gx
    out[1] = gy
    out[2] = p[2]
    for a in range(3):
        for b in range(3):
            acc = 0.0
            for i in range(3):
                for j in range(3):
                    acc += R[a, i] * C[i, j] * R[b, j]
            out[3 + 3 * a + b] = acc
    out[12] = math.sqrt(ss / n_in)
    out[13] = sig
    return OK


@njit(cache=True, error_model="numpy")
def _fit_segments(
    px: FloatArray,
    py: FloatArray,
    starts: np.ndarray,
    stops: np.ndarray,
    ox: FloatArray,
    oy: FloatArray,
    sigma: FloatArray,
    dtheta: FloatArray,
    use_lo: np.ndarray,
    use_hi: np.ndarray,
    sil: FloatArray,
    foot: float,
    range_model: bool,
    out: FloatArray,
    status: np.ndarray,
    tol: float,
    box: bool,
) -> None:  # pragma: no cover - numba
    nmax = 0
    for k in range(starts.shape[0]):
        nmax = max(nmax, stops[k] - starts[k])
    buf = np.empty((8, nmax))
    ws3 = np.empty((6, 3, 3))
    wv = np.empty((8, 3))
    mdl = np.empty(10)
    for k in range(starts.shape[0]):
        a = starts[k]
        b = stops[k]
        status[k] = _fit_one(
            px[a:b],
            py[a:b],
            ox[k],
            oy[k],
            sigma[k],
            dtheta[k],
            use_lo[k],
            use_hi[k],
            sil[k],
            foot,
            range_model,
            out[k],
            buf,
            ws3,
            wv,
            mdl,
            tol,
            box,
        )


def fit_ours_segments(
    px: FloatArray,
    py: FloatArray,
    starts: np.ndarray,
    stops: np.ndarray,
    ox: FloatArray,
    oy: FloatArray,
    sigma: FloatArray,
    dtheta: FloatArray,
    use_lo: np.ndarray,
    use_hi: np.ndarray,
    sil: FloatArray | None = None,
    footprint: float = 0.0,
    range_model: bool = True,
    tolerance: float = 1.0,
    box_tangents: bool = True,
) -> tuple[FloatArray, np.ndarray]:
    """Run the kernel on K segments ``px[starts[k]:stops[k]]``.

    All per-segment arrays have shape (K,); ``sigma <= 0`` means "estimate from residuals",
    ``dtheta <= 0`` means "estimate the beam spacing from the bearings". ``tolerance`` scales
    the LM stopping thresholds (1.0: the defaults the detector uses; tests pass e.g. 1e-8 to
    get a tightly converged reference of the same cost). ``box_tangents``: where both tangents
    are observed, refine the fit by the uniform tangent intervals the Gaussian silhouette terms
    stand for (:func:`_box_tangents`; the detector's default); False = the plain MAP of the
    Gaussian surrogate.

    Returns
    -------
    out : ndarray of shape (K, 14)
        cx, cy, r, cov (row-major 3x3 over cx, cy, r), rms of the inlier returns, sigma used.
        NaN where failed.
    status : ndarray of shape (K,), int64
        Kernel status code (``STATUS_MESSAGES``).
    """
    k = starts.shape[0]
    if sil is None:
        sil = np.full((k, 4), np.nan)
    out = np.full((k, 14), np.nan)
    status = np.zeros(k, dtype=np.int64)
    _fit_segments(
        np.ascontiguousarray(px, dtype=np.float64),
        np.ascontiguousarray(py, dtype=np.float64),
        np.ascontiguousarray(starts, dtype=np.int64),
        np.ascontiguousarray(stops, dtype=np.int64),
        np.ascontiguousarray(ox, dtype=np.float64),
        np.ascontiguousarray(oy, dtype=np.float64),
        np.ascontiguousarray(sigma, dtype=np.float64),
        np.ascontiguousarray(dtheta, dtype=np.float64),
        np.ascontiguousarray(use_lo, dtype=np.bool_),
        np.ascontiguousarray(use_hi, dtype=np.bool_),
        np.ascontiguousarray(sil, dtype=np.float64).reshape(k, 4),
        float(footprint),
        bool(range_model),
        out,
        status,
        float(tolerance),
        bool(box_tangents),
    )
    out[status != OK] = np.nan
    return out, status
