"""How the re-fitted pieces of candidates join the numpy pipeline's output (ours, issue 11).

:meth:`~stemmap.scan.detect.ScanTrunkDetector._run_numpy` fits every candidate segment once
and keeps those that pass every test. A trunk merged with a branch, stub or neighbouring stem
fails as a whole; the re-fits cut it into pieces or take its largest consistent arc, and a
piece that passes every test takes its parent's place in the output. This module decides which
candidates are re-fitted and how their accepted pieces enter the output columns
(:func:`~stemmap.scan._segment_fits._output_columns`); the cuts themselves are
:mod:`stemmap.scan._refit` (corner, outlier and gap splits), :mod:`stemmap.scan._step_split`,
:mod:`stemmap.scan._split_search` and :mod:`stemmap.scan._arcs`.

Output order: the row of the ``k``-th candidate (among every candidate before the segment
filters when a split or arc re-fit needs them, else among those that passed) has order key
``2k``, a piece of it ``2k + 1``, so after the final stable sort a piece sits where its parent
would have (an accepted parent that gives way to its arc loses its row).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri

from stemmap.scan._arcs import arc_pieces
from stemmap.scan._beam_layout import _chi2_table
from stemmap.scan._cut_ends import trim_cut_ends
from stemmap.scan._fast_arcs import continues_outline
from stemmap.scan._refit import Refitted, refit_pieces, split_refit
from stemmap.scan._segment_fits import _Fitted, _output_columns
from stemmap.scan._split_search import search_refit
from stemmap.scan._step_split import step_refit
from stemmap.scan.features import footprint_correct, segment_features
from stemmap.scan.plausibility import REASONS, segment_reasons
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["add_pieces", "arc_candidates", "split_pieces"]

_DEPTH = REASONS.index("depth")
_RMS = REASONS.index("rms")

#: The output columns (:func:`~stemmap.scan._segment_fits._output_columns`) and their order
#: keys (module docstring).
Columns = dict[str, np.ndarray]


def split_pieces(
    detector: ScanTrunkDetector,
    every: Segments,
    segs: Segments,
    fitted: _Fitted,
    codes: NDArray[np.int8],
    pos: NDArray[np.int64],
    cols: Columns,
    order_key: np.ndarray,
    grid: FloatArray,
    wrap: bool,
    fate: dict[str, Any] | None = None,
) -> tuple[Columns, np.ndarray]:
    """The accepted pieces of the candidates the config splits, added to the output.

    ``every``: every candidate (before the segment filters when a corner split, ``split_search``
    or ``step_split`` is on); ``segs`` / ``fitted`` / ``codes``: the candidates that passed the
    segment filters, their fits (after the end trims) and fit reason codes; ``pos``: their
    indices into ``every``. Corner split (``refit_pieces`` with ``refit_split="corners"``):
    candidates not convex (``depth``) or failing the RMS test are cut at their concave
    corners; ``step_split``: those failing the RMS test without a trunk from the corner split
    at their largest range step; ``split_search``: those still without a trunk at every cut.
    Otherwise ``refit_pieces`` re-fits the pieces of the candidates that failed a fit test.
    ``fate``: :meth:`~stemmap.scan.detect.ScanTrunkDetector._run_numpy`."""
    cfg = detector.config
    corners = cfg.refit_pieces and cfg.refit_split == "corners"
    search = cfg.split_search or cfg.step_split
    if (corners or search) and len(every):
        # not convex (depth) or failed the RMS test: a trunk merged with its neighbour
        depth = segment_reasons(every, segment_features(every), cfg) == _DEPTH
        which = depth.copy()
        which[pos[codes == _RMS]] = True
        got = split_refit(detector, every, which, grid, wrap) if corners else None
        if cfg.step_split:
            # failed the RMS test, no trunk from the corner split: cut at the largest step
            rms = np.zeros(len(every), dtype=bool)
            rms[pos[codes == _RMS]] = True
            if got is not None:
                rms[got.parent[got.ok]] = False
                which[got.parent[got.ok]] = False
            cols, order_key = add_pieces(detector, cols, order_key, got, grid, wrap, fate, every)
            for g in step_refit(detector, every, rms, grid, wrap):
                which[g.parent[g.ok]] = False
                cols, order_key = add_pieces(detector, cols, order_key, g, grid, wrap, fate, every)
            got = None
        if cfg.split_search:
            # the candidates whose corner split gave no trunk: search every cut; unless
            # split_search_convex, only those that are not convex (depth): one convex
            # outline that fails the RMS test is as often a lumpy object (a rock) as a
            # trunk with a stub (sixteenth round)
            if not cfg.split_search_convex:
                which &= depth
            if got is not None:
                which[got.parent[got.ok]] = False
            cols, order_key = add_pieces(detector, cols, order_key, got, grid, wrap, fate, every)
            got = search_refit(detector, every, which, grid, wrap)
        cols, order_key = add_pieces(detector, cols, order_key, got, grid, wrap, fate, every)
    elif cfg.refit_pieces:
        got = refit_pieces(detector, segs, fitted, codes, grid, wrap)
        if fate is not None and got is not None:
            fate["split"].append((pos[got.parent], got.ok))
        if got is not None and np.any(got.ok):
            more = _output_columns(got.segs, got.fitted, got.ok, detector.config)
            # a piece takes its parent's place in the output (the parent failed)
            cols = {k: np.concatenate((cols[k], more[k])) for k in cols}
            order_key = np.concatenate((order_key, 2 * pos[got.parent[got.ok]] + 1))
    return cols, order_key


def add_pieces(
    detector: ScanTrunkDetector,
    cols: Columns,
    order_key: np.ndarray,
    got: Refitted | None,
    grid: FloatArray,
    wrap: bool,
    fate: dict[str, Any] | None = None,
    every: Segments | None = None,
) -> tuple[Columns, np.ndarray]:
    """The accepted pieces of a split (``got``, parents indexing every candidate ``every``)
    added to the output; each takes its parent's place (odd order key). ``cut_ends`` drops
    their cut-end returns (:func:`~stemmap.scan._cut_ends.trim_cut_ends`), then
    ``behind_sigmas`` and ``stub_sigmas`` trim them as they trim accepted candidates.
    ``fate``: :meth:`~stemmap.scan.detect.ScanTrunkDetector._run_numpy`."""
    if fate is not None and got is not None:
        fate["split"].append((got.parent, got.ok))
    if got is None or not np.any(got.ok):
        return cols, order_key
    if every is not None:
        got = trim_cut_ends(detector, got, every, grid, wrap)
    p_segs, p_fit = detector._trim_ends(got.segs, got.fitted, got.ok, grid, wrap)
    got = got._replace(segs=p_segs, fitted=p_fit)
    more = _output_columns(got.segs, got.fitted, got.ok, detector.config)
    cols = {k: np.concatenate((cols[k], more[k])) for k in cols}
    return cols, np.concatenate((order_key, 2 * got.parent[got.ok] + 1))


def _outline_goes_on(
    detector: ScanTrunkDetector,
    every: Segments,
    got: Refitted,
    i: int,
    cols: Columns,
    order_key: np.ndarray,
) -> bool:
    """Whether the accepted candidate that arc ``i`` of ``got`` would replace keeps its
    returns (:func:`stemmap.scan._fast_arcs.continues_outline`, which the compiled kernel
    calls with the same numbers): its returns as it was fitted (footprint-corrected for a
    first-echo scanner), its output row's circle, the arc's circle and range noise."""
    cfg = detector.config
    p = int(got.parent[i])
    seg = every.select(np.arange(len(every)) == p)
    if cfg.beam_footprint_deg > 0:
        seg = footprint_correct(seg, math.radians(cfg.beam_footprint_deg))
    pts = seg.points
    arc_beams = got.segs.points.beam[got.segs.start[i] : got.segs.stop[i]]
    qa = int(np.flatnonzero(pts.beam == arc_beams[0])[0])
    row = int(np.flatnonzero(order_key == 2 * p)[0])
    cx, cy = (float(v) for v in cols["centers"][row])
    ac = got.fitted.centers[i]
    return bool(
        continues_outline(
            np.ascontiguousarray(pts.x, dtype=np.float64),
            np.ascontiguousarray(pts.y, dtype=np.float64),
            np.ascontiguousarray(pts.r, dtype=np.float64),
            0,
            len(pts.r),
            qa,
            qa + arc_beams.shape[0],
            cx,
            cy,
            float(cols["radii"][row]),
            (float(ac[0]), float(ac[1]), float(got.fitted.radii[i])),
            float(got.fitted.sigma[i]),
            float(cfg.bark_roughness),
            _chi2_table(pts.n_beams),
        )
    )


def arc_candidates(
    detector: ScanTrunkDetector,
    every: Segments,
    cols: Columns,
    order_key: np.ndarray,
    parent_rms: FloatArray,
    grid: FloatArray,
    wrap: bool,
    fate: dict[str, Any] | None = None,
) -> tuple[Columns, np.ndarray]:
    """``arc_refit``: the largest consistent arcs (:func:`~stemmap.scan._arcs.arc_pieces`)
    of the candidates of ``every`` rejected as not convex (``depth``); a passing arc takes
    its parent's place in the output. With a finite ``arc_replace`` also of the accepted
    candidates (``order_key`` even, fit RMS ``parent_rms`` in the same order)."""
    # rejected for not being a convex arc: a trunk that runs on into a branch (lidR,
    # scan-detection-history.md); pieces of candidates that failed the RMS test were tried too
    # and passed as trunks on the simulator's bushes (precision 0.975 -> 0.947)
    cfg = detector.config
    which = segment_reasons(every, segment_features(every), cfg) == _DEPTH
    # a candidate whose corner split (refit_split="corners") gave a trunk is done: its arc
    # would be the same trunk twice
    which[order_key[order_key % 2 == 1] // 2] = False
    replace = math.isfinite(cfg.arc_replace)
    if replace:
        # accepted candidates too: kept (output row) ones at even keys
        rms_of = np.full(len(every), np.nan)
        rms_of[order_key[order_key % 2 == 0] // 2] = parent_rms
        which |= np.isfinite(rms_of)
    got = arc_pieces(detector, every, which, grid, wrap, corrected=False)
    if fate is not None and got is not None:  # (pieces of rejected parents: as accepted)
        fate["arc"].append((got.parent, got.ok))
    if got is None or not np.any(got.ok):
        return cols, order_key
    ok = got.ok.copy()
    stay = np.ones(order_key.shape[0], dtype=bool)
    if replace:
        par_rms = rms_of[got.parent]
        acc = np.isfinite(par_rms)
        # an accepted candidate gives way to its arc only when the arc explains its
        # returns much better (a fillet or stub at one end pulled the whole fit) and its
        # own residuals are not the range noise: it fails the upper 1 % chi^2 test the
        # arc passes (n x RMS^2 > chi2_0.99(n - 3) x sigma^2; a 5-return arc of a good
        # 6-return fit reads a third of its RMS by chance: demo seed 1, scan 475)
        sig = got.fitted.sigma
        better = par_rms > np.maximum(cfg.arc_replace * got.fitted.rms, sig)
        n_par = every.counts[got.parent]
        limit = chdtri(np.maximum(n_par - 3, 1).astype(np.float64), 0.01)
        with np.errstate(invalid="ignore"):
            better &= n_par * par_rms * par_rms > limit * sig * sig
        # ... and its outline does not go on past the arc's cut on the circle it was fitted
        # (_fast_arcs.continues_outline; benchmark seed 6, scan 188)
        for i in np.flatnonzero(ok & acc & better):
            better[i] = not _outline_goes_on(detector, every, got, int(i), cols, order_key)
        ok &= ~acc | better
        gone = got.parent[ok & acc]
        stay = ~(np.isin(order_key // 2, gone) & (order_key % 2 == 0))
    if not np.any(ok):
        return cols, order_key
    got = trim_cut_ends(detector, got._replace(ok=ok), every, grid, wrap)
    g_segs, g_fit = detector._trim_ends(got.segs, got.fitted, ok, grid, wrap, behind=False)
    more = _output_columns(g_segs, g_fit, ok, detector.config)
    cols = {k: np.concatenate((cols[k][stay], more[k])) for k in cols}
    return cols, np.concatenate((order_key[stay], 2 * got.parent[ok] + 1))
