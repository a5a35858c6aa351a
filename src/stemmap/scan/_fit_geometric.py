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

The Levenberg-Marquardt core (residual model, Huber weights, solves, the damped iteration) is
:mod:`stemmap.scan._fit_lm`; this module drops its own numba cache when that file changes
(:func:`stemmap._numba_cache.drop_stale_cache`, at the end). The detector's compiled pipeline
(:mod:`stemmap.scan._detect_fast`) calls ``_fit_one`` directly; that module drops its numba
cache when this file or :mod:`~stemmap.scan._fit_lm` changes (see its docstring).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit, nrt_njit
from stemmap.scan import _fit_lm
from stemmap.scan._fit_lm import _footprint_range as _footprint_range
from stemmap.scan._fit_lm import _inv3, _range_residual, _solve3, _valid, levenberg_marquardt
from stemmap.types import FloatArray

__all__ = ["STATUS_MESSAGES", "fit_ours_segments", "kasa_start"]

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

_REJECT = 4.0  # outlier rejection threshold, sigma units, after the Huber fit
_SIGMA_FLOOR = 2e-4  # metres: smallest noise scale used when sigma is estimated from residuals
_SQRT12 = math.sqrt(12.0)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)


@leaf_njit()
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
        e, _, _, _, m, _, _, _ = _range_residual(
            i, ux, uy, rho, p[0], p[1], p[2], f_i, tmp, mdl[10]
        )
        return math.sqrt(e * e + m * m)
    return abs(math.sqrt((lx[i] - p[0]) ** 2 + (ly[i] - p[1]) ** 2) - p[2])


@leaf_njit()
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


@leaf_njit()
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


@nrt_njit()
def _median_spacing(th: FloatArray) -> float:  # pragma: no cover - numba
    """Median spacing of the sorted bearings ``th`` (the beam step when none is given); kept
    out of :func:`_fit_one`, which compiles without reference counting and cannot
    allocate."""
    diffs = np.diff(np.sort(th))
    return float(np.median(diffs))


@nrt_njit()
def _median_of(x: FloatArray) -> float:  # pragma: no cover - numba
    """``np.median(x)`` (allocates: kept out of :func:`_fit_one`)."""
    return float(np.median(x))


@nrt_njit()
def _reject_largest(dabs: FloatArray, keep: FloatArray, limit: float) -> int:  # pragma: no cover
    """Drop (``keep`` = 0) up to N // 4 returns with |residual| ``dabs`` > ``limit``, largest
    first, if any is (``np.max``: none where one is NaN); return how many (allocates: kept out
    of :func:`_fit_one`)."""
    n = dabs.shape[0]
    n_rej = 0
    if not np.max(dabs) > limit:
        return n_rej
    order = np.argsort(-dabs)
    for j in range(n // 4):
        i = order[j]
        if dabs[i] > limit:
            keep[i] = 0.0
            n_rej += 1
    return n_rej


@nrt_njit()
def kasa_start(lx: FloatArray, ly: FloatArray, p: FloatArray) -> bool:  # pragma: no cover
    """The algebraic (Kasa) circle of the local-frame returns (``lx``, ``ly``) into ``p``
    (cx, cy, r), the start without a silhouette; False where the returns are collinear
    (allocates: kept out of :func:`_fit_one`). Public: the cloud's slice fits
    (:mod:`stemmap.cloud.slicefit`) compile it in too."""
    n = lx.shape[0]
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
        return False
    kcx = -0.5 * sol[0]
    kcy = -0.5 * sol[1]
    r2 = kcx * kcx + kcy * kcy - sol[2]
    if not r2 > 0.0:
        return False
    p[0] = kcx * sc + mx
    p[1] = kcy * sc + my
    p[2] = math.sqrt(r2) * sc
    return True


@leaf_njit()
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

    ``buf`` (8, >= N), ``ws3`` (6, 3, 3), ``wv`` (8, 3) and ``mdl`` (11,) are scratch space
    shared by all segments of a batch, so a fit allocates nothing on the common path; the
    caller sets ``mdl[10]``, the least share of the footprint in the edge returns' range
    window (0.5: the default edge model; :func:`_cost_and_normal`), which the fit leaves.
    ``tol``: scale of the LM stopping thresholds (:func:`levenberg_marquardt`; 1.0 = the
    defaults). ``box``: refine arcs with both tangents by the uniform tangent intervals
    (:func:`_box_tangents`)."""
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
        dtheta = _median_spacing(th)
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
    # No silhouette: start from the algebraic (Kasa) solution in the local frame.
    if not use_sil and not kasa_start(lx, ly, p):
        return COLLINEAR
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
        levenberg_marquardt(lx, ly, rho, ux, uy, keep, p, mdl, rho_min, True, ws3, wv, tol)
        ss = 0.0
        for i in range(n):
            d = _abs_residual(i, lx, ly, rho, ux, uy, p, mdl, tmp)
            ss += d * d
        dof = n - 3 if n > 3 else 1
        sig = max(math.sqrt(ss / dof), _SIGMA_FLOOR)
    mdl[0] = 1.0 / sig
    levenberg_marquardt(lx, ly, rho, ux, uy, keep, p, mdl, rho_min, True, ws3, wv, tol)
    # ---- outlier rejection (mixed pixels): drop up to N // 4 returns beyond 4 sigma ----
    if n >= 6:
        for i in range(n):
            dabs[i] = _abs_residual(i, lx, ly, rho, ux, uy, p, mdl, tmp)
        scale = sig
        if sigma <= 0.0:
            scale = max(1.4826 * _median_of(dabs) * math.sqrt(n / (n - 3.0)), _SIGMA_FLOOR)
        n_rej = _reject_largest(dabs, keep, _REJECT * scale)
        if n_rej > 0:
            if sigma <= 0.0:
                ss = 0.0
                for i in range(n):
                    ss += keep[i] * dabs[i] * dabs[i]
                sig = max(math.sqrt(ss / max(n - n_rej - 3, 1)), _SIGMA_FLOOR)
                mdl[0] = 1.0 / sig
            levenberg_marquardt(lx, ly, rho, ux, uy, keep, p, mdl, rho_min, True, ws3, wv, tol)
    if not _valid(p[0], p[1], p[2], rho_min, use_sil):
        return NOT_CONVERGED
    if not use_sil and p[2] > 1e3 * max(extent, 1e-9):
        return COLLINEAR
    # ---- covariance from the final (robustly weighted) Gauss-Newton Hessian ----
    # the last levenberg_marquardt left the normal equations at the returned p in ws3[0] (same
    # p, mdl, keep, robust weights as a fresh _cost_and_normal: the identical numbers, one pass
    # saved)
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
        for a in range(3):  # (element by element: an array copy would need the NRT)
            for b in range(3):
                Ce[a, b] = C[a, b]
        if _box_tangents(pe, Ce, mdl, wv[6:8]) and _valid(pe[0], pe[1], pe[2], rho_min, use_sil):
            p[0], p[1], p[2] = pe[0], pe[1], pe[2]
            for a in range(3):
                for b in range(3):
                    C[a, b] = Ce[a, b]
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
    share: float,
) -> None:  # pragma: no cover - numba
    nmax = 0
    for k in range(starts.shape[0]):
        nmax = max(nmax, stops[k] - starts[k])
    buf = np.empty((8, nmax))
    ws3 = np.empty((6, 3, 3))
    wv = np.empty((8, 3))
    mdl = np.empty(11)
    mdl[10] = share
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
    edge_window: float = 0.5,
) -> tuple[FloatArray, np.ndarray]:
    """Run the kernel on K segments ``px[starts[k]:stops[k]]``.

    All per-segment arrays have shape (K,); ``sigma <= 0`` means "estimate from residuals",
    ``dtheta <= 0`` means "estimate the beam spacing from the bearings". ``tolerance`` scales
    the LM stopping thresholds (1.0: the defaults the detector uses; tests pass e.g. 1e-8 to
    get a tightly converged reference of the same cost). ``box_tangents``: where both tangents
    are observed, refine the fit by the uniform tangent intervals the Gaussian silhouette terms
    stand for (:func:`_box_tangents`; the detector's default); False = the plain MAP of the
    Gaussian surrogate. ``edge_window``: the least share of the footprint in the range window
    of a footprint-averaged edge return (:func:`stemmap.scan._fit_lm._footprint_range_share`;
    0.5, the default edge model; ``DetectorConfig.edge_hit_window``).

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
        float(edge_window),
    )
    out[status != OK] = np.nan
    return out, status


# after every kernel is defined, before the first call loads the cache: the kernels compile in
# _fit_lm's, so an edit there must drop this module's entries too (stemmap._numba_cache)
_numba_cache.drop_stale_cache(_fit_segments, __file__, _fit_lm.__file__)
