"""Per-candidate steps of the compiled detector (:mod:`stemmap.scan._detect_fast`): the
segment filters as a reason code, the circle fit with its plausibility tests, arc extent and
quality, and the validated corner split of a rejected candidate (``refit_split="corners"``,
ours, issue 11).

Each repeats the expressions of the numpy reference in the same order, so the compiled
detector equals the numpy pipeline bit for bit (tests/scan/test_detect_fast.py):
:func:`stemmap.scan.plausibility.segment_reasons` and
:func:`~stemmap.scan.features.segment_features`; ``ScanTrunkDetector._fit_candidates``,
:func:`~stemmap.scan.plausibility.fitted_reasons` and ``_segment_fits._output_columns``;
:func:`stemmap.scan._refit.split_refit` with :func:`~stemmap.scan._refit.corner_cut_pieces`
and :func:`~stemmap.scan._refit.validate_pieces`. The parameter vector ``prm`` is read by
position (:data:`stemmap.scan._kernel_params.PARAM_NAMES`).

numba's cache of this module is dropped when a file whose kernels or constants it compiles in
changes (:func:`stemmap._numba_cache.drop_stale_cache`, as for ``_detect_fast``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit
from stemmap.scan import (
    _corners,
    _fast_robust,
    _fast_segments,
    _fit_geometric,
    _fit_lm,
    _kernel_params,
    features,
)
from stemmap.scan._corners import may_have_corner, piece_table, sagitta, segment_corners
from stemmap.scan._fast_robust import _range_roughness, _robust_residual_scale
from stemmap.scan._fast_segments import _algebraic_floor, _geometric_cov, _seg_sum
from stemmap.scan._fit_geometric import OK, _fit_one
from stemmap.scan._kernel_params import OUT_COLUMNS, PARAM_INDEX
from stemmap.scan.features import MIXED_FRACTION_STD
from stemmap.types import FloatArray

#: Reason codes of :data:`stemmap.scan.plausibility.REASONS` the kernel returns, and the
#: pre-fit bound's "fails a fit test, which one not known" (no fit was run).
_DEPTH = 5
_FIT_FAILED = 9
_RADIUS = 10
_RATIO = 11
_CENTRE = 12
_RMS = 13
_PREFIT = -1

#: Scratch of the kernel: silhouette priors (4,), the fit's ordered priors (4,), the fit's
#: output (14,), per-return values (N,), the fit's buffers (8, N), a 3x3 normal matrix, the
#: segment features (2,); and the fit's work arrays (6, 3, 3), (8, 3), (11,).
_Scratch = tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]
_Work = tuple[FloatArray, FloatArray, FloatArray]
_RAD2DEG = 180.0 / math.pi
_SQRT12 = math.sqrt(12.0)


@leaf_njit()
def _grid_at(grid: FloatArray, beam: int, n: int, wrap: bool) -> float:  # pragma: no cover
    """Range of ``beam`` in the scan's grid, inf for no return or outside the scan (the
    ``at`` helper of :func:`stemmap.scan.features.edge_silhouette`)."""
    if wrap:
        v = grid[beam % n]
    elif 0 <= beam < n:
        v = grid[beam]
    else:
        return math.inf
    return v if math.isfinite(v) else math.inf


@leaf_njit()
def _edge_prior(
    grid: FloatArray,
    edge_r: float,
    b_edge: int,
    step: int,
    n: int,
    wrap: bool,
    h: float,
    margin: float,
    out: FloatArray,
    o: int,
) -> None:  # pragma: no cover - numba
    """One end of :func:`stemmap.scan.features.edge_silhouette` (with ``mixed_fraction``):
    writes (offset, std) in beam spacings to ``out[o:o + 2]``, NaN for the default."""
    out[o] = np.nan
    out[o + 1] = np.nan
    r1 = _grid_at(grid, b_edge + step, n, wrap)
    r2 = _grid_at(grid, b_edge + 2 * step, n, wrap)
    bg = math.isfinite(r1) and r1 > edge_r + margin
    if not (bg and math.isfinite(r2)):
        return
    if abs(r2 - r1) <= margin:
        out[o] = 0.5
        out[o + 1] = (1.0 - 2.0 * h) / _SQRT12
    elif r2 > r1 + margin:
        m = r1
        a = 1.0 / edge_r
        b = 1.0 / r2
        f = b * (1.0 - m * b) / ((a - b) * (m * (a + b) - 1.0))
        if not (edge_r < m and m < r2) or not math.isfinite(f):
            return
        f = min(max(f, 0.0), 1.0)
        out[o] = 1.0 - h + 2.0 * h * f
        out[o + 1] = 2.0 * h * MIXED_FRACTION_STD


_HIT_MIN = PARAM_INDEX["edge_hit_min"]
_HIT_MAX = PARAM_INDEX["edge_hit_max"]


@leaf_njit()
def _edge_default(
    sil: FloatArray,
    prm: FloatArray,
    h: float,
    use: bool,
    grid: FloatArray,
    b_lo: int,
    b_hi: int,
    n: int,
    wrap: bool,
) -> None:  # pragma: no cover - numba
    """The ends whose next beam beyond (``b_lo - 1``, ``b_hi + 1``) returned nothing get
    :func:`stemmap.scan.features.edge_default_prior` of the configured return-threshold
    interval (``edge_hit_min`` / ``edge_hit_max``; nothing at the default 0.5 / 0.5), as
    :func:`stemmap.scan.features.edge_silhouette` does."""
    lo = prm[_HIT_MIN]
    hi = prm[_HIT_MAX]
    if not use or not h > 0.0 or (lo == 0.5 and hi == 0.5):
        return
    off = 0.5 + h * (lo + hi - 1.0)
    std = (1.0 + 2.0 * h * (hi - lo)) / _SQRT12
    if math.isinf(_grid_at(grid, b_lo - 1, n, wrap)):
        sil[0] = off
        sil[1] = std
    if math.isinf(_grid_at(grid, b_hi + 1, n, wrap)):
        sil[2] = off
        sil[3] = std


@leaf_njit(inline="always")
def _segment_code(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    tmp: FloatArray,
    a: int,
    b: int,
    partial: bool,
    prm: FloatArray,
    chi2: FloatArray,
    noise_s: float,
    feat: FloatArray,
) -> int:  # pragma: no cover - numba
    """Reason code of the segment filters for returns ``a:b`` (0 = kept;
    :func:`stemmap.scan.plausibility.segment_reasons` with the features of
    :func:`stemmap.scan.features.segment_features`); writes the edge-beam chord width and the
    sagitta depth to ``feat[0:2]``."""
    i1 = b - 1
    cnt = float(b - a)
    cross = px[a] * py[i1] - py[a] * px[i1]
    dot = px[a] * px[i1] + py[a] * py[i1]
    theta = abs(math.atan2(cross, dot))
    hh = math.sin(theta / 2.0)
    ra = pr[a]
    rb = pr[i1]
    width = math.sqrt((ra - rb) * (ra - rb) + 4.0 * ra * rb * hh * hh)  # Xue 2018 eq. 12
    depth = sagitta(px, py, a, b)  # features.sagitta_depth, Zheng §3.2 criterion 4
    den = width * width / 4.0 + depth * depth
    curv = 2.0 * depth / den if den > 0 else 0.0
    feat[0] = width
    feat[1] = depth
    if not cnt >= prm[16]:  # min_points
        return 1
    if partial and not cnt >= prm[17]:  # min_points_partial
        return 2
    if not cnt <= prm[18]:  # max_points
        return 3
    if not (width >= prm[19] and width <= prm[20]):  # min_width, max_width
        return 4
    if not depth >= prm[21]:  # min_depth
        return _DEPTH
    if not (curv >= prm[22] and curv <= prm[23]):  # min_curvature, max_curvature
        return 6
    if prm[24] > 0.0:  # reject_straight: line_fit_rms + is_straight (chi-square or ratio)
        mx = _seg_sum(px, a, b) / cnt
        my = _seg_sum(py, a, b) / cnt
        for i in range(a, b):
            qx = px[i] - mx
            tmp[i] = qx * qx
        sxx = _seg_sum(tmp, a, b) / cnt
        for i in range(a, b):
            qy = py[i] - my
            tmp[i] = qy * qy
        syy = _seg_sum(tmp, a, b) / cnt
        for i in range(a, b):
            tmp[i] = (px[i] - mx) * (py[i] - my)
        sxy = _seg_sum(tmp, a, b) / cnt
        tr = sxx + syy
        det = sxx * syy - sxy * sxy
        lam_min = tr / 2.0 - math.sqrt(max(tr * tr / 4.0 - det, 0.0))
        line_rms = math.sqrt(max(lam_min, 0.0))
        sig = max(prm[29] + prm[30] * (_seg_sum(pr, a, b) / cnt), noise_s)
        if prm[25] > 0.0:  # straight_chi2
            dof = max(cnt - 2.0, 1.0)
            stat = cnt * line_rms * line_rms / (sig * sig)
            straight = stat <= chi2[int(dof)]
        else:
            excess = math.sqrt(max(line_rms * line_rms - sig * sig, 0.0))
            straight = excess < prm[26] * width  # straight_ratio
        straight &= not (depth > prm[52] * sig)  # straight_depth_sigmas
        if straight and cnt >= prm[27]:  # straight_min_points
            return 7
    if prm[28] > 0.0 and partial:  # drop_partial
        return 8
    return 0


@leaf_njit(inline="always")
def _fit_candidate(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    pb: np.ndarray,
    a: int,
    b: int,
    oc0: bool,
    oc1: bool,
    tr0: bool,
    tr1: bool,
    width: float,
    grid: FloatArray,
    noise_s: float,
    prm: FloatArray,
    exact: bool,
    sil: FloatArray,
    sil_fit: FloatArray,
    fit_out: FloatArray,
    tmp: FloatArray,
    buf: FloatArray,
    jtj: FloatArray,
    ws3: FloatArray,
    wv: FloatArray,
    mdl: FloatArray,
    res: FloatArray,
) -> int:  # pragma: no cover - numba
    """Fit, plausibility tests, arc extent and quality of the candidate ``a:b``
    (detect.ScanTrunkDetector._run: ``_fit_candidates``, ``fitted_reasons``,
    ``_output_columns``). Returns the reason code of the first fit test it fails (0 = kept:
    ``res[:OUT_COLUMNS]`` is its output row, ``res[OUT_COLUMNS]`` its sigma and
    ``res[OUT_COLUMNS + 1]`` its fit RMS), or ``_PREFIT``
    when the pre-fit bound shows that no fit can pass (unless ``exact``: then the fit runs and
    the code is the test's)."""
    n = grid.shape[0]
    wrap = prm[3] > 0.0
    margin = prm[10]
    sigma0 = prm[29]
    sigma_rel = prm[30]
    fit_sigma_given = prm[31] > 0.0
    max_radius = prm[33]
    max_rw = prm[34]
    max_rms_sigma = prm[35]
    divergence = prm[36]
    inc = prm[39]
    rms_robust = prm[42] > 0.0
    bark = prm[43]
    absinc = abs(inc)
    h_sil = divergence / (2.0 * absinc) if absinc > 0.0 else 0.0
    use_sil = prm[37] > 0.0 and 0.0 < h_sil < 0.5
    rms_check = math.isfinite(max_rms_sigma)
    cnt_i = b - a
    mean_r = _seg_sum(pr, a, b) / cnt_i
    sig = max(sigma0 + sigma_rel * mean_r, noise_s)
    if prm[40] > 0.0 and fit_sigma_given:  # sigma_from_data (sigma 0: the fit estimates it)
        sig = max(sig, min(_range_roughness(pr[a:b]), prm[41] * sig))
    sil[:] = np.nan
    if use_sil:
        _edge_prior(grid, pr[a], pb[a], -1, n, wrap, h_sil, margin, sil, 0)
        _edge_prior(grid, pr[b - 1], pb[b - 1], 1, n, wrap, h_sil, margin, sil, 2)
    _edge_default(sil, prm, h_sil, prm[37] > 0.0, grid, pb[a], pb[b - 1], n, wrap)  # use_silhouette
    sil_width = width
    if use_sil:
        beyond = 0.0 if math.isnan(sil[0]) else max(sil[0] - 0.5, 0.0)
        beyond += 0.0 if math.isnan(sil[2]) else max(sil[2] - 0.5, 0.0)
        sil_width = width + beyond * mean_r * absinc
    if rms_check and not rms_robust and not exact:  # (the bound holds for the plain RMS only)
        # Exact early reject (docs/algorithms/scan-detection.md, "pre-fit bound"): a
        # circle the checks below accept has r <= r_cap and RMS <= k sigma, so every
        # |d_i - r| <= sqrt(N) k sigma and d_i + r <= 2 r_cap + sqrt(N) k sigma = M;
        # with (d - r) = (d^2 - r^2) / (d + r), N RMS^2 >= kasa_min / M^2. If even that
        # floor exceeds the RMS limit, no fit can pass: skip the (costly) fit.
        r_cap = min(max_radius, max_rw * max(sil_width, 1e-9))
        lim = max_rms_sigma * sig
        if bark > 0.0:  # the bound grows with the radius: take it at r_cap
            lim = max_rms_sigma * math.sqrt(sig * sig + (bark * r_cap) * (bark * r_cap))
        m_cap = 2.0 * r_cap + math.sqrt(cnt_i) * lim
        floor = _algebraic_floor(px, py, a, b) / (m_cap * m_cap)
        if floor > 1.001 * cnt_i * lim * lim:  # margin: round-off of the floor
            return _PREFIT
    e_start = not (oc0 or tr0)
    e_end = not (oc1 or tr1)
    if inc < 0:  # the fit takes the ends in bearing order
        use_lo, use_hi = e_end, e_start
        sil_fit[0] = sil[2]
        sil_fit[1] = sil[3]
        sil_fit[2] = sil[0]
        sil_fit[3] = sil[1]
    else:
        use_lo, use_hi = e_start, e_end
        for q in range(4):  # (element by element: an array copy would need the NRT)
            sil_fit[q] = sil[q]
    fit_out[:] = np.nan
    status = _fit_one(
        px[a:b],
        py[a:b],
        0.0,
        0.0,
        sig if fit_sigma_given else 0.0,
        absinc,
        use_lo,
        use_hi,
        sil_fit,
        divergence,
        prm[38] > 0.0,  # range_model
        fit_out,
        buf,
        ws3,
        wv,
        mdl,
        1.0,  # the fit's default stopping thresholds
        True,  # uniform tangent intervals on two-tangent arcs (the fit's default)
    )
    if status != OK:
        return _FIT_FAILED
    cx = fit_out[0]
    cy = fit_out[1]
    rad = fit_out[2]
    if not (rad >= prm[32] and rad <= max_radius):
        return _RADIUS
    if not rad <= max_rw * max(sil_width, 1e-9):
        return _RATIO
    if not math.hypot(cx, cy) > mean_r:
        return _CENTRE
    for i in range(a, b):
        r_i = math.hypot(px[i] - cx, py[i] - cy) - rad
        tmp[i] = r_i * r_i
    rms = math.sqrt(_seg_sum(tmp, a, b) / cnt_i)
    if rms_check:
        lim = max_rms_sigma * sig
        if bark > 0.0:  # plausibility.rms_limit
            lim = max_rms_sigma * math.sqrt(sig * sig + (bark * rad) * (bark * rad))
        if rms_robust:
            if not _robust_residual_scale(px[a:b], py[a:b], cx, cy, rad) <= lim:
                return _RMS
        elif not rms <= lim:
            return _RMS
    cov_ok = True
    for q in range(9):
        cov_ok &= math.isfinite(fit_out[3 + q])
    if not cov_ok:
        _geometric_cov(px, py, a, b, cx, cy, rad, sig, tmp, jtj, fit_out)
    # arc extent around the centre (detect._arc_deg)
    ref = math.atan2(-cy, -cx)
    pmax = -math.inf
    pmin = math.inf
    for i in range(a, b):
        phi = math.atan2(py[i] - cy, px[i] - cx) - ref
        # numba's float % is CPython's (fmod, then the divisor's sign), i.e. np.mod
        phi = math.pi - (math.pi - phi) % (2.0 * math.pi)
        pmax = max(pmax, phi)
        pmin = min(pmin, phi)
    # quality (detect._quality)
    support = min(cnt_i / 10.0, 1.0)
    sq = max(sig, 1e-6)
    e = max(rms - sq, 0.0) / (3.0 * sq)
    partial = oc0 or oc1 or tr0 or tr1
    for q in range(12):
        res[q] = fit_out[q]
    res[12] = (pmax - pmin) * _RAD2DEG
    res[13] = width
    res[14] = support * math.exp(-(e * e)) * (0.5 if partial else 1.0)
    res[15] = cnt_i
    res[OUT_COLUMNS] = sig
    res[OUT_COLUMNS + 1] = rms
    return 0


@leaf_njit(inline="always")
def corner_threshold(
    pr: FloatArray, a: int, b: int, depth: float, noise_s: float, prm: FloatArray
) -> float:  # pragma: no cover - numba
    """Least concave depth of a corner of candidate ``a:b`` with sagitta ``depth``
    (:func:`~stemmap.scan._refit.corner_cut_pieces`): ``corner_depth`` if the candidate is
    not a convex arc, else ``corner_depth_convex``, at least ``corner_sigmas`` range-noise
    sigmas; ``inf`` where no return has ``corner_span`` neighbours on both sides. The
    split's pre-test: a convex candidate with ``corner_depth_convex`` infinite (every
    candidate that reached the RMS test, with ``min_depth`` >= 0) has no corner and costs
    no look at its returns."""
    span = int(prm[45])
    if b - a < 2 * span + 1:
        return math.inf
    thr = prm[46] if depth < max(prm[21], 0.0) else prm[47]
    if not thr < math.inf:
        return math.inf
    sig = max(prm[29] + prm[30] * (_seg_sum(pr, a, b) / float(b - a)), noise_s)
    return max(thr, prm[48] * sig)


@leaf_njit()
def _split_parent(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    pb: np.ndarray,
    a: int,
    b: int,
    flags: tuple[bool, bool, bool, bool],
    width: float,
    code: int,
    grid: FloatArray,
    noise_s: float,
    prm: FloatArray,
    chi2: FloatArray,
    scratch: _Scratch,
    ws: _Work,
    corner: np.ndarray,
    table: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    pres: FloatArray,
) -> int:  # pragma: no cover - numba
    """``refit_split="corners"`` for one rejected candidate ``a:b`` (reason ``code``: depth,
    rms or ``_PREFIT``; :func:`stemmap.scan._refit.split_refit`) with concave corners
    ``corner`` (:func:`corner_threshold`,
    :func:`~stemmap.scan._corners.segment_corners`): cut there, every piece judged by
    the segment filters and fitted; with ``refit_validate`` accepted only as the
    candidate's one passing piece, no circle-like sibling failing its fit, no return of
    the candidate more than 3 sigma inside its circle (``_refit.validate_pieces``,
    ``_returns_inside``). Writes the accepted pieces' output rows to ``pres`` and
    returns their number."""
    sil, sil_fit, fit_out, tmp, buf, jtj, feat = scratch
    ws3, wv, mdl = ws
    oc0, oc1, tr0, tr1 = flags
    if code == _PREFIT:  # rejected by the pre-fit bound: which fit test, only a fit tells
        code = _fit_candidate(
            px, py, pr, pb, a, b, oc0, oc1, tr0, tr1, width, grid, noise_s, prm, True,
            sil, sil_fit, fit_out, tmp, buf, jtj, ws3, wv, mdl, pres[0],
        )  # fmt: skip
        if code != _RMS:
            return 0
    pst, psp, poc0, poc1, ptr0, ptr1 = table
    k = piece_table(a, b, corner, oc0, oc1, tr0, tr1, pst, psp, poc0, poc1, ptr0, ptr1)
    n_pass = 0
    n_fail = 0  # circle-like (passed the segment filters) pieces whose fit fails
    for q in range(k):
        qa = pst[q]
        qb = psp[q]
        partial = poc0[q] or poc1[q] or ptr0[q] or ptr1[q]
        pres[q, OUT_COLUMNS] = math.nan  # not passed
        if _segment_code(px, py, pr, tmp, qa, qb, partial, prm, chi2, noise_s, feat) != 0:
            continue
        w = feat[0]
        c = _fit_candidate(
            px, py, pr, pb, qa, qb, poc0[q], poc1[q], ptr0[q], ptr1[q], w, grid, noise_s,
            prm, False, sil, sil_fit, fit_out, tmp, buf, jtj, ws3, wv, mdl, pres[q],
        )  # fmt: skip
        if c == 0:
            n_pass += 1
        else:
            n_fail += 1
            pres[q, OUT_COLUMNS] = math.nan
    validate = prm[57] > 0.0
    if validate and (n_fail > 0 or n_pass > 1):
        return 0
    out = 0
    for q in range(k):
        sq = pres[q, OUT_COLUMNS]
        if math.isnan(sq):
            continue
        if validate:  # a trunk hides what is behind it: no return of the parent inside
            lim = pres[q, 2] - 3.0 * sq
            inside = False
            for i in range(a, b):
                inside |= math.hypot(px[i] - pres[q, 0], py[i] - pres[q, 1]) < lim
            if inside:
                continue
        if out != q:  # (element by element: an array copy would need the NRT)
            for col in range(pres.shape[1]):
                pres[out, col] = pres[q, col]
        out += 1
    return out


@njit(cache=True, error_model="numpy", inline="always")
def _emit(
    rows: FloatArray, scans: np.ndarray, n_out: int, s: int, res: FloatArray
) -> tuple[FloatArray, np.ndarray, int]:  # pragma: no cover - numba
    """Append the output row ``res[:OUT_COLUMNS]`` of scan ``s``, growing the tables."""
    if n_out == rows.shape[0]:
        rows2 = np.empty((2 * n_out, OUT_COLUMNS))
        rows2[:n_out] = rows
        rows = rows2
        scans2 = np.empty(2 * n_out, dtype=np.int64)
        scans2[:n_out] = scans
        scans = scans2
    for q in range(OUT_COLUMNS):
        rows[n_out, q] = res[q]
    scans[n_out] = s
    return rows, scans, n_out + 1


@leaf_njit(inline="always")
def has_corners(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    a: int,
    b: int,
    depth: float,
    noise_s: float,
    prm: FloatArray,
    tmp: FloatArray,
    corner: np.ndarray,
) -> bool:  # pragma: no cover - numba
    """The corner split's pre-test, inline in the kernel: whether candidate ``a:b`` (sagitta
    ``depth``) has a concave corner (:func:`corner_threshold`,
    :func:`~stemmap.scan._corners.segment_corners`, flags left in ``corner``). Costs no look
    at the returns where the threshold is infinite, runs the exact test only where the
    squared one (:func:`~stemmap.scan._corners.may_have_corner`) finds a deep return, and
    allocates nothing."""
    thr = corner_threshold(pr, a, b, depth, noise_s, prm)
    if not thr < math.inf:
        return False
    span = int(prm[45])
    if not may_have_corner(px, py, a, b, span, thr):  # no square root per return
        return False
    return segment_corners(px, py, a, b, span, thr, tmp, corner) > 0


@njit(cache=True, error_model="numpy")
def _split_emit(
    rows: FloatArray,
    scans: np.ndarray,
    n_out: int,
    s: int,
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    pb: np.ndarray,
    j: int,
    st: np.ndarray,
    sp: np.ndarray,
    oc0: np.ndarray,
    oc1: np.ndarray,
    tr0: np.ndarray,
    tr1: np.ndarray,
    wid: FloatArray,
    dep: FloatArray,
    code: int,
    grid: FloatArray,
    noise_s: float,
    prm: FloatArray,
    chi2: FloatArray,
    scratch: _Scratch,
    ws: _Work,
    corner: np.ndarray,
    table: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    pres: FloatArray,
) -> tuple[FloatArray, np.ndarray, int]:  # pragma: no cover - numba
    """:func:`_split_parent` for candidate ``j`` of the table ``st, sp, ...`` of scan ``s``,
    rejected with ``code`` (``_DEPTH``, or ``_PREFIT``: some fit test failed) and with a
    concave corner (:func:`has_corners`, flags in ``corner``); the accepted pieces are
    appended to the output ``rows, scans`` (its place in the output: the candidate's)."""
    a = st[j]
    b = sp[j]
    k = _split_parent(
        px, py, pr, pb, a, b, (oc0[j], oc1[j], tr0[j], tr1[j]), wid[j], code, grid,
        noise_s, prm, chi2, scratch, ws, corner, table, pres,
    )  # fmt: skip
    for q in range(k):
        rows, scans, n_out = _emit(rows, scans, n_out, s, pres[q])
    return rows, scans, n_out


# after every kernel is defined, before the first call loads the cache (see the module notes)
_numba_cache.drop_stale_cache(
    _fit_candidate,
    __file__,
    _fit_geometric.__file__,
    features.__file__,
    _corners.__file__,
    _fast_robust.__file__,
    _fast_segments.__file__,
    _fit_lm.__file__,
    _kernel_params.__file__,
)
