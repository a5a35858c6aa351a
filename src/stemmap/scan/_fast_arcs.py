"""The largest consistent arc of a candidate segment, compiled (ours, issue 11): the arc search
of ``arc_refit`` shared by both detector paths, and the compiled path's arc candidate.

:func:`largest_arc` grows a circle from every short convex seed window of a segment's returns,
adding the neighbouring return (the side with the smaller residual) while its residual to the
circle so far is within ``max(k x 1.4826 MAD, floor)`` of the arc's residuals, re-fitting
Kasa's (1976) algebraic circle from running sums after each addition; the largest run wins
(ties: the smaller residual RMS). :func:`arc_run` adds the conditions under which that run is
a candidate of its own (scan-detection-history.md, "Fourth round" and "Fifth round"). The numpy
pipeline (:func:`stemmap.scan._arcs.consensus_arcs`) and the compiled kernel
(:mod:`stemmap.scan._detect_fast`) call the same two functions, so the arcs they find are the
same run of returns; :func:`arc_candidate` then judges that run in the kernel as
:func:`stemmap.scan._arcs.arc_pieces` does with numpy (cut-end flags, segment filters, fit and
plausibility tests without the bark allowance), through the same per-candidate blocks as the
corner split (:mod:`stemmap.scan._fast_candidates`).

numba's cache of this module is dropped when a file whose kernels it compiles in changes
(:func:`stemmap._numba_cache.drop_stale_cache`, as for ``_detect_fast``).
"""

from __future__ import annotations

import math

import numpy as np

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit
from stemmap.scan import (
    _corners,
    _fast_candidates,
    _fast_robust,
    _fast_segments,
    _fit_geometric,
    _fit_lm,
    _kernel_params,
    features,
)
from stemmap.scan._fast_candidates import _fit_candidate, _Scratch, _segment_code, _Work
from stemmap.scan._fast_robust import _median_inplace
from stemmap.scan._kernel_params import OUT_COLUMNS
from stemmap.types import FloatArray

__all__ = [
    "ARC_WORK_ROWS",
    "FRONT_SIGMAS",
    "MAX_SEEDS",
    "MIN_SHARE",
    "arc_candidate",
    "arc_consistent",
    "arc_run",
    "continues_outline",
    "largest_arc",
]

#: At most this many seed windows per segment (evenly spaced): bounds the cost of long segments.
MAX_SEEDS = 24
#: An arc must hold at least this share of its segment's returns: a trunk that runs on into a
#: branch fills a third or more of the segment (lidR at 0.25-1 deg: 26 of 78 returns at 1.3 m,
#: 5-8 of 11-20 at 5-9 m); a 2 cm bark ridge or stub at the end of a 150-return trunk does not
#: (aRchi at 2 m, 0.25 deg: 6 of ~150 returns fitted as a 5 cm stem inside the 55 cm trunk).
MIN_SHARE = 0.25
#: :func:`continues_outline`: a return across the arc's cut this many noise sigmas (with the
#: bark allowance) in front of the arc circle's tangent range continues the outline (the
#: scale of ``arc_tangent_sigmas``' default, 3).
FRONT_SIGMAS = 3.0
#: Rows of the work array of :func:`largest_arc`: per return 9 Kasa terms and 2 buffers, then
#: the 3 x 4 elimination tableau and two running-sum rows (work shape: (ARC_WORK_ROWS,
#: max(N, 9)) for segments of up to N returns).
ARC_WORK_ROWS = 16
_MAD = 1.4826


@leaf_njit()
def _kasa(s: FloatArray, m: FloatArray) -> tuple[bool, float, float, float]:  # pragma: no cover
    """Kasa circle from the running sums ``s`` = (n, Sx, Sy, Sxx, Syy, Sxy, Sz, Sxz, Syz) with
    z = x^2 + y^2 (local coordinates): the normal equations solved by Gaussian elimination
    with partial pivoting in the 3 x 4 tableau ``m``; (False, ...) when a pivot is zero or the
    squared radius is not positive and finite."""
    m[0, 0] = s[3]
    m[0, 1] = s[5]
    m[0, 2] = s[1]
    m[0, 3] = s[7]
    m[1, 0] = s[5]
    m[1, 1] = s[4]
    m[1, 2] = s[2]
    m[1, 3] = s[8]
    m[2, 0] = s[1]
    m[2, 1] = s[2]
    m[2, 2] = s[0]
    m[2, 3] = s[6]
    for c in range(3):
        p = c
        for i in range(c + 1, 3):
            if abs(m[i, c]) > abs(m[p, c]):
                p = i
        if m[p, c] == 0.0:
            return False, 0.0, 0.0, 0.0
        if p != c:
            for q in range(c, 4):
                tq = m[c, q]
                m[c, q] = m[p, q]
                m[p, q] = tq
        for i in range(c + 1, 3):
            f = m[i, c] / m[c, c]
            for q in range(c, 4):
                m[i, q] -= f * m[c, q]
    w = m[2, 3] / m[2, 2]
    v = (m[1, 3] - m[1, 2] * w) / m[1, 1]
    u = (m[0, 3] - m[0, 1] * v - m[0, 2] * w) / m[0, 0]
    cx = 0.5 * u
    cy = 0.5 * v
    r2 = w + cx * cx + cy * cy
    if not (r2 > 0.0 and math.isfinite(r2)):
        return False, 0.0, 0.0, 0.0
    return True, cx, cy, math.sqrt(r2)


@leaf_njit()
def largest_arc(
    px: FloatArray,
    py: FloatArray,
    a: int,
    b: int,
    floor: float,
    k: float,
    seed: int,
    r_min: float,
    r_max: float,
    ends_only: bool,
    work: FloatArray,
) -> tuple[int, int]:  # pragma: no cover - numba
    """The largest run ``[lo, hi)`` (relative to ``a``) of the consecutive returns ``a:b``
    (sensor frame, origin = sensor) that one circle explains: grown from every
    ``seed``-return window (at most :data:`MAX_SEEDS`, evenly spaced) whose Kasa circle has a
    radius in [r_min, r_max] and lies beyond the returns (convex towards the sensor); a
    neighbour joins when its residual is within ``max(k x 1.4826 MAD, floor)`` of the arc's
    current circle, the side with the smaller residual first (the start side on a tie).
    ``ends_only``: only arcs that reach the first or the last return count (a trunk whose
    segment runs on into a branch or stem on one side; a run in the middle of a long segment
    is far more often a piece of a bush or wall that happens to be round -- on the
    simulator's clutter, 178 of 179 passing arcs were). ``work``: scratch of shape
    (:data:`ARC_WORK_ROWS`, >= max(b - a, 9)). (-1, -1) when no seed window qualifies."""
    n = b - a
    if n < seed:
        return -1, -1
    t = work[:9]  # per return: 1, x, y, xx, yy, xy, z, xz, yz (local coordinates)
    e = work[9]
    d = work[10]
    m = work[11:14, :4]
    s = work[14]
    s2 = work[15]
    ox = 0.0
    oy = 0.0
    for i in range(n):
        ox += px[a + i]
        oy += py[a + i]
    ox /= n
    oy /= n
    for i in range(n):
        lx = px[a + i] - ox
        ly = py[a + i] - oy
        z = lx * lx + ly * ly
        t[0, i] = 1.0
        t[1, i] = lx
        t[2, i] = ly
        t[3, i] = lx * lx
        t[4, i] = ly * ly
        t[5, i] = lx * ly
        t[6, i] = z
        t[7, i] = lx * z
        t[8, i] = ly * z
    n_start = n - seed + 1
    step = 1 if n_start <= MAX_SEEDS else -(-n_start // MAX_SEEDS)
    best_n = -1
    best_rms = math.inf
    best_lo = -1
    best_hi = -1
    for a0 in range(0, n_start, step):
        lo = a0
        hi = a0 + seed
        for q in range(9):
            acc = 0.0
            for i in range(lo, hi):
                acc += t[q, i]
            s[q] = acc
        ok, cx, cy, r = _kasa(s, m)
        if not ok or not (r_min <= r <= r_max):
            continue
        mx = 0.0
        my = 0.0
        for i in range(lo, hi):
            mx += t[1, i]
            my += t[2, i]
        mx /= hi - lo
        my /= hi - lo
        if math.hypot(cx + ox, cy + oy) <= math.hypot(mx + ox, my + oy):
            continue  # centre not beyond the returns: concave towards the sensor
        while True:
            cnt = hi - lo
            for i in range(lo, hi):
                ei = math.hypot(t[1, i] - cx, t[2, i] - cy) - r
                e[i - lo] = ei
                d[i - lo] = ei
            med = _median_inplace(d, cnt)
            for i in range(cnt):
                d[i] = abs(e[i] - med)
            tol = max(k * _MAD * _median_inplace(d, cnt), floor)
            pick = -1
            e_pick = math.inf
            if lo > 0:
                ei = abs(math.hypot(t[1, lo - 1] - cx, t[2, lo - 1] - cy) - r)
                if ei <= tol:
                    pick = lo - 1
                    e_pick = ei
            if hi < n:
                ei = abs(math.hypot(t[1, hi] - cx, t[2, hi] - cy) - r)
                if ei <= tol and ei < e_pick:
                    pick = hi
            if pick < 0:
                break
            for q in range(9):
                s2[q] = s[q] + t[q, pick]
            ok, cx2, cy2, r2 = _kasa(s2, m)
            if not ok or not (r_min <= r2 <= r_max):
                break
            for q in range(9):
                s[q] = s2[q]
            cx = cx2
            cy = cy2
            r = r2
            if pick < lo:
                lo = pick
            else:
                hi = pick + 1
        if ends_only and lo > 0 and hi < n:
            continue  # not at an end: a trunk runs on into a branch on one side
        cnt = hi - lo
        ss = 0.0
        for i in range(cnt):  # e holds the residuals of the final arc
            ss += e[i] * e[i]
        rms = math.sqrt(ss / cnt)
        if cnt > best_n or (cnt == best_n and rms < best_rms):
            best_n = cnt
            best_rms = rms
            best_lo = lo
            best_hi = hi
    return best_lo, best_hi


@leaf_njit()
def arc_run(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    a: int,
    b: int,
    sigma: float,
    prm: FloatArray,
    work: FloatArray,
) -> tuple[int, int]:  # pragma: no cover - numba
    """The arc of ``arc_refit`` in the segment of returns ``a:b`` with range noise ``sigma``
    (:func:`stemmap.scan._arcs.consensus_arcs`): :func:`largest_arc` with seed
    ``max(min_points, 4)``, ``arc_sigmas``, floor ``arc_floor_sigmas`` x ``sigma`` (the
    noise only, not the bark allowance: a fillet leaves the circle gradually), radii of the
    config; kept when it holds at least ``min_points_partial`` returns (with
    ``arc_short_steps``: ``min_points`` when a range step larger than ``max_jump`` sets it off
    at every cut end) and :data:`MIN_SHARE` of the segment's, and not all of them. ``prm``:
    the kernel's parameter vector (:data:`stemmap.scan._kernel_params.PARAM_NAMES`). Returns
    ``[lo, hi)`` relative to ``a``, (-1, -1) for none."""
    min_points = prm[16]
    mpp = prm[17]
    seed = max(int(min_points), 4)
    least = min_points if prm[62] > 0.0 else mpp  # arc_short_steps
    if not b - a > least:  # no room for an arc of >= least returns, fewer than the segment's
        return -1, -1
    floor = prm[60] * sigma  # arc_floor_sigmas
    lo, hi = largest_arc(px, py, a, b, floor, prm[59], seed, prm[32], prm[33], True, work)
    if lo < 0:
        return -1, -1
    n = b - a
    got = hi - lo
    if not (max(least, MIN_SHARE * n) <= got and got < n):
        return -1, -1
    if got >= mpp:
        return lo, hi
    # a short arc counts only where a range step sets it off at every cut end
    step = math.inf
    if lo > 0:
        step = min(step, abs(pr[a + lo - 1] - pr[a + lo]))
    if hi < n:
        step = min(step, abs(pr[a + hi] - pr[a + hi - 1]))
    if step < math.inf and step > prm[7]:  # max_jump
        return lo, hi
    return -1, -1


@leaf_njit()
def arc_verdict(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    pb: np.ndarray,
    a: int,
    b: int,
    lo: int,
    hi: int,
    flags: tuple[bool, bool, bool, bool],
    grid: FloatArray,
    noise_s: float,
    prm: FloatArray,
    chi2: FloatArray,
    scratch: _Scratch,
    ws: _Work,
    res: FloatArray,
    bark: float,
) -> int:  # pragma: no cover - numba
    """``arc_refit`` for the candidate ``a:b`` with end flags ``flags`` (occluded start / end,
    truncated start / end) and its arc ``[lo, hi)`` (:func:`arc_run`, relative to ``a``), as
    :func:`stemmap.scan._arcs.arc_pieces` judges it: its cut ends occluded only where the
    return across is nearer by more than ``occlusion_margin``, the segment filters, the fit
    and its plausibility tests. ``prm`` must carry ``bark_roughness`` 0 (the arc's RMS test
    has no bark allowance), then :func:`arc_consistent` (``bark``: the config's
    ``bark_roughness``). 1 when the arc passes (``res[:OUT_COLUMNS]`` is its output row,
    then its sigma and its fit RMS), 0 when it is circle-like (passes the segment filters)
    but fails the fit or its tests, -1 when it fails the segment filters (the three verdicts
    of ``_arcs.piece_passes``, which the step split's validation reads)."""
    sil, sil_fit, fit_out, tmp, buf, jtj, feat = scratch
    ws3, wv, mdl = ws
    margin = prm[10]
    oc0, oc1, tr0, tr1 = flags
    qa = a + lo
    qb = a + hi
    if qa > a:  # a cut end: occluded only by a nearer return across it
        oc0 = pr[qa - 1] < pr[qa] - margin
        tr0 = False
    if qb < b:
        oc1 = pr[qb] < pr[qb - 1] - margin
        tr1 = False
    partial = oc0 or oc1 or tr0 or tr1
    if _segment_code(px, py, pr, tmp, qa, qb, partial, prm, chi2, noise_s, feat) != 0:
        return -1
    w = feat[0]
    code = _fit_candidate(
        px, py, pr, pb, qa, qb, oc0, oc1, tr0, tr1, w, grid, noise_s, prm, False,
        sil, sil_fit, fit_out, tmp, buf, jtj, ws3, wv, mdl, res,
    )  # fmt: skip
    if code != 0:
        return 0
    ok = arc_consistent(
        pr, qa, qb, res[0], res[1], res[2], res[OUT_COLUMNS], res[OUT_COLUMNS + 1], bark, prm, chi2
    )
    return 1 if ok else 0


@leaf_njit()
def arc_candidate(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    pb: np.ndarray,
    a: int,
    b: int,
    lo: int,
    hi: int,
    flags: tuple[bool, bool, bool, bool],
    grid: FloatArray,
    noise_s: float,
    prm: FloatArray,
    chi2: FloatArray,
    scratch: _Scratch,
    ws: _Work,
    res: FloatArray,
    bark: float,
) -> bool:  # pragma: no cover - numba
    """Whether the arc ``[lo, hi)`` of the candidate ``a:b`` passes (:func:`arc_verdict` 1)."""
    v = arc_verdict(
        px, py, pr, pb, a, b, lo, hi, flags, grid, noise_s, prm, chi2, scratch, ws, res, bark
    )
    return v == 1


@leaf_njit()
def arc_consistent(
    pr: FloatArray,
    qa: int,
    qb: int,
    cx: float,
    cy: float,
    r: float,
    sig: float,
    rms: float,
    bark: float,
    prm: FloatArray,
    chi2: FloatArray,
) -> bool:  # pragma: no cover - numba
    """The fifteenth round's tests of an arc ``qa:qb`` (ranges ``pr``) whose fit gave the
    circle (``cx``, ``cy``, ``r``; sensor frame), sigma ``sig`` and RMS ``rms``
    (:func:`stemmap.scan._arcs.arc_tests` is the same on numpy arrays):
    ``arc_chi2``: ``n x rms^2 <= chi2_0.99(n - 3) x sig^2`` (``chi2``: the kernel's upper 1 %
    table by degrees of freedom); ``arc_tangent_sigmas`` k: no return farther than the
    tangent range ``sqrt(cx^2 + cy^2 - r^2)`` by more than ``k sqrt(sig^2 + (bark r)^2)``
    (``bark``: the config's ``bark_roughness``; a circle around the sensor fails)."""
    n = qb - qa
    if prm[64] > 0.0 and n > 3 and n * rms * rms > chi2[n - 3] * sig * sig:  # arc_chi2
        return False
    k = prm[63]  # arc_tangent_sigmas
    if k < math.inf:
        d2 = cx * cx + cy * cy - r * r
        if not d2 > 0.0:
            return False
        far = pr[qa]
        for i in range(qa + 1, qb):
            if pr[i] > far:
                far = pr[i]
        br = bark * r
        if far - math.sqrt(d2) > k * math.sqrt(sig * sig + br * br):
            return False
    return True


@leaf_njit()
def continues_outline(
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    a: int,
    b: int,
    qa: int,
    qb: int,
    cx: float,
    cy: float,
    rad: float,
    arc_c: tuple[float, float, float],
    sig: float,
    bark: float,
    chi2: FloatArray,
) -> bool:  # pragma: no cover - numba
    """Whether an accepted candidate ``a:b`` (returns ``px, py, pr``, sensor frame; its fit
    the circle ``cx, cy, rad``) keeps its returns against its arc ``qa:qb`` (absolute
    indices; the arc's circle ``arc_c`` = (x, y, r), its range noise ``sig``) that
    ``arc_replace`` would put in its place (issue 11, Dec 5: benchmark seed 6, scan 188).
    True when both hold:

    * a return across a cut end of the arc lies nearer than the arc circle's tangent range
      ``sqrt(|c|^2 - r^2)`` by more than :data:`FRONT_SIGMAS` x ``sqrt(sig^2 + (bark r)^2)``
      (``arc_tangent_sigmas``' scale): were the arc the whole trunk, the surface across the
      cut would stand in front of its silhouette edge; the outline goes on towards the
      sensor, as a larger convex surface's does;
    * the candidate's circle explains each part within the range noise: the arc's returns
      (sum of squared orthogonal residuals ``<= chi2_0.99(m) x sig^2``, m returns) and the
      returns the arc leaves out (``<= chi2_0.99(n - m) x sig^2``): a fit pulled by a stub or
      fillet misses the part it is pulled from or the part that pulls it, so when it misses
      neither, its chi-square excess is the noise spread over both parts.

    ``chi2``: the kernel's upper 1 % table by degrees of freedom. The numpy pipeline
    (:func:`stemmap.scan._pieces.arc_candidates`) calls this same function."""
    ax, ay, ar = arc_c
    d2 = ax * ax + ay * ay - ar * ar
    if not d2 > 0.0:
        return False
    tangent = math.sqrt(d2)
    br = bark * ar
    lim = FRONT_SIGMAS * math.sqrt(sig * sig + br * br)
    front = False
    if qa > a and tangent - pr[qa - 1] > lim:
        front = True
    if qb < b and tangent - pr[qb] > lim:
        front = True
    if not front:
        return False
    s_arc = 0.0
    s_out = 0.0
    for i in range(a, b):
        e = math.hypot(px[i] - cx, py[i] - cy) - rad
        if qa <= i < qb:
            s_arc += e * e
        else:
            s_out += e * e
    s2 = sig * sig
    return s_arc <= chi2[qb - qa] * s2 and s_out <= chi2[(b - a) - (qb - qa)] * s2


# after every kernel is defined, before the first call loads the cache (see the module notes)
_numba_cache.drop_stale_cache(
    arc_candidate,
    __file__,
    _fast_candidates.__file__,
    _fit_geometric.__file__,
    features.__file__,
    _corners.__file__,
    _fast_robust.__file__,
    _fast_segments.__file__,
    _fit_lm.__file__,
    _kernel_params.__file__,
)
