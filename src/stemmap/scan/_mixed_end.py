"""Candidates short of ``min_points`` whose outline a mixed return continues (ours, issue 11).

A footprint-averaging scanner (SICK LMS-class) reports, for a beam whose footprint holds a
sliver of a trunk and a surface behind it, one range between the two, weighted by the power
each sends back (:mod:`stemmap.sim.footprint`; Hebert & Krotkov 1992, Tuley et al. 2005). Such
a *mixed return* lies farther than the trunk's edge return, so the range-jump segmentation
cuts it off, and a trunk seen by four beams keeps three clean returns: below ``min_points``
(4 in the ``stemmap`` preset), no candidate. On FORTLS's noise-free averaging scans this is
every view textbook Kasa (``min_points`` 3) measures and the detector does not find
(docs/algorithms/scan-detection.md, "The two FORTLS rows left against textbook Kasa"). A global
``min_points`` 3 finds them but also keeps 3-return clutter (simulated precision −0.013 to
−0.030 on every seed of the clutter drive, the same section, part 4).

The evidence that the outline continues is the mixed return itself: the beam ``n1`` beyond an
end is more than ``occlusion_margin`` farther than the end return (behind it, not an
occluder), and ``n1`` is not on a surface that carries on at its range: the beam after it
(``n2``) returned nothing or lies more than ``occlusion_margin`` farther than ``n1``. A lone
return between the trunk's edge and what lies beyond it is the blend of the two (the same
reading :func:`~stemmap.scan.features.edge_silhouette` takes for its mixed-pixel prior when
``n2`` returned; here also when it did not, the far surface's own edge inside ``n1``'s
footprint). A clean background behind the edge (``n2`` at ``n1``'s range) is no evidence: so
ends every isolated trunk seen against a wall or a farther stem.

:func:`least_points` gives each segment the returns it needs: ``min_points``, lowered to
``mixed_end_min_points`` where an end has a mixed return behind it. The segment filters
(:func:`~stemmap.scan.plausibility.segment_reasons`) and the selections after segmentation
read it; the fit and every later test are unchanged (``min_points_partial`` still holds an
occluded or truncated candidate, the trims keep ``max(min_points, min_points_partial)``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig

__all__ = ["least_points", "mixed_end_on", "mixed_ends"]


def mixed_end_on(cfg: DetectorConfig) -> bool:
    """Whether ``mixed_end_min_points`` acts: set, below ``min_points``, and the scanner is
    a footprint-averaging one (``beam_divergence_deg`` > 0, no first-echo footprint
    correction): a first-echo scanner has no mixed returns."""
    return (
        0 < cfg.mixed_end_min_points < cfg.min_points
        and cfg.beam_divergence_deg > 0
        and cfg.beam_footprint_deg == 0
    )


def mixed_ends(
    segs: Segments, grid: FloatArray, wrap: bool, margin: float
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per segment, whether the beam beyond its first / its last return (in beam order) is a
    mixed return behind it (module docstring). ``grid`` (S, N): the processed range grid the
    returns came from (inf / NaN: no return); ``wrap``: beam -1 is beam N - 1."""
    p = segs.points
    n = p.n_beams
    g = np.asarray(grid, dtype=np.float64).reshape(p.n_scans, n)

    def at(beams: NDArray[np.int64]) -> FloatArray:
        if wrap:
            val: FloatArray = g[segs.scan, np.mod(beams, n)]
        else:
            val = np.where(
                (beams >= 0) & (beams < n), g[segs.scan, np.clip(beams, 0, n - 1)], np.inf
            )
        return np.where(np.isfinite(val), val, np.inf)

    out = []
    for idx, step in ((segs.start, -1), (segs.stop - 1, 1)):
        if len(segs) == 0:
            out.append(np.zeros(0, dtype=bool))
            continue
        edge_r = p.r[idx]
        r1 = at(p.beam[idx] + step)
        r2 = at(p.beam[idx] + 2 * step)
        with np.errstate(invalid="ignore"):
            behind = np.isfinite(r1) & (r1 > edge_r + margin)
            out.append(behind & (~np.isfinite(r2) | (r2 > r1 + margin)))
    return out[0], out[1]


def least_points(
    cfg: DetectorConfig, segs: Segments, grid: FloatArray, wrap: bool
) -> NDArray[np.int64]:
    """The returns each segment of ``segs`` needs: ``min_points``, or
    ``mixed_end_min_points`` where an end has a mixed return behind it (:func:`mixed_ends`;
    only when :func:`mixed_end_on`)."""
    least = np.full(len(segs), cfg.min_points, dtype=np.int64)
    if not mixed_end_on(cfg) or len(segs) == 0:
        return least
    # only the segments the option can admit are looked at
    short = (segs.counts >= cfg.mixed_end_min_points) & (segs.counts < cfg.min_points)
    if not np.any(short):
        return least
    sub = segs.select(short)
    first, last = mixed_ends(sub, grid, wrap, cfg.occlusion_margin)
    rows = np.flatnonzero(short)[first | last]
    least[rows] = cfg.mixed_end_min_points
    return least
