"""The step split of ``step_split``, compiled (ours, issue 11): the numba twin of
:func:`stemmap.scan._step_split.step_refit` for one candidate inside the detector kernel
(:mod:`stemmap.scan._detect_fast`).

A candidate that fails the RMS test (and whose corner split gave no trunk) is read at its
largest absolute range step (:func:`largest_step`); a step within ``3 sqrt(2)`` noise sigmas
(the segment's sigma, with ``step_noise_pool`` at least the scan's pooled step noise) is noise.
A step that isolates a one-return spike towards the sensor drops that return and the rest is
judged whole; any other step cuts the candidate into two pieces, their cut ends occluded only
by a nearer return across the cut (``_arcs._cut_flags``). Every piece is judged as an arc of
``arc_refit`` (:func:`~stemmap.scan._fast_arcs.arc_verdict`: segment filters, fit,
the fit tests without the bark allowance, :func:`~stemmap.scan._fast_arcs.arc_consistent`),
validated as the corner split's pieces (``_refit.validate_pieces``: the one passing piece, no
circle-like sibling failing; no return of the candidate 3 sigma inside its circle) and vetoed
when a return of the candidate was seen through its circle (``_split_search.seen_through``).
The same expressions in the same order as the numpy functions, so both paths agree bit for bit
(tests/scan/test_detect_fast.py, tests/scan/test_detect_fast_real.py). ``step_twigs`` (every
dip dropped) stays numpy-only: ``ScanTrunkDetector._compiled`` refuses it.

numba's cache of this module is dropped when a file whose kernels it compiles in changes
(:func:`stemmap._numba_cache.drop_stale_cache`, as for ``_detect_fast``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stemmap import _numba_cache
from stemmap._leaf_jit import leaf_njit
from stemmap.scan import (
    _corners,
    _fast_arcs,
    _fast_candidates,
    _fast_robust,
    _fast_segments,
    _fit_geometric,
    _fit_lm,
    _kernel_params,
    features,
)
from stemmap.scan._fast_arcs import arc_verdict
from stemmap.scan._fast_candidates import (
    _RMS,
    _emit,
    _fit_candidate,
    _Scratch,
    _Work,
)
from stemmap.scan._fast_segments import _seg_sum
from stemmap.scan._kernel_params import OUT_COLUMNS
from stemmap.types import FloatArray

__all__ = ["largest_step", "step_emit", "step_limit"]

#: Noise sigmas of the step and of the seen-through test (``_step_split._SIGMAS``,
#: ``_split_search._SIGMAS``).
_SIGMAS = 3.0


@leaf_njit()
def step_limit(
    pr: FloatArray, a: int, b: int, noise_s: float, step_s: float, prm: FloatArray
) -> float:  # pragma: no cover - numba
    """The noise step of candidate ``a:b``: ``3 sqrt(2)`` times its range-noise sigma
    (``plausibility.segment_sigma``; ``noise_s`` the scan's own estimate, 0 where the config
    reads none), at least ``step_s`` (``step_noise_pool``: the scan's pooled step noise, 0 when
    off; ``np.fmax``)."""
    sig = max(prm[29] + prm[30] * (_seg_sum(pr, a, b) / float(b - a)), noise_s)
    if math.isnan(sig) or step_s > sig:
        sig = step_s if not math.isnan(step_s) else sig
    return _SIGMAS * math.sqrt(2.0) * sig


@leaf_njit()
def largest_step(
    pr: FloatArray, a: int, b: int, limit: float
) -> tuple[int, int]:  # pragma: no cover - numba
    """(first, spike) of candidate ``a:b`` (:func:`stemmap.scan._step_split.largest_steps`,
    :func:`~stemmap.scan._step_split.front_spikes`): ``first`` the return after its largest
    absolute range step (the first of ties), -1 for none or a step within ``limit``;
    ``spike`` one of the step's two returns nearer than both its neighbours by more than
    ``limit``, else -1."""
    if b - a < 2:
        return -1, -1
    best = -1.0
    f = -1
    for i in range(a, b - 1):
        d = abs(pr[i + 1] - pr[i])
        if d > best:
            best = d
            f = i + 1
    if abs(pr[f] - pr[f - 1]) <= limit:
        return -1, -1
    spike = -1
    for i in (f - 1, f):
        if a < i < b - 1 and min(pr[i - 1], pr[i + 1]) - pr[i] > limit:
            spike = i
    return f, spike


@leaf_njit()
def _seen_through(
    px: FloatArray, py: FloatArray, pr: FloatArray, a: int, b: int, res: FloatArray
) -> bool:  # pragma: no cover - numba
    """Whether a return of the candidate ``a:b`` was seen through the circle of the piece
    row ``res`` (``_split_search.seen_through``, ``k`` 3) or lies 3 sigma inside it
    (``_refit._returns_inside``)."""
    cx = res[0]
    cy = res[1]
    rad = res[2]
    sig = res[OUT_COLUMNS]
    lim = rad - 3.0 * sig
    for i in range(a, b):
        if math.hypot(px[i] - cx, py[i] - cy) < lim:
            return True
    k = _SIGMAS
    inner = rad - k * sig
    for i in range(a, b):
        r = pr[i]
        ux = px[i] / r
        uy = py[i] / r
        along = cx * ux + cy * uy
        perp2 = (cx * cx + cy * cy) - along * along
        hit = (inner > 0) and (perp2 < inner * inner) and (along > 0)
        entry = along - math.sqrt(max(rad * rad - perp2, 0.0))
        if hit and r > entry + k * sig:
            return True
    return False


@njit(cache=True, error_model="numpy")
def step_emit(
    rows: FloatArray,
    scans: np.ndarray,
    n_out: int,
    s: int,
    px: FloatArray,
    py: FloatArray,
    pr: FloatArray,
    pb: np.ndarray,
    a: int,
    b: int,
    flags: tuple[bool, bool, bool, bool],
    width: float,
    rms_known: bool,
    grid: FloatArray,
    noise_s: float,
    step_s: float,
    prm: FloatArray,
    prm_arc: FloatArray,
    chi2: FloatArray,
    scratch: _Scratch,
    ws: _Work,
    pres: FloatArray,
    copy: tuple[FloatArray, FloatArray, FloatArray, np.ndarray],
) -> tuple[FloatArray, np.ndarray, int]:  # pragma: no cover - numba
    """``step_split`` of the rejected candidate ``a:b`` of scan ``s`` (end ``flags``: occluded
    start / end, truncated start / end; chord ``width``) whose corner split gave no trunk
    (module docstring). ``rms_known``: it failed the RMS test; False: the pre-fit bound
    rejected it, and an exact fit (after the step is found) tells whether the test it fails
    is the RMS test (run last, where a piece passed). The accepted piece (at most one) is
    appended to ``rows, scans``."""
    limit = step_limit(pr, a, b, noise_s, step_s, prm)
    f, spike = largest_step(pr, a, b, limit)
    if f < 0:
        return rows, scans, n_out
    bark = prm[43]
    n_pass = 0
    got = -1
    if spike >= 0:
        # the spike dropped (Segments.drop: the flags unchanged), the rest judged whole
        cx, cy, cr, cb = copy
        m = 0
        for i in range(a, b):
            if i != spike:
                cx[m] = px[i]
                cy[m] = py[i]
                cr[m] = pr[i]
                cb[m] = pb[i]
                m += 1
        v = arc_verdict(
            cx, cy, cr, cb, 0, m, 0, m, flags, grid, noise_s, prm_arc, chi2, scratch, ws, pres[0],
            bark,
        )  # fmt: skip
        if v == 1:
            got = 0
    else:
        # cut at the step, each piece judged as an arc (arc_verdict: a cut end occluded only
        # by a nearer return across it, as _arcs._cut_flags)
        for q in range(2):
            lo, hi = (0, f - a) if q == 0 else (f - a, b - a)
            v = arc_verdict(
                px, py, pr, pb, a, b, lo, hi, flags, grid, noise_s, prm_arc, chi2, scratch, ws,
                pres[q], bark,
            )  # fmt: skip
            if v == 1:
                n_pass += 1
                got = q
            elif v == 0:  # a circle-like piece fails: the candidate keeps its verdict
                return rows, scans, n_out
    if got < 0 or n_pass > 1:  # validate_pieces
        return rows, scans, n_out
    if _seen_through(px, py, pr, a, b, pres[got]):
        return rows, scans, n_out
    if not rms_known:
        # the pre-fit bound rejected the candidate: an exact fit tells whether the test it
        # fails is the RMS test (last: the pieces reject most candidates more cheaply; the
        # other piece's row is free)
        sil, sil_fit, fit_out, tmp, buf, jtj, _ = scratch
        ws3, wv, mdl = ws
        code = _fit_candidate(
            px, py, pr, pb, a, b, flags[0], flags[1], flags[2], flags[3], width, grid, noise_s,
            prm, True, sil, sil_fit, fit_out, tmp, buf, jtj, ws3, wv, mdl, pres[1 - got],
        )  # fmt: skip
        if code != _RMS:
            return rows, scans, n_out
    return _emit(rows, scans, n_out, s, pres[got])


# after every kernel is defined, before the first call loads the cache (see the module notes)
_numba_cache.drop_stale_cache(
    step_emit,
    __file__,
    _fast_arcs.__file__,
    _fast_candidates.__file__,
    _fit_geometric.__file__,
    features.__file__,
    _corners.__file__,
    _fast_robust.__file__,
    _fast_segments.__file__,
    _fit_lm.__file__,
    _kernel_params.__file__,
)
