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
absolute range step and judges the two pieces as the arcs of ``arc_refit`` are judged: segment
filters with a cut end occluded only when the return across it is nearer by more than
``occlusion_margin`` (:func:`~stemmap.scan._arcs._cut_flags`, the rule of ``build_segments``:
a branch behind the stem does not make the stem partial), the detector's fit, the RMS test
without the bark allowance, the tangent-range and chi-square tests
(:func:`~stemmap.scan._arcs.piece_passes`), accepted only together
(:func:`~stemmap.scan._refit.judge_pieces` with validation) and only when no return of the
candidate was seen through the piece's circle
(:func:`~stemmap.scan._split_search.seen_through`). Numpy path only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan._arcs import _cut_flags, piece_passes
from stemmap.scan._refit import Refitted, judge_pieces
from stemmap.scan._split_search import seen_through
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["largest_steps", "step_refit"]

#: Noise sigmas of the seen-through test (as ``_split_search``).
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


def step_refit(
    detector: ScanTrunkDetector,
    every: Segments,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> Refitted | None:
    """``step_split``: the candidates of ``every`` (before footprint correction) flagged by
    ``which`` cut at their largest range step (:func:`largest_steps`), the two pieces judged
    as arcs (module docstring). ``parent`` indexes ``every``; None when nothing was cut."""
    cfg = detector.config
    if not np.any(which):
        return None
    sub = every.select(which)
    first = largest_steps(sub)
    first = first[first >= 0]
    if first.size == 0:
        return None
    mark = np.zeros(len(sub.points), dtype=np.int64)
    mark[first] = 1
    cut = sub.cut(np.cumsum(mark) % 2 == 1)
    # cut ends occluded only by a nearer return across the cut (the arcs' rule)
    pieces = _cut_flags(sub, cut, np.arange(len(sub.points)), cfg.occlusion_margin)
    local = sub.labels[pieces.start].astype(np.int64)
    got = judge_pieces(
        detector, sub, pieces, local, which, grid, wrap, validate=True, tests=piece_passes
    )
    if got is None or not np.any(got.ok):
        return got
    through = seen_through(
        every, got.parent, got.fitted.centers, got.fitted.radii, got.fitted.sigma, got.ok, _SIGMAS
    )
    return got._replace(ok=got.ok & ~through)
