"""Compiled single-pass version of :class:`~stemmap.scan.detect.ScanTrunkDetector`'s pipeline.

One numba kernel runs, scan by scan, every step the detector otherwise runs as a chain of
vectorised numpy functions: range gate and field-of-view window, three-neighbour median filter
(Xue et al. 2018 §2.2), 360-degree seam cut, point extraction, range-jump (Zheng et al. 2012
eq. 2) or adaptive Euclidean segmentation, occlusion flags, single-point curvature filter
(Zheng eq. 3), radius median filter with optional splitting (visual-lidar paper 2023 §2.3),
segment features and filters (Xue eq. 12 width, Zheng §3.2 depth and curvature, chi-square
straightness test), the edge-silhouette priors, the "ours" circle fit (the same compiled
``_fit_one`` of :mod:`stemmap.scan._fit_geometric`), the plausibility checks, arc extent and
quality, with ``refit_split="corners"`` the validated corner split of rejected candidates and
with ``arc_refit`` the largest consistent arc of a candidate (ours, issue 11;
:mod:`stemmap.scan._fast_arcs`) and with ``step_split`` the cut of a candidate that fails the
RMS test at its largest range step (:mod:`stemmap.scan._fast_step_split`). The named pure
functions in :mod:`~stemmap.scan.preprocess`, :mod:`~stemmap.scan.segment` and
:mod:`~stemmap.scan.features` remain the reference: this
kernel evaluates the same expressions in the same order, and every per-segment sum replicates
numpy's pairwise summation of ``np.add.reduceat`` (:func:`_seg_sum`), so its results equal the
reference pipeline's bit for bit on this machine (tests/scan/test_detect_fast.py compares them;
docs/algorithms/scan-detection.md, "Speed").

Why: the numpy pipeline pays ~100 small array dispatches per call, which dominate the latency
of a single scan (~1 ms) and a third of the batch time; the kernel touches each return a few
times in cache and allocates nothing per scan on the common path.

Which calls take this path is decided by ``ScanTrunkDetector._compiled``: fit "ours", no
first-echo footprint correction, no tilt compensation to apply, re-fitted pieces only as corner
splits, no relaxed RMS tests. Everything else runs the numpy pipeline.

The kernel's helpers live in :mod:`stemmap.scan._fast_candidates` (per candidate: segment
filters as a reason code, fit and plausibility tests, arc and quality, the corner split),
:mod:`stemmap.scan._fast_robust` (medians and robust scales: range roughness, the scan's own
noise estimate, the fit's residual scale) and :mod:`stemmap.scan._fast_segments` (numpy's
pairwise sums, the segment table's select / drop, the pre-fit algebraic floor, the covariance
fallback); its parameter vector is :mod:`stemmap.scan._kernel_params`.

numba's on-disk cache (``cache=True``) of this module is keyed on this file alone, but the
kernel compiles in those helpers and constants, ``_fit_one`` of
:mod:`stemmap.scan._fit_geometric` (with its Levenberg-Marquardt core,
:mod:`stemmap.scan._fit_lm`), the corner and gap cuts (:mod:`stemmap.scan._corners`,
:mod:`stemmap.scan._gaps`) and the constant ``MIXED_FRACTION_STD`` of
:mod:`stemmap.scan.features`; at import :func:`stemmap._numba_cache.drop_stale_cache` drops
this module's cache entries when any of those files or the compile flags
(:mod:`stemmap._leaf_jit`) changed (an edit, or a ``git pull`` into an editable install), so the
stale code cannot keep running (tests/test_numba_cache.py lists the same files).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap import _numba_cache
from stemmap.scan import (
    _corners,
    _fast_arcs,
    _fast_candidates,
    _fast_robust,
    _fast_segments,
    _fast_step_split,
    _fit_geometric,
    _fit_lm,
    _gaps,
    _kernel_params,
    features,
)
from stemmap.scan._corners import corner_parity, cut_tables, sagitta
from stemmap.scan._fast_arcs import ARC_WORK_ROWS, arc_candidate, arc_run, continues_outline
from stemmap.scan._fast_candidates import (
    _DEPTH,
    _PREFIT,
    _RAD2DEG,
    _edge_default,
    _edge_prior,
    _emit,
    _split_emit,
    has_corners,
)
from stemmap.scan._fast_robust import (
    _batch_scan_noise,
    _median,
    _range_roughness,
    _robust_residual_scale,
    _scan_noise,
)
from stemmap.scan._fast_robust import _interior_triples as _interior_triples
from stemmap.scan._fast_robust import _median_inplace as _median_inplace
from stemmap.scan._fast_segments import (
    _algebraic_floor,
    _drop,
    _geometric_cov,
    _seg_sum,
    _select_min,
)
from stemmap.scan._fast_step_split import step_emit
from stemmap.scan._fit_geometric import OK, _fit_one
from stemmap.scan._gaps import gap_cut_flags, gap_cut_occlusion
from stemmap.scan._kernel_params import N_PARAMS as N_PARAMS
from stemmap.scan._kernel_params import OUT_COLUMNS
from stemmap.scan._kernel_params import PARAM_INDEX as PARAM_INDEX
from stemmap.scan._kernel_params import PARAM_NAMES as PARAM_NAMES
from stemmap.types import FloatArray

__all__ = ["N_PARAMS", "PARAM_INDEX", "detect_scans"]

_BATCH_MIN = PARAM_INDEX["scan_noise_batch_min"]
_STEP = PARAM_INDEX["step_split"]
_STEP_NOISE = PARAM_INDEX["step_noise_on"]
_STEP_POOL = PARAM_INDEX["step_noise_pool"]
_STEP_BATCH_MIN = PARAM_INDEX["step_noise_batch_min"]
_EDGE_WINDOW = PARAM_INDEX["edge_window"]
_BIWEIGHT = PARAM_INDEX["batch_noise_biweight"]


@njit(cache=True, error_model="numpy")
def _detect_kernel(
    ranges: FloatArray,
    cosb: FloatArray,
    sinb: FloatArray,
    fov_in: np.ndarray,
    prm: FloatArray,
    chi2: FloatArray,
) -> tuple[FloatArray, np.ndarray, int]:  # pragma: no cover - numba
    """The detector pipeline over every scan (see the module docstring and
    :func:`detect_scans`). ``prm`` is unpacked below in :data:`PARAM_NAMES` order (keep the two
    in step). Each block names the reference function whose expressions it repeats."""
    s_count, n = ranges.shape
    lo = prm[0]
    hi = prm[1]
    median = prm[2] > 0.0
    wrap = prm[3] > 0.0
    first_beam = int(prm[4])
    last_beam = int(prm[5])
    euclid = prm[6] > 0.0
    max_jump = prm[7]
    range_factor = prm[8]
    max_skip = int(prm[9])
    margin = prm[10]
    pcur_on = prm[11] > 0.0
    pcur_min = prm[12]
    rmed_on = prm[13] > 0.0
    rmed = prm[14]
    split = prm[15] > 0.0
    min_points = prm[16]
    min_points_partial = prm[17]
    max_points = prm[18]
    min_width = prm[19]
    max_width = prm[20]
    min_depth = prm[21]
    min_curv = prm[22]
    max_curv = prm[23]
    reject_straight = prm[24] > 0.0
    straight_chi2 = prm[25] > 0.0
    straight_ratio = prm[26]
    straight_min_points = prm[27]
    drop_partial = prm[28] > 0.0
    sigma0 = prm[29]
    sigma_rel = prm[30]
    fit_sigma_given = prm[31] > 0.0
    min_radius = prm[32]
    max_radius = prm[33]
    max_rw = prm[34]
    max_rms_sigma = prm[35]
    divergence = prm[36]
    use_sil_cfg = prm[37] > 0.0
    range_model = prm[38] > 0.0
    inc = prm[39]
    sigma_from_data = prm[40] > 0.0
    rough_max = prm[41]
    rms_robust = prm[42] > 0.0
    bark = prm[43]
    corners_on = prm[44] > 0.0
    corner_span = int(prm[45])
    corner_depth = prm[46]
    corner_convex = prm[47]
    corner_sigmas = prm[48]
    gap_splits = int(prm[49])
    gap_ratio = prm[50]
    gap_sigmas = prm[51]
    straight_depth_sigmas = prm[52]
    # sigma_from_scan acts only where a sigma is configured (segment_sigma)
    scan_on = prm[53] > 0.0 and fit_sigma_given
    scan_jump = prm[54]
    scan_surface = prm[55]
    # scan_noise_pool: every scan's estimate first, those without one sharing the batch's;
    # scan_noise_batch: those still without one taking every scan's pooled estimate
    batch_min = prm[_BATCH_MIN]
    pool_on = scan_on and (prm[65] > 0.0 or batch_min < math.inf)
    biweight = prm[_BIWEIGHT] > 0.0  # batch_noise_scale="biweight"
    noise_all = (
        _batch_scan_noise(
            ranges,
            fov_in,
            lo,
            hi,
            scan_jump,
            scan_surface,
            prm[65] > 0.0,
            batch_min,
            None,
            biweight,
        )
        if pool_on
        else np.zeros(1)
    )
    # step_split (_fast_step_split), with step_noise_pool every scan's step noise; that pass
    # also gives every scan's own estimate, the scan noise where it is not pooled (own_noise)
    step_on = prm[_STEP] > 0.0
    step_noise = step_on and prm[_STEP_NOISE] > 0.0
    own_noise = np.zeros(s_count)
    step_all = (
        _batch_scan_noise(
            ranges,
            fov_in,
            lo,
            hi,
            scan_jump,
            scan_surface,
            prm[_STEP_POOL] > 0.0,
            prm[_STEP_BATCH_MIN],
            own_noise,
            biweight,
        )
        if step_noise
        else np.zeros(s_count)
    )
    own_on = step_noise and scan_on and not pool_on
    refit_on = prm[56] > 0.0  # refit_pieces with refit_split="corners" (_fast_candidates)
    arcs_on = prm[58] > 0.0  # arc_refit (_fast_arcs)
    arc_replace = prm[61]
    replace_on = arcs_on and arc_replace < math.inf
    # an arc holds fewer returns than its segment and at least this many (_fast_arcs.arc_run)
    arc_least = min_points if prm[62] > 0.0 else min_points_partial
    convex_min = max(min_depth, 0.0)  # segments with a smaller sagitta: cut at corner_depth
    absinc = abs(inc)
    h_sil = divergence / (2.0 * absinc) if absinc > 0.0 else 0.0
    use_sil = use_sil_cfg and 0.0 < h_sil < 0.5
    rms_check = math.isfinite(max_rms_sigma)
    # scratch, reused by every scan
    g0 = np.empty(n)
    grid = np.empty(n)
    bidx = np.empty(n, dtype=np.int64)
    pb = np.empty(n, dtype=np.int64)
    pr = np.empty(n)
    px = np.empty(n)
    py = np.empty(n)
    tmp = np.empty(n)
    keep = np.empty(n, dtype=np.bool_)
    corner = np.empty(n, dtype=np.bool_)
    st = np.empty(n, dtype=np.int64)
    sp = np.empty(n, dtype=np.int64)
    oc0 = np.empty(n, dtype=np.bool_)
    oc1 = np.empty(n, dtype=np.bool_)
    tr0 = np.empty(n, dtype=np.bool_)
    tr1 = np.empty(n, dtype=np.bool_)
    st2 = np.empty(n, dtype=np.int64)
    sp2 = np.empty(n, dtype=np.int64)
    oc02 = np.empty(n, dtype=np.bool_)
    oc12 = np.empty(n, dtype=np.bool_)
    tr02 = np.empty(n, dtype=np.bool_)
    tr12 = np.empty(n, dtype=np.bool_)
    wid = np.empty(n)
    dep = np.empty(n)
    ccode = np.empty(n, dtype=np.int64)
    feat = np.empty(2)
    pres = np.empty((n, OUT_COLUMNS + 2))
    sil = np.empty(4)
    sil_fit = np.empty(4)
    fit_out = np.empty(14)
    buf = np.empty((8, n))
    ws3 = np.empty((6, 3, 3))
    wv = np.empty((8, 3))
    mdl = np.empty(11)
    mdl[10] = prm[_EDGE_WINDOW]  # the edge range window's share (_fit_one leaves it)
    jtj = np.empty((3, 3))
    dnoise = np.empty(n)
    scratch = (sil, sil_fit, fit_out, tmp, buf, jtj, feat)  # _fast_candidates' scratch
    ws = (ws3, wv, mdl)
    # arc_refit: the arc's own fit output (an accepted parent's stays in fit_out), the arc
    # search's work rows, the parameters without the bark allowance (the arc's RMS test)
    scratch_arc = (sil, sil_fit, np.empty(14), tmp, buf, jtj, feat)
    arc_work = np.empty((ARC_WORK_ROWS, max(n, 9)))
    prm_arc = prm.copy()
    prm_arc[43] = 0.0  # bark_roughness
    step_copy = (np.empty(n), np.empty(n), np.empty(n), np.empty(n, dtype=np.int64))
    cap = max(16, 2 * s_count)
    rows = np.empty((cap, OUT_COLUMNS))
    scans = np.empty(cap, dtype=np.int64)
    n_out = 0
    n_cand = 0
    for s in range(s_count):
        # ---- range gate and field-of-view window (preprocess.gate_ranges / fov_window) ----
        for k in range(n):
            v = ranges[s, k]
            g0[k] = v if (v > lo and v < hi and fov_in[k]) else np.nan
        # ---- the scan's own range-noise scale (plausibility.scan_noise, ours) ----
        if pool_on:
            noise_s = noise_all[s]
        elif own_on:  # (the same numbers as _scan_noise: _batch_scan_noise's own)
            noise_s = own_noise[s]
        else:
            noise_s = _scan_noise(g0, scan_jump, scan_surface, dnoise) if scan_on else 0.0
        # ---- three-neighbour median filter (preprocess.median_filter3, Xue 2018 §2.2) ----
        if median and n >= 3:
            grid[0] = g0[0]
            grid[n - 1] = g0[n - 1]
            for k in range(1, n - 1):
                a = g0[k - 1]
                b = g0[k]
                c = g0[k + 1]
                if math.isfinite(a) and math.isfinite(b) and math.isfinite(c):
                    grid[k] = max(min(a, c), min(max(a, c), b))
                else:
                    grid[k] = b
        else:
            grid[:] = g0
        # ---- 360-degree seam (preprocess.seam_shift / roll_beams) ----
        shift = 0
        if wrap:
            gap = -1
            for k in range(n):
                if not math.isfinite(grid[k]):
                    gap = k
                    break
            if gap >= 0:
                shift = gap
            else:
                best = -math.inf
                for k in range(n):
                    jmp = abs(grid[k] - grid[k - 1])  # k = 0: beam N - 1
                    if jmp > best:
                        best = jmp
                        shift = k
            g0[:] = grid
            for k in range(n):
                bidx[k] = (k + shift) % n
                grid[k] = g0[bidx[k]]
        else:
            for k in range(n):
                bidx[k] = k
        # ---- returns (segment.extract_points) ----
        m = 0
        for k in range(n):
            v = grid[k]
            if math.isfinite(v):
                pb[m] = k
                pr[m] = v
                px[m] = v * cosb[bidx[k]]
                py[m] = v * sinb[bidx[k]]
                m += 1
        if m == 0:
            continue
        # ---- segmentation (segment.range_jump_breaks / euclidean_breaks) + build_segments --
        ns = 0
        for i in range(m):
            brk = i == 0
            if not brk:
                gap_b = pb[i] - pb[i - 1]
                brk = gap_b > max_skip + 1
                if not brk:
                    if euclid:
                        d = math.hypot(px[i] - px[i - 1], py[i] - py[i - 1])
                        thr = max_jump
                        if range_factor > 0.0:
                            thr = max_jump + range_factor * min(pr[i], pr[i - 1]) * absinc * float(
                                gap_b
                            )
                        brk = d > thr
                    else:
                        brk = abs(pr[i] - pr[i - 1]) > max_jump
            if brk:
                if ns > 0:
                    sp[ns - 1] = i
                st[ns] = i
                ns += 1
        sp[ns - 1] = m
        last = last_beam
        for j in range(ns):
            b0 = pb[st[j]]
            b1 = pb[sp[j] - 1]
            r0 = pr[st[j]]
            r1 = pr[sp[j] - 1]
            prev_r = grid[max(b0 - 1, 0)]
            next_r = grid[min(b1 + 1, n - 1)]
            oc0[j] = b0 > first_beam and prev_r < r0 - margin
            oc1[j] = b1 < last and next_r < r1 - margin
            tr0[j] = b0 <= first_beam
            tr1[j] = b1 >= last
        # ---- Segments.select(counts >= min_points): compact returns and table ----
        ns, m = _select_min(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns, min_points)
        # ---- single-point curvature (features.point_curvature, Zheng 2012 eq. 3) ----
        if pcur_on and ns > 0:
            for j in range(ns):
                for i in range(st[j], sp[j]):
                    keep[i] = True
                    if st[j] < i < sp[j] - 1:
                        cur = pr[i + 1] - 2.0 * pr[i] + pr[i - 1]
                        keep[i] = not (cur < pcur_min)
            ns, m = _drop(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns)
        # ---- radius median filter (features.radius_median_filter, visual-lidar §2.3) ----
        if rmed_on and ns > 0:
            any_drop = False
            for j in range(ns):
                a = st[j]
                b = sp[j]
                xmin = px[a]
                xmax = px[a]
                ymin = py[a]
                ymax = py[a]
                for i in range(a, b):
                    keep[i] = True
                    xmin = min(xmin, px[i])
                    xmax = max(xmax, px[i])
                    ymin = min(ymin, py[i])
                    ymax = max(ymax, py[i])
                if math.hypot(xmax - xmin, ymax - ymin) > rmed:
                    mx = _median(px, a, b)
                    my = _median(py, a, b)
                    for i in range(a, b):
                        keep[i] = math.hypot(px[i] - mx, py[i] - my) <= rmed
                        any_drop |= not keep[i]
            if any_drop:
                if split:
                    # Segments.cut: new pieces where the keep flag changes; inner ends occluded
                    st, sp, oc0, oc1, tr0, tr1, st2, sp2, oc02, oc12, tr02, tr12, ns = cut_tables(
                        st, sp, oc0, oc1, tr0, tr1, st2, sp2, oc02, oc12, tr02, tr12, keep, ns
                    )
                else:
                    ns, m = _drop(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns)
            ns, m = _select_min(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns, min_points)
        # ---- concave-corner cuts of non-convex segments (detect._corner_cuts, ours) ----
        if corners_on and ns > 0:
            for j in range(ns):  # corner depth threshold per segment (wid is free here)
                a = st[j]
                b = sp[j]
                thr = corner_depth if sagitta(px, py, a, b) < convex_min else corner_convex
                sig = max(sigma0 + sigma_rel * (_seg_sum(pr, a, b) / float(b - a)), noise_s)
                wid[j] = max(thr, corner_sigmas * sig)
        if (
            corners_on
            and ns > 0
            and corner_parity(px, py, st, sp, ns, corner_span, wid, tmp, keep, corner)
        ):
            st, sp, oc0, oc1, tr0, tr1, st2, sp2, oc02, oc12, tr02, tr12, ns = cut_tables(
                st, sp, oc0, oc1, tr0, tr1, st2, sp2, oc02, oc12, tr02, tr12, keep, ns
            )
            for i in range(m):  # the junction return belongs to neither piece
                keep[i] = not corner[i]
            ns, m = _drop(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns)
            ns, m = _select_min(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns, min_points)
        # ---- largest-gap cuts of non-convex segments (segment.split_largest_gap, ours) ----
        for _ in range(gap_splits):
            for j in range(ns):  # least excess of the gap over the median (wid is free here)
                a = st[j]
                b = sp[j]
                sig = max(sigma0 + sigma_rel * (_seg_sum(pr, a, b) / float(b - a)), noise_s)
                wid[j] = gap_sigmas * sig
            if ns == 0 or not gap_cut_flags(
                px, py, st, sp, ns, convex_min, gap_ratio, wid, keep, corner
            ):
                break
            st, sp, oc0, oc1, tr0, tr1, st2, sp2, oc02, oc12, tr02, tr12, ns = cut_tables(
                st, sp, oc0, oc1, tr0, tr1, st2, sp2, oc02, oc12, tr02, tr12, keep, ns
            )
            gap_cut_occlusion(pr, st, sp, oc0, oc1, ns, m, corner, margin)
            ns, m = _select_min(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns, min_points)
        # ---- segment features and filters (detect._filter, features.segment_features) ----
        nk = 0
        for j in range(ns):
            a = st[j]
            b = sp[j]
            i1 = b - 1
            cnt = float(b - a)
            partial = oc0[j] or oc1[j] or tr0[j] or tr1[j]
            cross = px[a] * py[i1] - py[a] * px[i1]
            dot = px[a] * px[i1] + py[a] * py[i1]
            theta = abs(math.atan2(cross, dot))
            hh = math.sin(theta / 2.0)
            ra = pr[a]
            rb = pr[i1]
            width = math.sqrt((ra - rb) * (ra - rb) + 4.0 * ra * rb * hh * hh)
            depth = sagitta(px, py, a, b)  # features.sagitta_depth, Zheng §3.2 criterion 4
            den = width * width / 4.0 + depth * depth
            curv = 2.0 * depth / den if den > 0 else 0.0
            ok = cnt >= min_points
            ok &= (not partial) or cnt >= min_points_partial
            ok &= cnt <= max_points
            ok &= width >= min_width and width <= max_width
            # the first test failed is depth: a candidate for the corner split (refit_corners)
            # and the arc re-fit (arc_refit)
            cut_me = (refit_on or arcs_on) and ok and not depth >= min_depth
            ok &= depth >= min_depth
            ok &= curv >= min_curv and curv <= max_curv
            if ok and reject_straight:
                # line_fit_rms + is_straight (chi-square or ratio test)
                nf = float(b - a)
                mx = _seg_sum(px, a, b) / nf
                my = _seg_sum(py, a, b) / nf
                for i in range(a, b):
                    qx = px[i] - mx
                    tmp[i] = qx * qx
                sxx = _seg_sum(tmp, a, b) / nf
                for i in range(a, b):
                    qy = py[i] - my
                    tmp[i] = qy * qy
                syy = _seg_sum(tmp, a, b) / nf
                for i in range(a, b):
                    tmp[i] = (px[i] - mx) * (py[i] - my)
                sxy = _seg_sum(tmp, a, b) / nf
                tr = sxx + syy
                det = sxx * syy - sxy * sxy
                lam_min = tr / 2.0 - math.sqrt(max(tr * tr / 4.0 - det, 0.0))
                line_rms = math.sqrt(max(lam_min, 0.0))
                sig = max(sigma0 + sigma_rel * (_seg_sum(pr, a, b) / nf), noise_s)
                if straight_chi2:
                    dof = max(nf - 2.0, 1.0)
                    stat = nf * line_rms * line_rms / (sig * sig)
                    straight = stat <= chi2[int(dof)]
                else:
                    excess = math.sqrt(max(line_rms * line_rms - sig * sig, 0.0))
                    straight = excess < straight_ratio * width
                straight &= not (depth > straight_depth_sigmas * sig)
                ok &= not (straight and cnt >= straight_min_points)
            if drop_partial:
                ok &= not partial
            if ok or cut_me:  # Segments.select(keep): the table is compacted in place below
                st[nk] = a
                sp[nk] = b
                oc0[nk] = oc0[j]
                oc1[nk] = oc1[j]
                tr0[nk] = tr0[j]
                tr1[nk] = tr1[j]
                wid[nk] = width
                dep[nk] = depth
                ccode[nk] = 0 if ok else _DEPTH
                n_cand += ok
                nk += 1
        # ---- fit, plausibility, arc and quality (detect.ScanTrunkDetector._run) ----
        for j in range(nk):
            a = st[j]
            b = sp[j]
            if ccode[j] == _DEPTH:  # rejected as not convex: cut without a fit
                n_before = n_out
                if refit_on and has_corners(px, py, pr, a, b, dep[j], noise_s, prm, tmp, corner):
                    rows, scans, n_out = _split_emit(
                        rows, scans, n_out, s, px, py, pr, pb, j, st, sp, oc0, oc1, tr0, tr1,
                        wid, dep, _DEPTH, grid, noise_s, prm, chi2, scratch, ws, corner,
                        (st2, sp2, oc02, oc12, tr02, tr12), pres,
                    )  # fmt: skip
                # its largest consistent arc, unless its corner split gave the trunk
                if arcs_on and n_out == n_before and b - a > arc_least:
                    sig = max(sigma0 + sigma_rel * (_seg_sum(pr, a, b) / (b - a)), noise_s)
                    lo_a, hi_a = arc_run(px, py, pr, a, b, sig, prm, arc_work)
                    if lo_a >= 0 and arc_candidate(
                        px, py, pr, pb, a, b, lo_a, hi_a, (oc0[j], oc1[j], tr0[j], tr1[j]),
                        grid, noise_s, prm_arc, chi2, scratch_arc, ws, pres[0], bark,
                    ):  # fmt: skip
                        rows, scans, n_out = _emit(rows, scans, n_out, s, pres[0])
                continue
            cnt_i = b - a
            mean_r = _seg_sum(pr, a, b) / cnt_i
            sig = max(sigma0 + sigma_rel * mean_r, noise_s)
            if sigma_from_data and fit_sigma_given:  # sigma 0: the fit estimates its scale
                sig = max(sig, min(_range_roughness(pr[a:b]), rough_max * sig))
            sil[:] = np.nan
            if use_sil:
                _edge_prior(grid, pr[a], pb[a], -1, n, wrap, h_sil, margin, sil, 0)
                _edge_prior(grid, pr[b - 1], pb[b - 1], 1, n, wrap, h_sil, margin, sil, 2)
            _edge_default(sil, prm, h_sil, use_sil_cfg, grid, pb[a], pb[b - 1], n, wrap)
            sil_width = wid[j]
            if use_sil:
                beyond = 0.0 if math.isnan(sil[0]) else max(sil[0] - 0.5, 0.0)
                beyond += 0.0 if math.isnan(sil[2]) else max(sil[2] - 0.5, 0.0)
                sil_width = wid[j] + beyond * mean_r * absinc
            if rms_check and not rms_robust:  # (the bound holds for the plain RMS only)
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
                    n_before = n_out
                    if refit_on and has_corners(
                        px, py, pr, a, b, dep[j], noise_s, prm, tmp, corner
                    ):
                        # a fit test failed: which one, _split_parent re-fits to tell
                        rows, scans, n_out = _split_emit(
                            rows, scans, n_out, s, px, py, pr, pb, j, st, sp, oc0, oc1, tr0, tr1,
                            wid, dep, _PREFIT, grid, noise_s, prm, chi2, scratch, ws, corner,
                            (st2, sp2, oc02, oc12, tr02, tr12), pres,
                        )  # fmt: skip
                    if step_on and n_out == n_before:  # which fit test: step_emit re-fits
                        rows, scans, n_out = step_emit(
                            rows, scans, n_out, s, px, py, pr, pb, a, b,
                            (oc0[j], oc1[j], tr0[j], tr1[j]), wid[j], False, grid, noise_s,
                            step_all[s], prm, prm_arc, chi2, scratch_arc, ws, pres, step_copy,
                        )  # fmt: skip
                    continue
            e_start = not (oc0[j] or tr0[j])
            e_end = not (oc1[j] or tr1[j])
            if inc < 0:  # the fit takes the ends in bearing order
                use_lo, use_hi = e_end, e_start
                sil_fit[0] = sil[2]
                sil_fit[1] = sil[3]
                sil_fit[2] = sil[0]
                sil_fit[3] = sil[1]
            else:
                use_lo, use_hi = e_start, e_end
                sil_fit[:] = sil
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
                range_model,
                fit_out,
                buf,
                ws3,
                wv,
                mdl,
                1.0,  # the fit's default stopping thresholds
                True,  # uniform tangent intervals on two-tangent arcs (the fit's default)
            )
            if status != OK:
                continue
            cx = fit_out[0]
            cy = fit_out[1]
            rad = fit_out[2]
            good = rad >= min_radius and rad <= max_radius
            good &= rad <= max_rw * max(sil_width, 1e-9)
            good &= math.hypot(cx, cy) > mean_r
            shaped = good  # the tests before the RMS test passed
            for i in range(a, b):
                res = math.hypot(px[i] - cx, py[i] - cy) - rad
                tmp[i] = res * res
            rms = math.sqrt(_seg_sum(tmp, a, b) / cnt_i)
            if rms_check:
                lim = max_rms_sigma * sig
                if bark > 0.0:  # plausibility.rms_limit
                    lim = max_rms_sigma * math.sqrt(sig * sig + (bark * rad) * (bark * rad))
                if rms_robust:
                    good &= _robust_residual_scale(px[a:b], py[a:b], cx, cy, rad) <= lim
                else:
                    good &= rms <= lim
            if not good:
                n_before = n_out
                if refit_on and has_corners(px, py, pr, a, b, dep[j], noise_s, prm, tmp, corner):
                    # a fit test failed: which one, _split_parent re-fits to tell
                    rows, scans, n_out = _split_emit(
                        rows, scans, n_out, s, px, py, pr, pb, j, st, sp, oc0, oc1, tr0, tr1,
                        wid, dep, _PREFIT, grid, noise_s, prm, chi2, scratch, ws, corner,
                        (st2, sp2, oc02, oc12, tr02, tr12), pres,
                    )  # fmt: skip
                if step_on and shaped and n_out == n_before:  # failed the RMS test
                    rows, scans, n_out = step_emit(
                        rows, scans, n_out, s, px, py, pr, pb, a, b,
                        (oc0[j], oc1[j], tr0[j], tr1[j]), wid[j], True, grid, noise_s,
                        step_all[s], prm, prm_arc, chi2, scratch_arc, ws, pres, step_copy,
                    )  # fmt: skip
                continue
            # arc_replace: an accepted candidate gives way to its arc when its fit RMS exceeds
            # arc_replace x the arc's and the arc's sigma and its residuals fail the upper 1 %
            # chi^2 test at that sigma (detect._arc_candidates), unless its outline goes on past
            # the arc's cut on its own circle (_fast_arcs.continues_outline); that sigma is at
            # least max(sigma, the scan's noise), so below it no arc is looked for
            if replace_on and rms > max(sigma0, noise_s) and cnt_i > arc_least:
                sig_a = max(sigma0 + sigma_rel * mean_r, noise_s)  # (segment_sigma)
                lo_a, hi_a = arc_run(px, py, pr, a, b, sig_a, prm, arc_work)
                if (
                    lo_a >= 0
                    and arc_candidate(
                        px, py, pr, pb, a, b, lo_a, hi_a, (oc0[j], oc1[j], tr0[j], tr1[j]),
                        grid, noise_s, prm_arc, chi2, scratch_arc, ws, pres[0], bark,
                    )
                    and rms > max(arc_replace * pres[0, OUT_COLUMNS + 1], pres[0, OUT_COLUMNS])
                    and cnt_i * rms * rms
                    > chi2[cnt_i - 3] * pres[0, OUT_COLUMNS] * pres[0, OUT_COLUMNS]
                    and not continues_outline(
                        px, py, pr, a, b, a + lo_a, a + hi_a, cx, cy, rad,
                        (pres[0, 0], pres[0, 1], pres[0, 2]), pres[0, OUT_COLUMNS], bark, chi2,
                    )
                ):  # fmt: skip
                    rows, scans, n_out = _emit(rows, scans, n_out, s, pres[0])
                    continue
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
            partial = oc0[j] or oc1[j] or tr0[j] or tr1[j]
            qual = support * math.exp(-(e * e)) * (0.5 if partial else 1.0)
            if n_out == rows.shape[0]:
                rows2 = np.empty((2 * n_out, OUT_COLUMNS))
                rows2[:n_out] = rows
                rows = rows2
                scans2 = np.empty(2 * n_out, dtype=np.int64)
                scans2[:n_out] = scans
                scans = scans2
            row = rows[n_out]
            for q in range(12):
                row[q] = fit_out[q]
            row[12] = (pmax - pmin) * _RAD2DEG
            row[13] = wid[j]
            row[14] = qual
            row[15] = cnt_i
            scans[n_out] = s
            n_out += 1
    return rows[:n_out], scans[:n_out], n_cand


def detect_scans(
    ranges: FloatArray,
    cos_bearing: FloatArray,
    sin_bearing: FloatArray,
    fov_inside: np.ndarray,
    params: FloatArray,
    chi2_table: FloatArray,
) -> tuple[FloatArray, np.ndarray, int]:
    """Run the compiled pipeline on scans ``ranges`` (S, N).

    Parameters
    ----------
    ranges : ndarray of shape (S, N), float64, C-contiguous, metres (NaN/inf = no return)
    cos_bearing, sin_bearing : ndarray of shape (N,) -- ``np.cos`` / ``np.sin`` of the beam
        angles (computed by numpy, so the returns' coordinates equal the reference's)
    fov_inside : ndarray of shape (N,), bool -- beams inside the field of view
    params : ndarray of shape (N_PARAMS,) -- see :data:`PARAM_NAMES`
    chi2_table : ndarray -- upper 1 % chi-square quantiles by degrees of freedom (>= N entries)

    Returns
    -------
    rows : ndarray of shape (D, 16) -- cx, cy, r, cov (9), arc_deg, width, quality, n_points
    scans : ndarray of shape (D,), int -- scan index of each detection
    n_candidates : int -- candidate segments that reached the fit
    """
    rows, scans, n_cand = _detect_kernel(
        ranges, cos_bearing, sin_bearing, fov_inside, params, chi2_table
    )
    return rows, scans, int(n_cand)


# after every kernel is defined, before the first call loads the cache (see the module notes)
_numba_cache.drop_stale_cache(
    _detect_kernel,
    __file__,
    _fit_geometric.__file__,
    features.__file__,
    _corners.__file__,
    _fast_arcs.__file__,
    _fast_candidates.__file__,
    _gaps.__file__,
    _fast_robust.__file__,
    _fast_segments.__file__,
    _fast_step_split.__file__,
    _fit_lm.__file__,
    _kernel_params.__file__,
)
