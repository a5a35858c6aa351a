"""The Levenberg-Marquardt core of the "ours" circle fit (:mod:`stemmap.scan._fit_geometric`):
the residual model (range residuals of a footprint-averaged or thin beam, or orthogonal
distances, with the Gaussian silhouette terms), Huber weights, the Gauss-Newton normal
equations, 3x3 solves and the damped iteration. The model is documented in
:mod:`stemmap.scan.circle` and docs/algorithms/scan-fits.md.

Kept free of other modules' kernels: numba's cache of this file depends on this file and the
compile flags (:mod:`stemmap._leaf_jit`, dropped at import when it changes) alone;
the modules that compile these kernels in (:mod:`stemmap.scan._fit_geometric`,
:mod:`stemmap.scan._detect_fast`) drop their caches when it changes."""

from __future__ import annotations

import math

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit
from stemmap.types import FloatArray

_HUBER_K = 1.5  # Huber threshold in units of sigma (95 % efficiency under Gaussian noise)


_MAX_ITER = 40


@leaf_njit()
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


@leaf_njit()
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


@leaf_njit(inline="always")
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


@leaf_njit(inline="always")
def _huber(e: float, robust: bool) -> tuple[float, float]:  # pragma: no cover - numba
    """(cost, IRLS weight) of a normalised residual under the Huber loss (or plain LS)."""
    ae = abs(e)
    if robust and ae > _HUBER_K:
        return _HUBER_K * ae - 0.5 * _HUBER_K * _HUBER_K, _HUBER_K / ae
    return 0.5 * e * e, 1.0


@leaf_njit(inline="always")
def _footprint_range(
    b: float, s0: float, r: float, foot: float, out: FloatArray
) -> bool:  # pragma: no cover - numba
    """:func:`_footprint_range_share` with the half-footprint window (the fit's default edge
    model: a beam returns when half its footprint hits)."""
    return _footprint_range_share(b, s0, r, foot, 0.5, out)


@leaf_njit(inline="always")
def _footprint_range_share(
    b: float, s0: float, r: float, foot: float, share: float, out: FloatArray
) -> bool:  # pragma: no cover - numba
    """Mean range over the part of a beam footprint that hits the circle, and its partials.

    The beam's centre ray has unit direction u; ``b = u . c`` and ``s0 = u x c`` (signed
    distance of the centre from the ray). A ray rotated by delta (|delta| <= foot / 2) sees the
    centre at ``b + s0 delta`` along it and ``s0 - b delta`` across it (first order in delta,
    error < 0.03 mm for foot = 0.25 deg), so its first hit is at
    ``b + s0 delta - sqrt(r^2 - (s0 - b delta)^2)``. Averaged over the hit part
    [da, db] of the footprint (|s0 - b delta| <= r) the square root integrates in closed form.

    A beam returns only if at least a ``share`` of its footprint hits (0.5: its centre ray
    hits). When the circle leaves less than that, the window is kept at that share of the
    footprint on the circle's side (rays past the tangent count at their closest approach, the
    square root being 0 there): the prediction and its derivatives stay bounded and continuous
    where the model says the beam should not have returned; the silhouette term pulls the
    circle back. A share below one half (``DetectorConfig.edge_hit_window``, Dec 5) lets a
    sliver of the footprint on the circle read as the sliver's own mean range, as a scanner
    with a lower return threshold reports it, instead of as half a footprint whose rest lies
    past the tangent (a nearer range explained by a wider circle).
    Writes (pred, d pred/d b, d pred/d s0, d pred/d r) to ``out``; False if b <= 0."""
    if not b > 0.0:
        return False
    half = 0.5 * foot
    lo_c = (s0 - r) / b
    hi_c = (s0 + r) / b
    # the window reaches at least (share - 1/2) footprints past the centre ray on the circle's
    # side (0 for the half footprint)
    qw = share * foot - half
    da = max(-half, min(lo_c, -qw))
    db = min(half, max(hi_c, qw))
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
    if -half < lo_c < -qw:  # the lower limit is the circle's edge: da = (s0 - r) / b
        p_da = 0.5 * s0 + b * fpa / bw - S / (bw * wd)
        p_b += p_da * (-lo_c / b)
        p_s += p_da / b
        p_r += -p_da / b
    if qw < hi_c < half:  # the upper limit is the circle's edge: db = (s0 + r) / b
        p_db = 0.5 * s0 - b * fpb / bw + S / (bw * wd)
        p_b += p_db * (-hi_c / b)
        p_s += p_db / b
        p_r += p_db / b
    out[0] = pred
    out[1] = p_b
    out[2] = p_s
    out[3] = p_r
    return True


@leaf_njit(inline="always")
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
    share: float,
) -> tuple[float, float, float, float, float, float, float, float]:  # pragma: no cover
    """Range residual of return i (metres) along its beam and its Jacobian over (cx, cy, r),
    plus a second "miss" residual (distance by which the beam passes the circle) and its
    Jacobian: (e, j0, j1, j2, m, k0, k1, k2). ``foot > 0``: footprint-averaged prediction,
    the window at least ``share`` of the footprint (:func:`_footprint_range_share`).
    ``uxs``, ``uys``: unit beam directions of the returns."""
    ux = uxs[i]
    uy = uys[i]
    b = ux * cx + uy * cy
    s0 = ux * cy - uy * cx
    # d b / d(cx, cy) = u; d s0 / d(cx, cy) = (-uy, ux)
    if foot > 0.0:
        if _footprint_range_share(b, s0, r, foot, share, tmp):
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


@leaf_njit()
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
    use_sil, share): silhouette targets and inverse stds (0 = side unused), beam footprint (rad),
    indices of the lowest/highest-bearing returns (footprint-averaged in the range model) and
    whether residuals are ranges along the beams (1) or orthogonal distances (0), and the
    least share of the footprint the edge returns' range window keeps (0.5: the default
    model; :func:`_footprint_range_share`; set by the caller of :func:`_fit_one`, which leaves
    it; read with the range model only, so orthogonal-distance callers such as
    :mod:`stemmap.cloud.slicefit` pass 10 entries). ``tmp`` (>= 4) is scratch space."""
    acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    cost = 0.0
    n = lx.shape[0]
    inv_sigma = mdl[0]
    range_model = mdl[8] > 0.0
    foot = mdl[5]
    i_lo = int(mdl[6])
    i_hi = int(mdl[7])
    # read by the range model only: an orthogonal-distance caller may pass 10 entries
    share = mdl[10] if range_model else 0.5
    for i in range(n):
        if keep[i] == 0.0:
            continue
        if range_model:
            f_i = 0.0
            if (i == i_lo and mdl[3] > 0.0) or (i == i_hi and mdl[4] > 0.0):
                f_i = foot
            e, j0, j1, j2, m, k0, k1, k2 = _range_residual(
                i, ux, uy, rho, cx, cy, r, f_i, tmp, share
            )
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


@leaf_njit()
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


@leaf_njit()
def levenberg_marquardt(
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
    """Levenberg-Marquardt on (cx, cy, r) in place; returns (cost, iterations). Public: the
    cloud's slice fits (:mod:`stemmap.cloud.slicefit`) compile it in too.

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


# after every kernel is defined, before the first call loads the cache: no other module's
# kernels are compiled in here, but the compile flags (stemmap._leaf_jit) are
_numba_cache.drop_stale_cache(levenberg_marquardt, __file__)
