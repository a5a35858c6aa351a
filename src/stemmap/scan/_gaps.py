"""Compiled twin of the largest-gap cuts (:func:`stemmap.scan.segment.split_largest_gap`, ours,
issue 11) for the detection kernel (:mod:`stemmap.scan._detect_fast`): the same decisions in
the same arithmetic, on the kernel's segment tables. Its kernels compile in
:func:`stemmap.scan._corners.sagitta`: this module drops its numba cache when that file
changes (:func:`stemmap._numba_cache.drop_stale_cache`, at the end)."""

from __future__ import annotations

import math

import numpy as np

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit, nrt_njit
from stemmap.scan import _corners
from stemmap.scan._corners import sagitta
from stemmap.types import FloatArray

__all__ = ["gap_cut_flags", "gap_cut_occlusion"]


@nrt_njit()
def gap_cut_flags(
    px: FloatArray,
    py: FloatArray,
    st: np.ndarray,
    sp: np.ndarray,
    ns: int,
    convex_min: float,
    ratio: float,
    excess: FloatArray,
    keep: np.ndarray,
    cut: np.ndarray,
) -> bool:  # pragma: no cover - numba
    """Mark (``cut``) the return after the largest gap of every segment with >= 2 returns whose
    sagitta is below ``convex_min`` (first maximum on ties, as ``np.argmax``) if it exceeds
    ``ratio`` x the segment's median gap and the median gap by more than ``excess[j]``, and
    write the
    parity of the cuts so far into ``keep`` (``cut_tables`` splits where it changes). Returns
    whether any segment is cut."""
    par = False
    any_cut = False
    for j in range(ns):
        a = st[j]
        b = sp[j]
        at = -1
        if b - a >= 2 and sagitta(px, py, a, b) < convex_min:
            best = -1.0
            gaps = np.empty(b - 1 - a)
            for i in range(a, b - 1):
                g = math.hypot(px[i + 1] - px[i], py[i + 1] - py[i])
                gaps[i - a] = g
                if g > best:
                    best = g
                    at = i + 1
            gaps.sort()
            h = gaps.shape[0] // 2
            med = gaps[h] if gaps.shape[0] % 2 == 1 else 0.5 * (gaps[h - 1] + gaps[h])
            if not (best > ratio * med and best - med > excess[j]):
                at = -1
        for i in range(a, b):
            cut[i] = i == at
            if cut[i]:
                par = not par
                any_cut = True
            keep[i] = par
    return any_cut


@leaf_njit()
def gap_cut_occlusion(
    pr: FloatArray,
    st: np.ndarray,
    sp: np.ndarray,
    oc0: np.ndarray,
    oc1: np.ndarray,
    ns: int,
    m: int,
    cut: np.ndarray,
    margin: float,
) -> None:  # pragma: no cover - numba
    """After ``cut_tables``: a cut end is occluded only when the return across the cut is
    nearer by more than ``margin`` (``split_largest_gap``; ``cut_tables`` marks every inner
    end occluded)."""
    for j in range(ns):
        a = st[j]
        b = sp[j]
        if cut[a]:
            oc0[j] = pr[a - 1] < pr[a] - margin
        if b < m and cut[b]:
            oc1[j] = pr[b] < pr[b - 1] - margin


# after every kernel is defined, before the first call loads the cache (stemmap._numba_cache)
_numba_cache.drop_stale_cache(gap_cut_flags, __file__, _corners.__file__)
