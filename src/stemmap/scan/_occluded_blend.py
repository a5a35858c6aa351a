"""The blend at an occluded segment end (ours, issue 11, Dec 5; ``occluded_blend_sigmas``).

An averaging scanner (SICK LMS-class: ``beam_divergence_deg`` > 0, no first-echo footprint
correction) reports the footprint-weighted mean range of what its beam covers. Where a nearer
object occludes one side of a trunk, the beam whose footprint straddles the occluder's
silhouette returns a blend of the occluder's range and the trunk's: anywhere between the two,
so nearer than the trunk surface at that bearing. When the blend lies within the segmentation
jump of the trunk it joins the trunk's segment as its end return (the segment's end is flagged
occluded: the beam beyond hit something nearer), and one return several centimetres in front
of the arc flattens its sagitta and pulls its circle. With footprint narrower than the beam
spacing at most one beam straddles an edge, so only the end return itself can be the blend.

:func:`drop_occluded_blends` removes that end return when it lies nearer than the next return
inward by more than ``k`` range-noise sigmas (a trunk's visible arc does not step towards the
sensor at an occluded end by more than the noise between two neighbouring beams: the surface
slope between two beams 0.5 deg apart on a 30 cm trunk at 3-5 m is below 1 cm except right at
the silhouette, which an occluded end does not show). The segment stays flagged occluded (the
beam beyond its new end, the blend, is nearer).

Simulator, benchmark drive seed 13, scan 201, tree 35 (36.5 cm at 4.66 m, left side behind a
nearer trunk): the blend at 4.45 m, 8 cm in front of its neighbour, makes the 9-return
candidate fail ``depth``; the 6-return arc that replaces it reads 23.8 cm (-12.7 cm, 29 % of
the seed's squared DBH error at <= 5 m). docs/algorithms/scan-detection.md, "Per seed or on
the mean".
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.scan.config import DetectorConfig
from stemmap.scan.features import segment_sum
from stemmap.scan.plausibility import segment_sigma
from stemmap.scan.segment import Segments


def blend_ends_on(cfg: DetectorConfig) -> bool:
    """Whether ``cfg`` asks for the trim and reads an averaging scanner."""
    return (
        math.isfinite(cfg.occluded_blend_sigmas)
        and cfg.beam_divergence_deg > 0
        and cfg.beam_footprint_deg == 0
    )


def drop_occluded_blends(segs: Segments, cfg: DetectorConfig) -> Segments:
    """``segs`` without the end return of each occluded end that lies nearer than the next
    return inward by more than ``occluded_blend_sigmas`` x the segment's range noise
    (:func:`~stemmap.scan.plausibility.segment_sigma`); segments of fewer than 2 returns are
    left as they are. Flags unchanged (:meth:`Segments.drop`)."""
    if len(segs) == 0 or not blend_ends_on(cfg):
        return segs
    r = segs.points.r
    n = segs.counts
    sigma = segment_sigma(cfg, segs, segment_sum(r, segs) / n)
    lim = cfg.occluded_blend_sigmas * sigma
    ok = n >= 2
    first, last = segs.start, segs.stop - 1
    nxt = np.minimum(first + 1, last)
    prv = np.maximum(last - 1, first)
    keep = np.ones(r.shape[0], dtype=bool)
    at_start = ok & segs.occluded_start & (r[first] < r[nxt] - lim)
    at_end = ok & segs.occluded_end & (r[last] < r[prv] - lim)
    keep[first[at_start]] = False
    keep[last[at_end]] = False
    return segs if keep.all() else segs.drop(keep)
