"""Step split: a candidate that fails the RMS test cut at its largest range step (ours, issue
11, seventeenth round).

A stem seen with 4-5 returns whose segment runs on into a branch *behind* its silhouette edge
(the TreeLS plot, scans 6 and 8 of the sixteenth round: steps of +6.8 and +9.0 cm, below
``max_jump`` 0.1 m and far below the range-adaptive threshold) is one candidate that fails the
RMS test. The validated corner split finds no concave corner there (the range rises across the
join), the arcs of ``arc_refit`` are sought in candidates rejected as not convex only, and a
piece of ``split_search`` counts as occluded at its cut, so a 4-return stem needs
``min_points_partial`` (5) returns there.

On one circle the range changes smoothly from beam to beam; the boundary between two objects in
one segment is the largest range discontinuity. This cuts each candidate at its largest
absolute range step, when that step exceeds what the range noise alone gives (``3 sqrt(2)``
sigmas of the segment: the difference of two returns' noise; on a scan with 3 cm noise the
largest step of a smooth trunk is noise), and judges the two pieces as the arcs of
``arc_refit`` are judged: segment filters with a cut end occluded only when the return across
it is nearer by more than ``occlusion_margin`` (:func:`~stemmap.scan._arcs._cut_flags`, the
rule of ``build_segments``: a branch behind the stem does not make the stem partial), the
detector's fit, the RMS test without the bark allowance, the tangent-range and chi-square tests
(:func:`~stemmap.scan._arcs.piece_passes`), accepted only together
(:func:`~stemmap.scan._refit.judge_pieces` with validation) and only when no return of the
candidate was seen through the piece's circle
(:func:`~stemmap.scan._split_search.seen_through`).

A step may instead isolate one return *in front*: nearer than both its neighbours by more than
the noise step (:func:`front_spikes`; the TreeLS plot, scan 1: a twig 5.7 cm in front of a
4-return stem, between its 2nd and 3rd returns). A solid surface seen from outside makes no
such dip; the return is an occluder, and the candidate is judged whole without it (same tests)
instead of being cut. The compiled path runs the same rule
(:mod:`stemmap.scan._fast_step_split`; both paths' detections agree, tests/scan/
test_detect_fast.py).

With ``step_twigs`` (Dec 5) *every* such dip of the candidate is dropped (:func:`front_dips`),
not only the one at its largest step, and a segment end nearer than its one neighbour counts
when no nearer return lies beyond the end: a stem seen through twigs on several of its beams
(meant for the TreeLS plot's held-out miss "twigs in front on several beams", which turned out
to be a run of three returns and a dip within the noise step in a ``depth`` reject: no real row
changes, and on the simulator it accepts a few more clutter pieces; docs/algorithms/
scan-detection.md, "Twigs on several beams"). A dip this drops needs the same evidence as the
spike: a range below both neighbours by more than the noise step. The remaining returns are
judged whole with the same tests. Numpy path only (the detector takes the numpy path).

With ``step_noise_pool`` (Dec 4) the noise sigma of the threshold is at least the batch's
pooled estimate where a scan has no estimate of its own (``ScanPoints.step_noise``): on a
single-tree scan the configured 1 cm stood for 3 cm noise, and a noise step was cut.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan._arcs import _cut_flags
from stemmap.scan._refit import Refitted
from stemmap.scan._split_search import judge_arcs
from stemmap.scan.features import segment_sum
from stemmap.scan.plausibility import segment_sigma
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["front_dips", "front_spikes", "largest_steps", "step_refit"]

#: Noise sigmas of the step (as the seen-through test's): a cut needs a step larger than this
#: many sigmas of the difference of two returns' noise (sqrt(2) sigma).
_SIGMAS = 3.0


def largest_steps(segs: Segments) -> NDArray[np.int64]:
    """Per segment of ``segs``, the index (into ``segs.points``) of the first return after its
    largest absolute range step between consecutive returns; -1 for a segment of fewer than
    two returns. Ties: the first."""
    r = segs.points.r
    out = np.full(len(segs), -1, dtype=np.int64)
    if len(r) < 2:
        return out
    step = np.abs(np.diff(r))
    # no step across a segment boundary
    inner = np.ones(len(r) - 1, dtype=bool)
    inner[segs.start[segs.start > 0] - 1] = False
    step = np.where(inner, step, -1.0)
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        if b - a >= 2:
            out[j] = a + 1 + int(np.argmax(step[a : b - 1]))
    return out


def front_spikes(segs: Segments, first: NDArray[np.int64], limit: FloatArray) -> NDArray[np.bool_]:
    """Per return of ``segs``, whether it is a one-return spike towards the sensor at a
    segment's largest step: one of the two returns of the step (``first`` - 1 or ``first``,
    indices into ``segs.points``, one per segment in ``segs`` order or -1) that has a neighbour
    of its segment on either side, both farther by more than ``limit`` (metres, per segment).
    A solid surface seen from outside gives no such dip: it is something in front of it (a
    twig before a stem)."""
    r = segs.points.r
    lab = segs.labels
    out = np.zeros(len(r), dtype=bool)
    for f in first[first >= 0]:
        j = lab[f]
        for i in (f - 1, f):
            if segs.start[j] < i < segs.stop[j] - 1:
                out[i] |= bool(min(r[i - 1], r[i + 1]) - r[i] > limit[j])
    return out


def front_dips(segs: Segments, limit: FloatArray) -> NDArray[np.bool_]:
    """Per return of ``segs``, whether it is a one-return dip towards the sensor: nearer than
    both its neighbours in its segment by more than ``limit`` (metres, per segment); a first
    or last return nearer than its one neighbour by more than ``limit`` when its end is neither
    occluded (no nearer return across it) nor truncated (not the field of view's edge). A
    solid surface seen from outside has no such dip: the returns of a convex outline rise
    from its nearest point outwards (``step_twigs``: every twig in front of a stem)."""
    r = segs.points.r
    lab = segs.labels
    n = len(r)
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    lim = limit[lab]
    d = np.diff(r)  # r[i + 1] - r[i]
    inf = np.full(1, np.inf)
    # the rise to the next / from the previous return within the segment (+inf beyond an end
    # that shows nothing nearer)
    nxt = np.concatenate([d, inf])
    prv = np.concatenate([inf, -d])
    last = segs.stop - 1
    nxt[last] = np.where(segs.occluded_end | segs.truncated_end, -np.inf, np.inf)
    prv[segs.start] = np.where(segs.occluded_start | segs.truncated_start, -np.inf, np.inf)
    out = (np.minimum(nxt, prv) > lim) & (segs.counts[lab] >= 2)
    return np.asarray(out, dtype=bool)


def step_refit(
    detector: ScanTrunkDetector,
    every: Segments,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> list[Refitted]:
    """``step_split``: the candidates of ``every`` (before footprint correction) flagged by
    ``which`` whose largest range step (:func:`largest_steps`) exceeds the noise (``3
    sqrt(2)`` sigmas): a candidate whose step isolates a return in front
    (:func:`front_spikes`) judged whole without it, every other one cut at the step into two
    pieces judged as arcs (module docstring). ``parent`` of each result indexes ``every``;
    empty when nothing was judged."""
    cfg = detector.config
    if not np.any(which):
        return []
    sub = every.select(which)
    r = sub.points.r
    lab = sub.labels
    sigma = segment_sigma(cfg, sub, segment_sum(r, sub) / sub.counts)
    if sub.points.step_noise is not None:
        # step_noise_pool: a scan without its own noise estimate reads the batch's pooled one
        sigma = np.fmax(sigma, sub.points.step_noise[sub.scan])
    limit = _SIGMAS * math.sqrt(2.0) * sigma
    first = largest_steps(sub)
    has = np.flatnonzero(first >= 0)
    noise = np.abs(r[first[has]] - r[first[has] - 1]) <= limit[has]
    first[has[noise]] = -1
    spike = front_spikes(sub, first, limit)
    if cfg.step_twigs:
        # every one-return dip in front, not only the largest step's (front_dips)
        spike |= front_dips(sub, limit)
    spiky = np.zeros(len(sub), dtype=bool)
    spiky[lab[spike]] = True
    first[spiky] = -1
    out = []
    if np.any(spiky):
        # the spike dropped, the candidate's other returns one piece with its own end flags
        pieces = sub.drop(~spike).select(spiky)
        out.append(
            judge_arcs(detector, every, sub, pieces, np.flatnonzero(spiky), which, grid, wrap)
        )
    if np.any(first >= 0):
        mark = np.zeros(len(r), dtype=np.int64)
        mark[first[first >= 0]] = 1
        cut = sub.cut(np.cumsum(mark) % 2 == 1)
        # cut ends occluded only by a nearer return across the cut (the arcs' rule)
        pieces = _cut_flags(sub, cut, np.arange(len(r)), cfg.occlusion_margin)
        local = lab[pieces.start].astype(np.int64)
        keep = first[local] >= 0
        pieces, local = pieces.select(keep), local[keep]
        out.append(judge_arcs(detector, every, sub, pieces, local, which, grid, wrap))
    return [g for g in out if g is not None]
