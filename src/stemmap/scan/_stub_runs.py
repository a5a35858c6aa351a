"""Drop a run of end returns that lies outside the circle of the rest: a branch leaving the
stem's flank over several beams (ours, issue 11, Dec 5, "lidR view by view"; numpy path).

:func:`stemmap.scan._stubs.outward_ends` deletes one end return at a time and judges it
against the circle fitted without it. A branch that leaves the flank over m beams (lidR scan
19: nine returns 16-97 mm outside the stem's ring, joined to the stem's twenty at a 2 mm
step) is never caught that way: with one of them deleted the other m - 1 still pull the
rest's circle, which then fails the chi-square test, and nothing is trimmed. The deletion
unit here is the run: for m = 1, 2, ... up to the candidate's returns less
``max(min_points, min_points_partial)``, the m end returns are deleted together, the rest is
fitted with that end occluded (whether the end is a silhouette is what is asked), and the
run goes at the *smallest* m for which

- the rest's circle passes every fit test and its residuals are the range noise (the upper
  1 % chi-square test of ``arc_chi2``, with the noise the fit weighted by: the measured
  noise of ``fit_noise_floor`` where that is on, else the segment's sigma), and
- every return of the run lies outside that circle by more than ``stub_sigmas`` deletion
  standard deviations ``sqrt(s^2 + g' C g)`` (the scale of
  :func:`~stemmap.scan._stubs.outward_ends`, ``s`` from the same noise).

The smallest m: a larger one would delete the stem's own returns as well once the branch is
gone (they lie on the rest's circle, so the second condition stops the run at the stem). The
rest keeps more than half of the candidate's returns (both runs together too): the deletion
test takes the rest as the stem, and a rest of a branch's few returns judged against 1 cm
passed once and made the stem's twenty the "run" (lidR scan 19 without ``fit_noise_floor``:
-22 cm). Each end is judged on the whole candidate; both ends' runs then go together. The new end is
occluded when the return just beyond it lies in front of the rest's circle (nearer than the
range at which its beam meets the circle: a branch in front hides the stem's silhouette, lidR
scan 19) and a silhouette edge otherwise (the beam missed the stem or met something behind
it). The trimmed candidate is fitted again and keeps the trim only when it passes every
test (the rule of :func:`~stemmap.scan._behind.trim_behind`). First-echo fits only (as
``stub_sigmas``): an averaging scanner's edge return is a mixed pixel outside the circle by
construction.

``stub_runs_snoop`` makes the search data snooping (Baarda 1968: a global test of the model
first, the local tests that locate the outliers only where it fails): a candidate is
searched only when its own circle fails the same upper 1 % chi-square test the rest must
pass (:func:`misfit`), and both tests and the deletion deviations read the noise measured on
the data, not capped by the tests' sigma (:func:`run_noise`). Without it a single-tree scan
with 3 cm of range noise and no estimate of its own was judged against 1 cm: with 8 returns
the smallest run whose rest passed was three of the stem's own (TreeLS pine, 0.5 deg, 3 cm:
-12 cm on one view, the row's RMSE 1.35 -> 6.14 cm). The snooping option also reads a
trimmed end as occluded where the return just beyond it lies nearer than the rest's tangent
range even though its beam misses the circle (a return there never showed that its beam
passed the stem; :func:`_in_front` ``tangent``).

``stub_runs_worst`` snoops one observation at a time first (Baarda 1968): of a candidate that
fails the global test, the return with the largest w-statistic (:func:`worst_return`) is
found; where it is not an end return and the candidate without it passes the global test, the
misfit lies at that return and a run may go only at the end on its side of the arc's middle
(:func:`_inner_worst_side`; the return itself is not removed). Needles in front of a clean
stem inside its arc failed the global test, and the stem's own end returns at the other end
went as the run (TreeLS pine, 0.25 deg, no noise: 1.49 -> 3.04 cm, with the option 1.93;
docs/algorithms/scan-detection.md, "The run test on clean needles").

``stub_runs_inner`` moves the deletion unit inside the arc (:mod:`stemmap.scan._inner_runs`):
where the smallest inner run in front of the rest's circle explains the misfit, that run goes
and no end run does (needles on two inner beams of TreeLS pine's scan 8 at 0.25 deg: the lo
silhouette return went with ``stub_runs_worst``, -1.46 -> -4.11 cm; with the option the
needle return went, -0.50; docs/algorithms/scan-detection.md, "Needles inside the arc").

References: W. Baarda, *A Testing Procedure for Use in Geodetic Networks*, Netherlands
Geodetic Commission, Publications on Geodesy 2(5), 1968.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri

from stemmap.scan._behind import _merge, _take
from stemmap.scan._inner_runs import _aranges, inner_runs
from stemmap.scan._refit import fit_passes
from stemmap.scan._segment_fits import fit_sigma
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted

__all__ = [
    "misfit",
    "outward_runs",
    "passes_global_test",
    "run_noise",
    "runs_outside",
    "trim_runs",
    "worst_return",
]


def _run_mask(segs: Segments, m: NDArray[np.int64], first: bool) -> NDArray[np.bool_]:
    """Per return of ``segs``, whether it is among the ``m`` first (or last) of its segment."""
    p_idx = np.arange(len(segs.points))
    lab = segs.labels
    if first:
        out: NDArray[np.bool_] = p_idx < segs.start[lab] + m[lab]
    else:
        out = p_idx >= segs.stop[lab] - m[lab]
    return out


def _block(m0: int, cost: NDArray[np.int64]) -> int:
    """The end (exclusive) of the next block of run lengths from ``m0``: as many as fit
    in :data:`BLOCK_RETURNS` returns to fit (``cost[i]``: the returns at ``m0 + i``), at
    least one."""
    within = int(np.searchsorted(np.cumsum(cost), BLOCK_RETURNS, side="right"))
    return m0 + max(within, 1)


#: Returns the run searches fit in one call at most: every run length whose rests fit in
#: this many returns is tried together (one vectorised fit instead of one per length; a
#: candidate that found its run at a shorter length is not tried at the longer ones of later
#: blocks). Only memory and speed depend on it, not the result: each rest's fit is the
#: rest's alone (the fit's one batch-wide switch, ``_segment_fits._fit_segments`` passing
#: sigma only when every segment's is positive, is the config's: all are when ``sigma`` or
#: ``sigma_rel`` is; tests/scan/test_run_search_blocks.py).
BLOCK_RETURNS = 1 << 19


def outward_runs(
    detector: ScanTrunkDetector, segs: Segments, grid: FloatArray, wrap: bool
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_], NDArray[np.bool_]]:
    """Per segment of ``segs``: how many returns go at its first / its last end (0: none) and
    whether the new first / last end is occluded (module docstring).

    Every run length m (both ends) is tried at once, in blocks of :data:`BLOCK_RETURNS`
    returns: the rests of all (end, candidate, m) in one fit (each rest's fit is its own: the
    same numbers as one fit per m), then per end and candidate the smallest m that hit."""
    cfg = detector.config
    p = segs.points
    least = max(cfg.min_points, cfg.min_points_partial)
    k = len(segs)
    n_all = segs.counts
    # the rest must hold at least `least` returns and more than half of them: the stem is
    # the majority of its candidate (else a branch's few returns become the reference and
    # the stem the run)
    m_max = np.where(n_all > least, np.minimum(n_all - least, (n_all - 1) // 2), 0)
    m_end = np.zeros((2, k), dtype=np.int64)  # row 0: the first end, row 1: the last
    occ = np.zeros((2, k), dtype=bool)
    open_ = np.ones((2, k), dtype=bool)
    top = int(m_max.max(initial=0))
    m0 = 1
    while m0 <= top:
        ms = np.arange(m0, top + 1)
        live = open_.sum(axis=0)  # ends still searched, per candidate
        cost = np.where(ms[:, None] <= m_max, (n_all - ms[:, None]) * live, 0).sum(axis=1)
        m1 = _block(m0, cost)
        # rows (end, candidate, m), m0 <= m < m1, of the ends still open
        e_open, j_open = np.nonzero(open_ & (m_max >= m0))
        n_m = np.minimum(m_max[j_open], m1 - 1) - m0 + 1
        e = np.repeat(e_open, n_m)
        j = np.repeat(j_open, n_m)
        m = _aranges(n_m) + m0
        m0 = m1
        if e.size == 0:
            continue
        first = e == 0
        keep = n_all[j] - m
        src = segs.start[j] + np.where(first, m, 0)
        stop = np.cumsum(keep).astype(np.int64)
        # the rest: the candidate less its m end returns, with that end occluded
        rest = Segments(
            p.take(np.repeat(src, keep) + _aranges(keep)),
            stop - keep,
            stop,
            segs.scan[j],
            first | segs.occluded_start[j],
            ~first | segs.occluded_end[j],
            segs.truncated_start[j] & ~first,
            segs.truncated_end[j] & first,
        )
        f = detector._fit_candidates(rest, grid, wrap)
        noise = run_noise(cfg, rest, f.sigma)
        n = keep.astype(np.float64)
        limit = chdtri(np.maximum(n - 3.0, 1.0), 0.01)
        with np.errstate(invalid="ignore"):
            good = fit_passes(cfg, f) & (n * f.rms * f.rms <= limit * noise * noise)
        # every return of the run outside the rest's circle by > stub_sigmas deviations
        run0 = np.where(first, segs.start[j], segs.stop[j] - m)
        pts = np.repeat(run0, m) + _aranges(m)
        row = np.repeat(np.arange(e.size), m)
        hit = np.flatnonzero(good & runs_outside(cfg, p.x[pts], p.y[pts], row, f, noise))
        if hit.size == 0:
            continue
        # per end and candidate, the smallest m that hit (rows ascend in m within each)
        key = e[hit] * k + j[hit]
        order = np.lexsort((m[hit], key))
        lead = np.ones(order.size, dtype=bool)
        lead[1:] = key[order][1:] != key[order][:-1]
        best = hit[order[lead]]
        eb, jb, mb = e[best], j[best], m[best]
        m_end[eb, jb] = mb
        open_[eb, jb] = False
        # the return just beyond the new end: in front of the rest's circle -> occluded
        inner = np.where(eb == 0, segs.start[jb] + mb - 1, segs.stop[jb] - mb)
        occ[eb, jb] = _in_front(
            p.x[inner], p.y[inner], f.centers[best], f.radii[best], cfg.stub_runs_snoop
        )
    occ &= m_end > 0
    return m_end[0], m_end[1], occ[0], occ[1]


def runs_outside(
    cfg: DetectorConfig,
    x: FloatArray,
    y: FloatArray,
    row: NDArray[np.int64],
    f: _Fitted,
    noise: FloatArray,
) -> NDArray[np.bool_]:
    """Per fit of ``f``, whether every return ``(x, y)`` of its run (``row``: the fit each
    belongs to) lies outside its circle by more than ``stub_sigmas`` deletion deviations
    ``sqrt(s^2 + (bark_roughness r)^2 + g' C g)`` (``s`` the fit's ``noise``, ``C`` its
    covariance, ``g`` the gradient of ``|p - c| - r`` in ``(cx, cy, r)``: the circle's own
    uncertainty where it is extrapolated to the return)."""
    cx, cy, r = f.centers[row, 0], f.centers[row, 1], f.radii[row]
    dx, dy = x - cx, y - cy
    dist = np.hypot(dx, dy)
    br = cfg.bark_roughness * r
    scale2 = noise[row] ** 2 + br * br
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.stack((-dx / dist, -dy / dist, -np.ones_like(dist)), axis=1)
        pred = np.einsum("ki,kij,kj->k", g, f.covs[row], g)
        out_pt = dist - r > cfg.stub_sigmas * np.sqrt(scale2 + np.maximum(pred, 0.0))
    out = np.ones(len(f.radii), dtype=bool)
    np.logical_and.at(out, row, out_pt)
    return out


def worst_return(segs: Segments, fitted: _Fitted, noise: FloatArray) -> NDArray[np.int64]:
    """Per segment of ``segs``, the position (from its first return) of the return with the
    largest standardised residual to its circle ``fitted``: Baarda's w-statistic
    ``|e| / (s sqrt(q))`` with ``e`` the orthogonal residual, ``s`` the run test's noise
    ``noise`` and ``q = 1 - g' C g / s^2`` the return's redundancy number (``C`` the fit's
    covariance, ``g`` the residual's gradient; floored at 0.05: an end return of a short
    arc holds almost all of its own residual). The observation data snooping points to
    first (``stub_runs_worst``, :func:`_inner_worst_side`)."""
    p = segs.points
    lab = segs.labels
    cx, cy, r = fitted.centers[lab, 0], fitted.centers[lab, 1], fitted.radii[lab]
    dx, dy = p.x - cx, p.y - cy
    dist = np.hypot(dx, dy)
    s2 = noise[lab] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.stack((-dx / dist, -dy / dist, -np.ones_like(dist)), axis=1)
        gcg = np.einsum("ki,kij,kj->k", g, fitted.covs[lab], g)
        q = np.clip(1.0 - gcg / s2, 0.05, 1.0)
        w = np.abs(dist - r) / np.sqrt(s2 * q)
    w = np.where(np.isfinite(w), w, 0.0)
    order = np.lexsort((-w, lab))  # per segment, the largest first
    first = np.concatenate(([0], np.cumsum(segs.counts)[:-1])).astype(np.int64)
    pos: NDArray[np.int64] = order[first] - segs.start
    return pos


def _inner_worst_side(
    detector: ScanTrunkDetector,
    sub: Segments,
    fitted: _Fitted,
    grid: FloatArray,
    wrap: bool,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """``stub_runs_worst``: per candidate of ``sub`` (those that failed the global test, fits
    ``fitted``) whether a run may go at its first / its last end. Where its worst return
    (:func:`worst_return`) is not an end return and the candidate without it passes the
    global test, the misfit lies at that return: a run may go only at the end on its side of
    the arc's middle (an end outlier of a short arc hands its residual on to its neighbour,
    whose w-statistic then is the largest, lidR scan 8; a run at the other end cannot be what
    made the misfit, TreeLS pine scans 8 and 17). Elsewhere both ends."""
    cfg = detector.config
    noise = run_noise(cfg, sub, fitted.sigma)
    pos = worst_return(sub, fitted, noise)
    k = len(sub)
    inner = (pos > 0) & (pos < sub.counts - 1) & (sub.counts - 1 >= 3)
    explained = np.zeros(k, dtype=bool)
    if np.any(inner):
        drop = np.zeros(len(sub.points), dtype=bool)
        drop[(sub.start + pos)[inner]] = True
        less = sub.select(inner).drop(~drop[np.repeat(inner, sub.counts)])
        f = detector._fit_candidates(less, grid, wrap)
        explained[inner] = passes_global_test(less.counts, f.rms, noise[inner])
    twice = 2 * pos
    first_ok = ~explained | (twice <= sub.counts - 1)
    last_ok = ~explained | (twice >= sub.counts - 1)
    return first_ok, last_ok


def run_noise(cfg: DetectorConfig, segs: Segments, sigma: FloatArray) -> FloatArray:
    """The range noise the run test reads for each segment of ``segs``: the noise the fit
    weighted by (``fit_noise_floor``, else the segment's ``sigma``); with
    ``stub_runs_snoop`` never below the noise measured on the data (the scale of
    :func:`~stemmap.scan._segment_fits.fit_sigma` not capped by ``sigma``)."""
    meas = fit_sigma(cfg.fit_noise_floor, segs, sigma, cap=False)
    if meas is None:
        return sigma
    noise: FloatArray = np.minimum(sigma, meas)  # fit_sigma's cap
    if cfg.stub_runs_snoop:
        noise = np.maximum(noise, meas)
    return noise


def passes_global_test(
    counts: NDArray[np.int64], rms: FloatArray, noise: FloatArray
) -> NDArray[np.bool_]:
    """The global test of data snooping: whether each circle fit of ``counts`` returns with
    RMS residual ``rms`` passes the upper 1 % chi-square test (n - 3 degrees of freedom)
    against the range noise ``noise``."""
    n = counts.astype(np.float64)
    limit = chdtri(np.maximum(n - 3.0, 1.0), 0.01)
    with np.errstate(invalid="ignore"):
        ok: NDArray[np.bool_] = n * rms * rms <= limit * noise * noise
    return ok


def misfit(
    cfg: DetectorConfig, segs: Segments, fitted: _Fitted, which: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """``which`` less the candidates whose own fit passes the upper 1 % chi-square test
    against :func:`run_noise` (``stub_runs_snoop``, the global test of data snooping: a
    candidate that a circle already explains within the measured noise has no run to
    look for); ``which`` itself when the option is off."""
    if not cfg.stub_runs_snoop or not np.any(which):
        return which
    noise = run_noise(cfg, segs, fitted.sigma)
    out: NDArray[np.bool_] = which & ~passes_global_test(segs.counts, fitted.rms, noise)
    return out


def _in_front(
    x: FloatArray, y: FloatArray, centers: FloatArray, radii: FloatArray, tangent: bool = False
) -> NDArray:
    """Whether each return (sensor at the origin) lies nearer than the range at which its
    beam first meets its circle; where the beam misses the circle False, or with
    ``tangent`` whether it lies nearer than the circle's tangent range ``sqrt(d^2 - r^2)``
    (a return there may hide the stem's silhouette: its beam never showed that it passed
    the stem)."""
    rho = np.hypot(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux, uy = x / rho, y / rho
        b = centers[:, 0] * ux + centers[:, 1] * uy
        s2 = centers[:, 0] ** 2 + centers[:, 1] ** 2 - b * b
        meets = s2 < radii * radii
        near = b - np.sqrt(np.maximum(radii * radii - s2, 0.0))
    out: NDArray[np.bool_] = meets & (rho < near)
    if tangent:
        with np.errstate(invalid="ignore"):
            q = np.sqrt(np.maximum(centers[:, 0] ** 2 + centers[:, 1] ** 2 - radii * radii, 0.0))
        out |= ~meets & (rho < q)
    return out


def trim_runs(
    detector: ScanTrunkDetector,
    segs: Segments,
    fitted: _Fitted,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> tuple[Segments, _Fitted]:
    """``segs`` without the end runs of the candidates ``which`` that lie outside the circle
    of their rest (:func:`outward_runs`), and the fits of the trimmed candidates; a trimmed
    candidate that fails a test keeps its returns and fit. The same segments in order."""
    which = misfit(detector.config, segs, fitted, which)
    if not np.any(which):
        return segs, fitted
    ids = np.flatnonzero(which)
    sub = segs.select(which)
    m_first, m_last, occ_first, occ_last = outward_runs(detector, sub, grid, wrap)
    if detector.config.stub_runs_worst:
        first_ok, last_ok = _inner_worst_side(detector, sub, _take(fitted, which), grid, wrap)
        m_first = np.where(first_ok, m_first, 0)
        m_last = np.where(last_ok, m_last, 0)
        occ_first &= first_ok
        occ_last &= last_ok
    inner = np.zeros(len(segs.points), dtype=bool)
    cut_inner = np.zeros(len(sub), dtype=bool)
    if detector.config.stub_runs_inner:
        # needles or a twig in front of the bark inside the arc explain the misfit: their
        # run goes, and no end run (the ends are the stem's)
        f_sub = _take(fitted, which)
        i_pos, i_len = inner_runs(
            detector, sub, f_sub, run_noise(detector.config, sub, f_sub.sigma), grid, wrap
        )
        cut_inner = i_len > 0
        m_first = np.where(cut_inner, 0, m_first)
        m_last = np.where(cut_inner, 0, m_last)
        occ_first &= ~cut_inner
        occ_last &= ~cut_inner
        lab = sub.labels
        rel = np.arange(len(sub.points)) - sub.start[lab]
        inner[np.repeat(which, segs.counts)] = (rel >= i_pos[lab]) & (rel < i_pos[lab] + i_len[lab])
    least = max(detector.config.min_points, detector.config.min_points_partial)
    # both ends: keep at least `least` returns and more than half (the first end's run wins)
    rest = sub.counts - m_first - m_last
    m_last = np.where((rest >= least) & (2 * rest > sub.counts), m_last, 0)
    occ_last &= m_last > 0
    cut = (m_first > 0) | (m_last > 0) | cut_inner
    if not np.any(cut):
        return segs, fitted
    k = len(segs)
    mf = np.zeros(k, dtype=np.int64)
    ml = np.zeros(k, dtype=np.int64)
    of = np.zeros(k, dtype=bool)
    ol = np.zeros(k, dtype=bool)
    mf[ids], ml[ids], of[ids], ol[ids] = m_first, m_last, occ_first, occ_last
    drop = _run_mask(segs, mf, True) | _run_mask(segs, ml, False) | inner
    sel = np.zeros(k, dtype=bool)
    sel[ids[cut]] = True
    trimmed = _trimmed_flags(segs.drop(~drop), mf > 0, ml > 0, of, ol)
    refit = detector._fit_candidates(trimmed.select(sel), grid, wrap)
    passed = fit_passes(detector.config, refit)
    if not np.any(passed):
        return segs, fitted
    rows = np.flatnonzero(sel)
    undo = np.zeros(k, dtype=bool)
    undo[rows[~passed]] = True
    drop &= ~undo[segs.labels]
    mf[undo] = 0
    ml[undo] = 0
    out = _trimmed_flags(segs.drop(~drop), mf > 0, ml > 0, of & ~undo, ol & ~undo)
    return out, _merge(fitted, rows[passed], _take(refit, passed))


def _trimmed_flags(
    segs: Segments,
    cut_start: NDArray[np.bool_],
    cut_end: NDArray[np.bool_],
    occ_start: NDArray[np.bool_],
    occ_end: NDArray[np.bool_],
) -> Segments:
    """A trimmed end is occluded where the run hid the stem (``occ_*``), a true silhouette
    edge otherwise; untrimmed ends keep their flags."""
    return Segments(
        segs.points,
        segs.start,
        segs.stop,
        segs.scan,
        np.where(cut_start, occ_start, segs.occluded_start),
        np.where(cut_end, occ_end, segs.occluded_end),
        segs.truncated_start & ~cut_start,
        segs.truncated_end & ~cut_end,
    )
