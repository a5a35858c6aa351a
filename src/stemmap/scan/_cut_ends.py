"""Drop the return at each cut end of an accepted piece: the junction of the stem with what
its segment ran on into (ours, issue 11, Dec 5, "The branch root at the arc end"; numpy
path, first-echo fits).

A piece (a corner split's, the step split's, a largest consistent arc) is cut from a segment
that joined the stem to another surface without a range jump: a branch leaving the flank,
its fillet, a stem or bush touching it. At the cut the last beam's footprint holds both
surfaces where they meet, and a first-echo beam returns the nearest of them. Two things then
go wrong with that end return. Its range is the junction's (the fillet stands out of the
stem's circle: lidR's branch root 6-12 mm outside the ring on five views, and one beam at
the corner on the branch itself), and the footprint correction
(:func:`~stemmap.scan.features.footprint_correct`) puts it at the side of its footprint
nearest the stem's apex, which is where a convex stem's nearest point lies but not where the
junction's is: laterally it can be off by up to a footprint (4.9 cm at 5.6 m, 0.5 deg). On a
5-8-return arc 6-9 m away that return sets the width and the fit follows it: lidR read
+3.0 to +6.2 cm on those five views (docs/algorithms/scan-detection.md, "The branch root at
the arc end").

And the stem's silhouette on that side was never seen: the beam beyond the end hit the
adjoining surface at about the stem's range, not the background behind the stem, so nothing
shows where the stem's tangent lies (the reason ``stub_runs_snoop`` reads a trimmed end as
occluded when the return beyond is nearer than the tangent range).

:func:`trim_cut_ends` (``cut_ends``): at each end of an accepted piece that is a cut (its
parent candidate continues beyond it) the end return goes and the end is occluded; the piece
is fitted again and keeps the trim only when the refit passes every test (the rule of
:func:`~stemmap.scan._behind.trim_behind`) and keeps at least ``max(min_points,
min_points_partial)`` returns and more than half of its own. A short far arc whose rest is
no longer a credible trunk keeps its end (lidR scans 6 and 9: four returns at 8.5-8.8 m).
First-echo fits only (:func:`~stemmap.scan._stubs.first_echo`): the averaging edge model
already reads an edge return as a mixed pixel.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan._behind import _merge, _take
from stemmap.scan._refit import Refitted, fit_passes
from stemmap.scan._stub_runs import _trimmed_flags
from stemmap.scan._stubs import first_echo
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["cut_flags", "trim_cut_ends"]


def cut_flags(
    pieces: Segments, every: Segments, parent: NDArray[np.int64]
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per piece, whether its first / its last return is a cut: not the first / last return
    of its parent candidate (``parent`` indexes ``every``; pieces keep the beam numbers of
    their parents' returns)."""
    pb, eb = pieces.points.beam, every.points.beam
    first = pb[pieces.start] != eb[every.start[parent]]
    last = pb[pieces.stop - 1] != eb[every.stop[parent] - 1]
    return first, last


def trim_cut_ends(
    detector: ScanTrunkDetector,
    got: Refitted,
    every: Segments,
    grid: FloatArray,
    wrap: bool,
) -> Refitted:
    """``got`` with the return at each cut end of its accepted pieces dropped and that end
    occluded, where the trimmed piece passes every test (module docstring); the same pieces
    in the same order. Unchanged when ``cut_ends`` is off or the fit is not first-echo."""
    cfg = detector.config
    if not cfg.cut_ends or not first_echo(cfg) or not np.any(got.ok):
        return got
    segs = got.segs
    c_s, c_e = cut_flags(segs, every, got.parent)
    least = max(cfg.min_points, cfg.min_points_partial)
    n = segs.counts
    rest = n - c_s - c_e
    act = got.ok & (c_s | c_e) & (rest >= least) & (2 * rest > n)
    if not np.any(act):
        return got
    c_s &= act
    c_e &= act
    drop = np.zeros(len(segs.points), dtype=bool)
    drop[segs.start[c_s]] = True
    drop[segs.stop[c_e] - 1] = True
    # the cut ends occluded: the stem's silhouette there was never seen
    trimmed = _trimmed_flags(segs.drop(~drop), c_s, c_e, c_s, c_e)
    refit = detector._fit_candidates(trimmed.select(act), grid, wrap)
    passed = fit_passes(cfg, refit)
    if not np.any(passed):
        return got
    rows = np.flatnonzero(act)
    undo = np.zeros(len(segs), dtype=bool)
    undo[rows[~passed]] = True
    drop &= ~undo[segs.labels]
    c_s &= ~undo
    c_e &= ~undo
    out = _trimmed_flags(segs.drop(~drop), c_s, c_e, c_s, c_e)
    return got._replace(segs=out, fitted=_merge(got.fitted, rows[passed], _take(refit, passed)))
