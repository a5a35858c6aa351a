"""Compiled segment cutting of :mod:`stemmap.scan._detect_fast`: the cut at flag changes
(:meth:`stemmap.scan.segment.Segments.cut`, for the splitting radius median filter and the
corner cuts) and the concave-corner flags (:func:`stemmap.scan.segment.concave_corners`,
ours, issue 11).

Same arithmetic, in the same order, as the numpy reference functions, so that the compiled
detector equals the numpy pipeline bit for bit (tests/scan/test_detect_fast.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit
from stemmap.types import FloatArray

__all__ = [
    "corner_parity",
    "cut_tables",
    "may_have_corner",
    "piece_table",
    "sagitta",
    "segment_corners",
]


@leaf_njit()
def sagitta(px: FloatArray, py: FloatArray, a: int, b: int) -> float:  # pragma: no cover - numba
    """Sagitta depth of returns ``a:b`` towards the sensor (numba twin of
    :func:`stemmap.scan.features.sagitta_depth`, Zheng et al. 2012 §3.2 criterion 4)."""
    i1 = b - 1
    x0 = px[a]
    y0 = py[a]
    dx = px[i1] - x0
    dy = py[i1] - y0
    length = math.hypot(dx, dy)
    safe = length if length > 0 else 1.0
    nx = -dy / safe
    ny = dx / safe
    if (nx * -x0 + ny * -y0) < 0:
        nx = -nx
        ny = -ny
    dmax = -math.inf
    dmin = math.inf
    for i in range(a, b):
        dd = (px[i] - x0) * nx + (py[i] - y0) * ny
        dmax = max(dmax, dd)
        dmin = min(dmin, dd)
    depth = dmax if dmax >= -dmin else dmin
    if not length > 0:
        depth = 0.0
    return depth


@leaf_njit(inline="always")
def _behind_chord(
    px: FloatArray, py: FloatArray, lo: int, i: int, c: int
) -> tuple[float, float, float]:  # pragma: no cover - numba
    """``|c| d`` for return ``i`` and the chord from return ``lo`` to ``c`` (``d``: its
    distance behind the chord, positive on the far side from the sensor at the origin), and
    the chord ``(cx, cy)``."""
    cx = px[c] - px[lo]
    cy = py[c] - py[lo]
    side_p = cx * (py[i] - py[lo]) - cy * (px[i] - px[lo])
    side_o = cy * px[lo] - cx * py[lo]
    return (-side_p if side_o > 0.0 else side_p), cx, cy


@leaf_njit()
def segment_corners(
    px: FloatArray,
    py: FloatArray,
    a: int,
    b: int,
    span: int,
    thr: float,
    d: FloatArray,
    corner: np.ndarray,
) -> int:  # pragma: no cover - numba
    """``corner[i]`` for the returns ``a:b`` of one segment: return ``i`` is a concave corner
    of :func:`~stemmap.scan.segment.concave_corners` deeper than ``thr``. Returns the number
    of corners. ``d`` is scratch."""
    for i in range(a, b):
        d[i] = -math.inf
        if i - span >= a and i + span < b:
            sd, cx, cy = _behind_chord(px, py, i - span, i, i + span)
            length = math.hypot(cx, cy)
            if length > 0.0:
                d[i] = sd / length
            else:
                d[i] = 0.0
    found = 0
    for i in range(a, b):
        prev = d[i - 1] if i > a else -math.inf
        nxt = d[i + 1] if i + 1 < b else -math.inf
        corner[i] = d[i] > thr and d[i] >= prev and d[i] > nxt
        found += corner[i]
    return found


@leaf_njit()
def may_have_corner(
    px: FloatArray, py: FloatArray, a: int, b: int, span: int, thr: float
) -> bool:  # pragma: no cover - numba
    """Whether any return of segment ``a:b`` lies behind the chord of its ``span``-th
    neighbours by more than about ``thr``: the squared test ``s^2 > 0.99 thr^2 |c|^2`` on
    the signed cross product ``s`` of :func:`segment_corners` (``d = s / |c|``), without its
    square root per return. False means no corner of :func:`segment_corners` deeper than
    ``thr`` (the 1 % slack covers the rounding of the exact test); True decides nothing."""
    lim = 0.99 * thr * thr
    for i in range(a + span, b - span):
        sd, cx, cy = _behind_chord(px, py, i - span, i, i + span)
        if sd > 0.0 and sd * sd > lim * (cx * cx + cy * cy):
            return True
    return False


@leaf_njit()
def corner_parity(
    px: FloatArray,
    py: FloatArray,
    st: np.ndarray,
    sp: np.ndarray,
    ns: int,
    span: int,
    thresholds: FloatArray,
    d: FloatArray,
    keep: np.ndarray,
    corner: np.ndarray,
) -> bool:  # pragma: no cover - numba
    """``keep[i]`` = parity of the concave corners up to return ``i`` of its segment (flips at
    every corner of :func:`segment_corners` deeper than the segment's ``thresholds[j]``,
    starts False in every segment; ``_refit.corner_cut_pieces``), ``corner[i]``: return ``i``
    is a corner. Returns whether any corner was found. ``d`` is scratch."""
    found = False
    for j in range(ns):
        a0 = st[j]
        b0 = sp[j]
        found |= segment_corners(px, py, a0, b0, span, thresholds[j], d, corner) > 0
        flag = False
        for i in range(a0, b0):
            if corner[i]:
                flag = not flag
            keep[i] = flag
    return found


@leaf_njit()
def piece_table(
    a: int,
    b: int,
    corner: np.ndarray,
    oc0: bool,
    oc1: bool,
    tr0: bool,
    tr1: bool,
    pst: np.ndarray,
    psp: np.ndarray,
    poc0: np.ndarray,
    poc1: np.ndarray,
    ptr0: np.ndarray,
    ptr1: np.ndarray,
) -> int:  # pragma: no cover - numba
    """The pieces of segment ``a:b`` (occlusion / truncation flags ``oc0, oc1, tr0, tr1``)
    between its ``corner`` returns, which belong to no piece: what
    ``segs.cut(np.cumsum(corner) % 2 == 1).drop(~corner)`` gives
    (``_refit.corner_cut_pieces``), inner ends occluded, the outer ends the segment's. Writes
    the piece table ``pst, psp`` (return ranges) and its flags; returns the number of pieces."""
    k = 0
    start = a
    for i in range(a, b + 1):
        if i < b and not corner[i]:
            continue
        if i > start:  # a non-empty piece start:i
            pst[k] = start
            psp[k] = i
            poc0[k] = oc0 if start == a else True
            ptr0[k] = tr0 and start == a
            poc1[k] = oc1 if i == b else True
            ptr1[k] = tr1 and i == b
            k += 1
        start = i + 1
    return k


@njit(cache=True, error_model="numpy")
def cut_tables(
    st: np.ndarray,
    sp: np.ndarray,
    oc0: np.ndarray,
    oc1: np.ndarray,
    tr0: np.ndarray,
    tr1: np.ndarray,
    st2: np.ndarray,
    sp2: np.ndarray,
    oc02: np.ndarray,
    oc12: np.ndarray,
    tr02: np.ndarray,
    tr12: np.ndarray,
    keep: np.ndarray,
    ns: int,
) -> tuple[
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    int,
]:  # pragma: no cover - numba
    """``Segments.cut(keep)`` into the spare ``*2`` tables: new pieces where ``keep`` changes
    between consecutive returns of a segment, inner ends occluded. Returns the cut table first,
    the old one as the new spare, and the number of pieces."""
    ns2 = 0
    for j in range(ns):
        for i in range(st[j], sp[j]):
            if i == st[j] or keep[i] != keep[i - 1]:
                if i != st[j]:
                    sp2[ns2 - 1] = i
                st2[ns2] = i
                first = i == st[j]
                oc02[ns2] = oc0[j] if first else True
                tr02[ns2] = first and tr0[j]
                oc12[ns2] = True
                tr12[ns2] = False
                ns2 += 1
        sp2[ns2 - 1] = sp[j]
        oc12[ns2 - 1] = oc1[j]
        tr12[ns2 - 1] = tr1[j]
    return st2, sp2, oc02, oc12, tr02, tr12, st, sp, oc0, oc1, tr0, tr1, ns2


# after every kernel is defined, before the first call loads the cache: no other module's
# kernels are compiled in here, but the compile flags (stemmap._leaf_jit) are
_numba_cache.drop_stale_cache(sagitta, __file__)
