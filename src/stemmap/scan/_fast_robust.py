"""Robust scales of the compiled detector (:mod:`stemmap.scan._detect_fast`): medians,
the range roughness of a segment, the scan's own range-noise estimate and the robust residual
scale of a fit. Each is the numba twin of a numpy function of :mod:`stemmap.scan.plausibility`
or :mod:`stemmap.scan.features` with the same arithmetic (tests/scan/test_plausibility.py,
tests/scan/test_detect_fast.py). Kept free of other modules' kernels: numba's cache of this
file depends on this file alone."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit, nrt_njit
from stemmap.types import FloatArray

#: 1.4826 MAD -> sigma for a Gaussian, / sqrt(6): the std of a second difference of iid noise
#: (plausibility.range_roughness; the same constant on both paths)
_ROUGH = 1.4826 / math.sqrt(6.0)


@nrt_njit()
def _range_roughness(r: FloatArray) -> float:
    """Robust range-noise + bark-roughness scale of consecutive returns (numba twin of
    :func:`stemmap.scan.plausibility.range_roughness`, same arithmetic)."""
    m = r.shape[0] - 2
    if m < 1:
        return 0.0
    d = np.empty(m)
    for i in range(m):
        d[i] = abs(r[i] - 2.0 * r[i + 1] + r[i + 2])
    d.sort()
    h = m // 2
    med = d[h] if m % 2 == 1 else 0.5 * (d[h - 1] + d[h])
    return _ROUGH * med


@leaf_njit()
def _median_inplace(d: FloatArray, m: int) -> float:  # pragma: no cover - numba
    """Median of ``d[:m]`` (mean of the two middle values for even ``m``, as ``np.median``)
    by quickselect (Hoare partition) in place: no allocation, ``d[:m]`` is reordered."""
    k = m // 2
    lo = 0
    hi = m - 1
    while lo < hi:
        pivot = d[(lo + hi) // 2]
        i = lo
        j = hi
        while i <= j:
            while d[i] < pivot:
                i += 1
            while d[j] > pivot:
                j -= 1
            if i <= j:
                t = d[i]
                d[i] = d[j]
                d[j] = t
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    upper = d[k]
    if m % 2 == 1:
        return upper
    lower = d[0]  # every value left of k is <= d[k] now: the lower middle is their largest
    for i in range(1, k):
        lower = max(lower, d[i])
    return 0.5 * (lower + upper)


#: plausibility.SCAN_NOISE_MIN_TRIPLES (the same value on both paths)
_SCAN_NOISE_MIN_TRIPLES = 16


@leaf_njit()
def _interior_triples(g: FloatArray, jump: float, d: FloatArray) -> tuple[int, int]:
    """Second differences of the interior continuous beam triples of ``g`` (``n >= 4`` beams),
    written to ``d[:m]`` in beam order; returns ``m`` and the longest run of consecutive ones.

    One branch-free pass over the range steps ``g[k] - g[k-1]``: a step is continuous when
    ``|g[k] - g[k-1]| <= jump``, false for NaN and, ``jump`` being finite, for any infinite
    return (so all returns of a counted triple are finite, as the reference checks); ``run``
    counts the continuous steps ending at beam ``k``. The triple centred at ``k - 2`` is
    continuous with both neighbouring triples (interior, the reference's ``ok``) exactly when
    the four steps ``k-3 .. k`` are, i.e. ``run >= 4``; a run of ``L`` continuous steps holds
    ``L - 3`` consecutive interior triples. Every second difference is written and the count
    advances only for interior ones: nothing to mispredict (the branching loop this replaced
    cost ~0.8 us per 361-beam scan, this one ~0.3; scan-detection-history.md, eighth round). Kept
    apart from :func:`_scan_noise`'s medians: compiled into one function, this loop ran at the
    old speed."""
    n = g.shape[0]
    last_bad = 0  # last beam whose step from the previous beam is not continuous (0: none)
    for k in range(1, 4):
        if not abs(g[k] - g[k - 1]) <= jump:
            last_bad = k
    m = 0
    longest = 0
    for k in range(4, n):
        cont = abs(g[k] - g[k - 1]) <= jump
        last_bad = last_bad if cont else k
        run = k - last_bad
        d[m] = g[k - 3] - 2.0 * g[k - 2] + g[k - 1]
        m += run >= 4
        longest = max(longest, run)
    return m, max(longest - 3, 0)


#: The largest finite float: ``jump`` is clamped to it, so an infinite ``jump`` (every finite
#: step continuous, as in the reference) still rejects infinite returns.
_FLOAT_MAX = float(np.finfo(np.float64).max)


@leaf_njit()
def _scan_noise(g: FloatArray, jump: float, surface: float, d: FloatArray) -> float:
    """Range-noise scale of one gated scan ``g`` from its interior continuous beam triples
    (numba twin of :func:`stemmap.scan.plausibility.scan_noise`, same statistic and
    arithmetic, bit for bit; ``d`` is scratch of at least ``g.shape[0]`` values; the triples
    from :func:`_interior_triples`)."""
    if g.shape[0] < 5:  # no interior triple
        return 0.0
    m, longest = _interior_triples(g, min(jump, _FLOAT_MAX), d)
    if m < _SCAN_NOISE_MIN_TRIPLES or 2 * longest > m:  # one surface must not decide
        return 0.0
    return _mad_scale(d, m, surface)


@njit(cache=True, error_model="numpy")
def _batch_scan_noise(
    ranges: FloatArray,
    fov_in: np.ndarray,
    lo: float,
    hi: float,
    jump: float,
    surface: float,
    pool: bool = True,
    batch_min: float = math.inf,
    own: FloatArray | None = None,
    biweight: bool = False,
) -> FloatArray:  # pragma: no cover - numba
    """Every scan's range-noise scale with the scans that have too few interior triples for
    an estimate of their own sharing one from the union of their triples (``pool``), and the
    scans still without one taking the estimate over every scan's triples where it is at least
    ``batch_min`` (numba twin of :func:`stemmap.scan.plausibility.scan_noise` with ``pool`` and
    ``batch_min``; scans gated to ``(lo, hi)`` and the field of view as the detector kernel
    gates them; the same arithmetic). ``own`` (shape (S,)), if given, receives every scan's own
    estimate before any pooling (0 where it has none): :func:`_scan_noise` of the scan, the
    same numbers, so the detector kernel reads its scan noise there instead of estimating it
    twice when the step split pools its own. ``biweight``: the estimate over every scan's
    triples is :func:`_biweight_scale`'s (``batch_noise_scale="biweight"``)."""
    s_count, n = ranges.shape
    out = np.zeros(s_count)
    if own is not None:
        own[:] = 0.0
    g = np.empty(n)
    d = np.empty(n)
    pool_v = np.empty(s_count * n)
    every = np.empty(s_count * n) if batch_min < math.inf else np.empty(0)
    lacking = np.zeros(s_count, dtype=np.bool_)
    unset = np.ones(s_count, dtype=np.bool_)
    pool_m = 0
    pool_longest = 0
    every_m = 0
    every_longest = 0
    jmp = min(jump, _FLOAT_MAX)
    for s in range(s_count):
        for k in range(n):
            v = ranges[s, k]
            g[k] = v if (v > lo and v < hi and fov_in[k]) else np.nan
        if n < 5:  # no interior triple
            continue
        m, longest = _interior_triples(g, jmp, d)
        if batch_min < math.inf:
            every[every_m : every_m + m] = d[:m]
            every_m += m
            every_longest = max(every_longest, longest)
        if m >= _SCAN_NOISE_MIN_TRIPLES and 2 * longest <= m:
            out[s] = _mad_scale(d, m, surface)
            unset[s] = False
            if own is not None:
                own[s] = out[s]
        elif pool and m < _SCAN_NOISE_MIN_TRIPLES:
            lacking[s] = True
            pool_v[pool_m : pool_m + m] = d[:m]
            pool_m += m
            pool_longest = max(pool_longest, longest)
    if pool_m >= _SCAN_NOISE_MIN_TRIPLES and 2 * pool_longest <= pool_m:
        e = _mad_scale(pool_v, pool_m, surface)
        for s in range(s_count):
            if lacking[s]:
                out[s] = e
                unset[s] = False
    if every_m >= _SCAN_NOISE_MIN_TRIPLES and 2 * every_longest <= every_m:
        e = (
            _biweight_scale(every, every_m, surface)
            if biweight
            else _mad_scale(every, every_m, surface)
        )
        if e >= batch_min:
            for s in range(s_count):
                if unset[s]:
                    out[s] = e
    return out


@leaf_njit()
def _mad_scale(d: FloatArray, m: int, surface: float) -> float:  # pragma: no cover - numba
    """``sqrt(max((1.4826 MAD / sqrt(6))^2 - surface^2, 0))`` of ``d[:m]`` (reordered)."""
    med = _median_inplace(d, m)
    for i in range(m):
        d[i] = abs(d[i] - med)
    e = _ROUGH * _median_inplace(d, m)
    return math.sqrt(max(e * e - surface * surface, 0.0))


#: plausibility.BIWEIGHT_C / BIWEIGHT_GAUSS (the same values on both paths)
_BIWEIGHT_C = 6.0
_BIWEIGHT_GAUSS = 1.0462


@nrt_njit()
def _biweight_scale(v: FloatArray, m: int, surface: float) -> float:  # pragma: no cover - numba
    """``sqrt(max((s_bi / sqrt(6))^2 - surface^2, 0))`` of ``v[:m]`` (left as it is), ``s_bi``
    the Gaussian-consistent biweight midvariance scale (numba twin of
    :func:`stemmap.scan.plausibility.biweight_scale`; its sums run over ``v`` in order, as the
    reference's ``np.cumsum``: the same value bit for bit)."""
    w = v[:m].copy()
    med = _median_inplace(w, m)
    for i in range(m):
        w[i] = abs(v[i] - med)
    s = _median_inplace(w, m)
    if not s > 0.0:
        return 0.0
    num = 0.0
    den = 0.0
    cs = _BIWEIGHT_C * s
    for i in range(m):
        u = (v[i] - med) / cs
        if abs(u) < 1.0:
            d = v[i] - med
            uu = u * u
            t = 1.0 - uu
            t2 = t * t
            num += d * d * (t2 * t2)
            den += t * (1.0 - 5.0 * uu)
    den = abs(den)
    if not den > 0.0:
        return 0.0
    e = math.sqrt(m * num) / den / _BIWEIGHT_GAUSS / math.sqrt(6.0)
    return math.sqrt(max(e * e - surface * surface, 0.0))


@nrt_njit()
def _robust_residual_scale(x: FloatArray, y: FloatArray, cx: float, cy: float, r: float) -> float:
    """1.4826 x the median absolute orthogonal residual (numba twin of
    :func:`stemmap.scan.plausibility.robust_residual_scale`, same arithmetic)."""
    m = x.shape[0]
    d = np.empty(m)
    for i in range(m):
        d[i] = abs(math.hypot(x[i] - cx, y[i] - cy) - r)
    d.sort()
    h = m // 2
    med = d[h] if m % 2 == 1 else 0.5 * (d[h - 1] + d[h])
    return 1.4826 * med


@nrt_njit()
def _median(v: FloatArray, start: int, stop: int) -> float:  # pragma: no cover - numba
    """Median of ``v[start:stop]`` (mean of the two middle values for even counts), as
    :func:`stemmap.scan.features._segment_median`."""
    s = np.sort(v[start:stop])
    c = stop - start
    return 0.5 * (s[(c - 1) // 2] + s[c // 2])


@njit(cache=True, error_model="numpy")
def segment_step_medians(
    r: FloatArray, start: np.ndarray, stop: np.ndarray
) -> FloatArray:  # pragma: no cover - numba
    """Per segment ``r[start[k]:stop[k]]``, the median absolute range step between its
    adjacent returns (0 for fewer than two returns): the step scale of
    :func:`stemmap.scan._segment_fits.fit_sigma`, which the first-echo run searches read for
    thousands of trial rests per call (a selection per segment in one scratch buffer instead of
    one ``lexsort`` of all of them; a median selects, so the value is the same to the bit)."""
    k = start.shape[0]
    out = np.zeros(k)
    longest = 0
    for j in range(k):
        longest = max(longest, stop[j] - start[j] - 1)
    d = np.empty(max(longest, 1))  # one scratch for every segment
    for j in range(k):
        a = start[j]
        c = stop[j] - a - 1
        if c < 1:
            continue
        for i in range(c):
            d[i] = abs(r[a + i + 1] - r[a + i])
        out[j] = _median_inplace(d, c)
    return out


# after every kernel is defined, before the first call loads the cache: no other module's
# kernels are compiled in here, but the compile flags (stemmap._leaf_jit) are
_numba_cache.drop_stale_cache(_range_roughness, __file__)
