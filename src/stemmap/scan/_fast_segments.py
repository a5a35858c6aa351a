"""Segment-table and per-segment helpers of the compiled detector
(:mod:`stemmap.scan._detect_fast`): numpy's pairwise summation (so per-segment sums equal
``np.add.reduceat`` bit for bit), the in-place ``Segments.select`` / ``Segments.drop`` of the
kernel's segment table, the algebraic (Kasa) cost floor of the pre-fit reject and the
covariance fallback of a singular fit Hessian. Kept free of other modules' kernels: numba's
cache of this file depends on this file alone."""

from __future__ import annotations

import math

import numpy as np

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit, nrt_njit
from stemmap.types import FloatArray


@leaf_njit()
def _pairwise(a: FloatArray, lo: int, n: int) -> float:  # pragma: no cover - numba
    """numpy's pairwise summation of ``a[lo:lo + n]`` (``DOUBLE_pairwise_sum``: blocks of 128,
    eight accumulators), so the sums below equal ``np.add.reduceat`` bit for bit."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    if n <= 128:
        r0 = a[lo]
        r1 = a[lo + 1]
        r2 = a[lo + 2]
        r3 = a[lo + 3]
        r4 = a[lo + 4]
        r5 = a[lo + 5]
        r6 = a[lo + 6]
        r7 = a[lo + 7]
        i = 8
        end = n - n % 8
        while i < end:
            j = lo + i
            r0 += a[j]
            r1 += a[j + 1]
            r2 += a[j + 2]
            r3 += a[j + 3]
            r4 += a[j + 4]
            r5 += a[j + 5]
            r6 += a[j + 6]
            r7 += a[j + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += a[lo + i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(a, lo, n2) + _pairwise(a, lo + n2, n - n2)


@leaf_njit()
def _seg_sum(a: FloatArray, start: int, stop: int) -> float:  # pragma: no cover - numba
    """``np.add.reduceat(a, starts)`` for one segment: the first value plus the pairwise sum of
    the rest (numpy's reduction order)."""
    return a[start] + _pairwise(a, start + 1, stop - start - 1)


@leaf_njit()
def _algebraic_floor(px: FloatArray, py: FloatArray, a: int, b: int) -> float:  # pragma: no cover
    """Minimum over all circles of the Kasa (algebraic) cost ``sum (|p - c|^2 - r^2)^2`` of the
    points ``a..b-1`` (a linear least-squares problem in (2c, r^2 - |c|^2), solved in centred
    coordinates; the residuals are summed explicitly). 0.0 when the points are collinear (no
    useful bound)."""
    nf = float(b - a)
    mx = 0.0
    my = 0.0
    for i in range(a, b):
        mx += px[i]
        my += py[i]
    mx /= nf
    my /= nf
    zm = 0.0
    for i in range(a, b):
        zm += (px[i] - mx) ** 2 + (py[i] - my) ** 2
    zm /= nf
    suu = 0.0
    svv = 0.0
    suv = 0.0
    suz = 0.0
    svz = 0.0
    for i in range(a, b):
        u = px[i] - mx
        v = py[i] - my
        z = u * u + v * v - zm
        suu += u * u
        svv += v * v
        suv += u * v
        suz += u * z
        svz += v * z
    det = suu * svv - suv * suv
    if not det > 1e-12 * (suu + svv) ** 2:
        return 0.0
    ca = (svv * suz - suv * svz) / det
    cb = (suu * svz - suv * suz) / det
    res = 0.0
    for i in range(a, b):
        u = px[i] - mx
        v = py[i] - my
        e = u * u + v * v - zm - ca * u - cb * v
        res += e * e
    return res


@leaf_njit()
def _select_min(
    st: np.ndarray,
    sp: np.ndarray,
    oc0: np.ndarray,
    oc1: np.ndarray,
    tr0: np.ndarray,
    tr1: np.ndarray,
    pb: np.ndarray,
    pr: FloatArray,
    px: FloatArray,
    py: FloatArray,
    keep: np.ndarray,
    ns: int,
    min_points: float,
) -> tuple[int, int]:  # pragma: no cover - numba
    """``Segments.select(counts >= min_points)`` in place: (segments, returns) left."""
    for j in range(ns):
        big = sp[j] - st[j] >= min_points
        for i in range(st[j], sp[j]):
            keep[i] = big
    return _drop(st, sp, oc0, oc1, tr0, tr1, pb, pr, px, py, keep, ns)


@leaf_njit()
def _drop(
    st: np.ndarray,
    sp: np.ndarray,
    oc0: np.ndarray,
    oc1: np.ndarray,
    tr0: np.ndarray,
    tr1: np.ndarray,
    pb: np.ndarray,
    pr: FloatArray,
    px: FloatArray,
    py: FloatArray,
    keep: np.ndarray,
    ns: int,
) -> tuple[int, int]:  # pragma: no cover - numba
    """``Segments.drop(keep)`` in place: returns not kept removed, emptied segments gone."""
    nk = 0
    w = 0
    for j in range(ns):
        start = w
        for i in range(st[j], sp[j]):
            if keep[i]:
                pb[w] = pb[i]
                pr[w] = pr[i]
                px[w] = px[i]
                py[w] = py[i]
                w += 1
        if w == start:
            continue
        st[nk] = start
        sp[nk] = w
        oc0[nk] = oc0[j]
        oc1[nk] = oc1[j]
        tr0[nk] = tr0[j]
        tr1[nk] = tr1[j]
        nk += 1
    return nk, w


@nrt_njit()
def _geometric_cov(
    px: FloatArray,
    py: FloatArray,
    a: int,
    b: int,
    cx: float,
    cy: float,
    rad: float,
    sig: float,
    tmp: FloatArray,
    jtj: FloatArray,
    out: FloatArray,
) -> None:  # pragma: no cover - numba
    """``detect._geometric_cov`` for one segment, written to ``out[3:12]`` (NaN if singular).
    Only reached when the fit's Hessian was singular (rare); numba's LAPACK may differ from
    numpy's in the last bits here."""
    nf = float(b - a)
    for i in range(a, b):
        dx = px[i] - cx
        dy = py[i] - cy
        d = math.hypot(dx, dy)
        res = d - rad
        tmp[i] = res * res
    rss = _seg_sum(tmp, a, b)
    s2 = max(sig * sig, rss / max(nf - 3.0, 1.0) if nf > 3.0 else 0.0)
    for u, v in ((0, 0), (1, 1), (0, 1), (0, 2), (1, 2)):
        for i in range(a, b):
            dx = px[i] - cx
            dy = py[i] - cy
            d = math.hypot(dx, dy)
            ds = d if d > 0 else 1.0
            e = (dx / ds, dy / ds, 1.0)
            tmp[i] = e[u] * e[v]
        jtj[u, v] = _seg_sum(tmp, a, b)
        jtj[v, u] = jtj[u, v]
    jtj[2, 2] = nf
    det = np.linalg.det(jtj)
    if math.isfinite(det) and abs(det) > 1e-12 * max(nf, 1.0) ** 3:
        inv = np.linalg.inv(jtj)
        for u in range(3):
            for v in range(3):
                out[3 + 3 * u + v] = inv[u, v] * s2
    else:
        for q in range(9):
            out[3 + q] = np.nan


# after every kernel is defined, before the first call loads the cache: no other module's
# kernels are compiled in here, but the compile flags (stemmap._leaf_jit) are
_numba_cache.drop_stale_cache(_pairwise, __file__)
