"""Needles and twigs in front of the bark inside the arc: the run test's inner explanation
(ours, issue 11, Dec 5, "Needles inside the arc"; numpy path, first-echo fits).

A first-echo beam returns from the nearest surface in its footprint. Where needles, a twig or
a leaf hang between the sensor and the bark, the beams that meet them return *in front of*
the stem: outside its circle, on the side facing the sensor. A stem's own return cannot lie
there by more than its bark roughness and the range noise, so an inner return that does is
an occluder, not the stem. The stem's own *end* returns are different: the silhouette return
and a branch root or collar at the end also lie outside the circle (the run test of
:mod:`stemmap.scan._stub_runs` and ``cut_ends`` are about them).

With ``stub_runs_snoop`` a candidate whose circle fails the global chi-square test is
searched for an outward end run; when the misfit comes from needles inside the arc, the
smallest end run whose rest passes is often the stem's own silhouette returns (the rest,
without them and with that end occluded, bends towards the needles). ``stub_runs_worst``
looks for one inner return that explains the misfit; a tuft over two beams is not one return
(TreeLS pine 0.25 deg nearest, no noise, scan 8: needles on beams 888 / 889, the largest
w-statistic on the own return 887 beside them, and the lo silhouette return went: -1.46 ->
-4.11 cm).

:func:`inner_runs` is data snooping with a run of inner returns as the deletion unit (Baarda
1968; the run of :mod:`stemmap.scan._stub_runs`, moved inside): for m = 1, 2, ... (the rest
keeping more than half of the returns and at least ``max(min_points, min_points_partial)``),
every run of m consecutive returns that holds neither end return is deleted in turn and the
rest fitted (its ends as they are); the smallest m for which some run's rest passes every fit
test and the global test (:func:`~stemmap.scan._stub_runs.passes_global_test` against
:func:`~stemmap.scan._stub_runs.run_noise`) and every return of the run lies outside the
rest's circle by more than ``stub_sigmas`` deletion deviations (the scale of
:func:`~stemmap.scan._stub_runs.outward_runs`) explains the misfit; of several such runs,
the one whose rest has the smallest residual sum of squares. The misfit is then in front of
the bark inside the arc: no end run goes (the ends are the stem's; ``stub_runs_inner``), and
the inner run itself is not fitted (the trimmed candidate is fitted again and keeps the cut
only when it passes every test, the rule of :func:`~stemmap.scan._behind.trim_behind`).

References: W. Baarda, *A Testing Procedure for Use in Geodetic Networks*, Netherlands
Geodetic Commission, Publications on Geodesy 2(5), 1968.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan._refit import fit_passes
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted

__all__ = ["inner_runs"]


def _aranges(counts: NDArray[np.int64]) -> NDArray[np.int64]:
    """``0 .. c - 1`` for every ``c`` of ``counts``, concatenated (no per-candidate loop)."""
    counts = np.asarray(counts, dtype=np.int64)
    return np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(
        np.cumsum(counts) - counts, counts
    )


def inner_runs(
    detector: ScanTrunkDetector,
    segs: Segments,
    fitted: _Fitted,
    noise: FloatArray,
    grid: FloatArray,
    wrap: bool,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per candidate of ``segs`` (fits ``fitted``, run-test noise ``noise``): the position
    (from its first return) and the length of the inner run of returns in front of the rest's
    circle that explains its misfit, length 0 where none does (module docstring).

    Every run length is tried at once, in blocks of
    :data:`~stemmap.scan._stub_runs.BLOCK_RETURNS` returns: the rests of all (candidate, m,
    position) in one fit (each rest's fit is its own: the same numbers as one fit per m),
    then per candidate the smallest m that hit."""
    from stemmap.scan._stub_runs import _block, passes_global_test, runs_outside

    cfg = detector.config
    p = segs.points
    k = len(segs)
    least = max(cfg.min_points, cfg.min_points_partial)
    n_all = segs.counts
    pos_out = np.zeros(k, dtype=np.int64)
    len_out = np.zeros(k, dtype=np.int64)
    # room for a run of m between the two end returns, and a rest of the majority
    m_max = np.minimum(np.minimum(n_all - least, (n_all - 1) // 2), n_all - 2)
    m_max = np.where(n_all >= 3, m_max, 0)
    open_ = m_max >= 1
    # a run in front of the rest's circle pulls the candidate's own circle towards itself
    # but not through itself: as a whole it lies outside that circle too (the sum of its
    # residuals is positive); only such runs are tried
    lab = segs.labels
    res = np.hypot(p.x - fitted.centers[lab, 0], p.y - fitted.centers[lab, 1]) - fitted.radii[lab]
    csum = np.concatenate(([0.0], np.cumsum(np.where(np.isfinite(res), res, 0.0))))
    top = int(m_max.max(initial=0))
    m0 = 1
    while m0 <= top:
        # every m of the block m0 <= m < m1 at once (:func:`~stemmap.scan._stub_runs._block`)
        ms = np.arange(m0, top + 1)[:, None]
        cost = np.where(open_ & (ms <= m_max), (n_all - 1 - ms) * n_all, 0).sum(axis=1)
        m1 = _block(m0, cost)
        ids = np.flatnonzero(open_ & (m_max >= m0))
        n_m = np.minimum(m_max[ids], m1 - 1) - m0 + 1
        j_m = np.repeat(ids, n_m)
        m_m = _aranges(n_m) + m0
        m0 = m1
        n_pos = n_all[j_m] - 1 - m_m  # first positions 1 .. n - 1 - m
        cand = np.repeat(j_m, n_pos)
        mm = np.repeat(m_m, n_pos)
        first = _aranges(n_pos) + 1
        at = segs.start[cand] + first
        tried = csum[at + mm] - csum[at] > 0.0
        if not np.any(tried):
            continue
        cand, mm, first = cand[tried], mm[tried], first[tried]
        # the rest of each (candidate, m, run): its returns less the run, as one segment
        keep_counts = n_all[cand] - mm
        rel = _aranges(n_all[cand])
        owner = np.repeat(np.arange(cand.size), n_all[cand])
        in_run = (rel >= first[owner]) & (rel < first[owner] + mm[owner])
        src = segs.start[cand][owner] + rel
        stop = np.cumsum(keep_counts).astype(np.int64)
        rest = Segments(
            p.take(src[~in_run]),
            stop - keep_counts,
            stop,
            segs.scan[cand],
            segs.occluded_start[cand],
            segs.occluded_end[cand],
            segs.truncated_start[cand],
            segs.truncated_end[cand],
        )
        f = detector._fit_candidates(rest, grid, wrap)
        good = fit_passes(cfg, f) & passes_global_test(rest.counts, f.rms, noise[cand])
        # every return of the run outside the rest's circle by > stub_sigmas deviations
        rp = src[in_run]
        hit = good & runs_outside(cfg, p.x[rp], p.y[rp], owner[in_run], f, noise[cand])
        if not np.any(hit):
            continue
        # per candidate the smallest m that hit; of its hits the one whose rest has the
        # smallest sum of squares (ties: the first position)
        h = np.flatnonzero(hit)
        sse = rest.counts[h] * f.rms[h] * f.rms[h]
        order = np.lexsort((first[h], sse, mm[h], cand[h]))
        lead = np.ones(order.size, dtype=bool)
        lead[1:] = cand[h][order][1:] != cand[h][order][:-1]
        best = h[order[lead]]
        pos_out[cand[best]] = first[best]
        len_out[cand[best]] = mm[best]
        open_[cand[best]] = False
    return pos_out, len_out
