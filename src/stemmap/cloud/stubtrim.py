"""The trim step of the slice circle fits (:func:`~stemmap.cloud.slicefit._fit_segments`).

After each fit the points of a segment are trimmed by their residual about its circle:
symmetric, ``|d| <= window x 1.4826 x MAD`` (the default); with the stub trim
(``StemConfig.slice_stub_trim``) the scale comes from the residuals inside the circle and the
outside bound is tighter; with the surface stub trim (``StemConfig.slice_stub_surface``) that
outside bound is measured from the local bark surface of the point's angular sector where
that surface lies outside the circle (docs/algorithms/cloud.md "The noisy spruce: a stub
trim measured from the local surface").
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray

#: trims of the stub trim (``StemConfig.slice_stub_trim``): fit, trim, refit this many times
STUB_TRIM_ROUNDS = 3
#: the fewest inside residuals the stub trim's scale is taken from (else the trim stays
#: symmetric): a median of n half-normal values has a relative standard error of ~1.1 /
#: sqrt(n), 35 % at 10 (with 5, pine_plot at 10 % lost 2 of its 13 stems; docs)
STUB_TRIM_MIN_INSIDE = 10
#: the surface stub trim's sector, as an arc length along the circle (m): a sector holds a
#: branch stub's returns as a minority (a stub is one branch diameter wide, 1-3 cm on the
#: lower stem of a conifer), so its median residual is the bark's; a fork's crotch or a lobe
#: spans a wider arc (lidR's crotch side ~30 cm) and moves the whole sector's median
SURFACE_SECTOR_ARC = 0.10
#: the fewest sectors of a circle (a thin stem: sectors of at most 90 degrees)
SURFACE_MIN_SECTORS = 4
#: the fewest returns in a sector for its median to lift the outside bound (the median of n
#: Gaussian values has a standard error of ~1.25 sigma / sqrt(n), 0.44 sigma at 8)
SURFACE_MIN_POINTS = 8


def _segment_medians(
    v: FloatArray, ids: NDArray[np.int64], sel: NDArray[np.bool_], k: int
) -> FloatArray:
    """Per segment, the median of ``v`` over the points ``sel`` (the upper middle value of an
    even count); inf for segments without a selected point.

    The trim's scale in :func:`trim_keep`: the median |residual| over a segment's inliers,
    or with the stub trim over its inside half only. Stubs and needles lie outside the bark,
    an opaque trunk returns nothing from inside it beyond the noise; a symmetric noise has
    the same ``|d|`` on both sides, so the inside half's median is still the noise's
    ``0.6745 sigma`` (the 1.4826 MAD constant holds), not widened by the stubs.
    """
    out = np.full(k, np.inf)
    idx = np.flatnonzero(sel)
    if idx.size:
        order = np.lexsort((v[idx], ids[idx]))
        s_ids = ids[idx][order]
        s_v = v[idx][order]
        starts = np.flatnonzero(np.r_[True, s_ids[1:] != s_ids[:-1]])
        counts = np.diff(np.r_[starts, s_ids.size])
        out[s_ids[starts]] = s_v[starts + counts // 2]
    return out


def surface_lift(
    pts: FloatArray,
    ids: NDArray[np.int64],
    k: int,
    centers: FloatArray,
    radii: FloatArray,
    signed: FloatArray,
    sel: NDArray[np.bool_],
) -> FloatArray:
    """Per point, how far its angular sector's bark surface lies outside the circle (m, >= 0;
    NaN where the sector cannot tell).

    Each segment's circle is cut into ``max(SURFACE_MIN_SECTORS, floor(2 pi r /
    SURFACE_SECTOR_ARC))`` equal sectors of angle about its centre -- fewer, down to one,
    where the segment has fewer than twice :data:`SURFACE_MIN_POINTS` points ``sel`` per
    sector (a sparse slice: the sector widens until its median means something); a
    sector's surface is the median signed residual of its points ``sel`` (the symmetric
    window: the returns a plain trim would keep). The lift is that median where it is
    positive, 0 where it is on or inside the circle (the stub trim's bound unchanged), and
    NaN where the sector holds fewer than :data:`SURFACE_MIN_POINTS` of them: without the
    local surface a stub cannot be told from the bark, and :func:`trim_keep` keeps the plain
    symmetric trim there.
    """
    lift = np.full(pts.shape[0], np.nan)
    use = sel & np.isfinite(signed)
    if not use.any():
        return lift
    r = np.where(np.isfinite(radii), radii, 0.0)
    nsec = np.maximum(SURFACE_MIN_SECTORS, np.floor(2 * math.pi * r / SURFACE_SECTOR_ARC))
    # a sparse segment gets fewer, wider sectors: on average twice SURFACE_MIN_POINTS each
    held = np.bincount(ids[use], minlength=k) // (2 * SURFACE_MIN_POINTS)
    nsec = np.maximum(np.minimum(nsec, held), 1).astype(np.int64)
    width = int(nsec.max())
    c = np.where(np.isfinite(centers), centers, 0.0)
    dx, dy = (pts - c[ids]).T
    frac = (np.arctan2(dy, dx) + math.pi) / (2 * math.pi)
    sec = np.minimum((frac * nsec[ids]).astype(np.int64), nsec[ids] - 1)
    sid = ids * width + sec
    med = _segment_medians(signed, sid, use, k * width)
    count = np.bincount(sid[use], minlength=k * width)
    judged = (count >= SURFACE_MIN_POINTS) & np.isfinite(med)
    up = np.where(judged, np.maximum(med, 0.0), np.nan)
    lift[:] = up[sid]
    return lift


def trim_keep(
    pts: FloatArray,
    ids: NDArray[np.int64],
    k: int,
    centers: FloatArray,
    radii: FloatArray,
    ok: NDArray[np.bool_],
    keep: NDArray[np.bool_],
    window: float,
    stub_trim: float,
    stub_surface: bool = False,
) -> NDArray[np.bool_]:
    """The points kept for the next fit of :func:`~stemmap.cloud.slicefit._fit_segments`.

    Drops |residual| > max(``window`` (3) x 1.4826 x MAD, 1 mm) of the segment, the MAD over
    its current inliers ``keep`` (after a RANSAC start, not over the clutter it excluded: a
    MAD over all points would let the clutter back in). ``stub_trim`` > 0: the MAD over the
    inliers inside the circle (where a segment has :data:`STUB_TRIM_MIN_INSIDE` of them) and
    an outside bound at ``min(stub_trim, window)`` of those robust sigmas.
    ``stub_surface``: that outside bound is raised by :func:`surface_lift` (the sector's
    surface where it lies outside the circle), and the trim stays symmetric in sectors with
    too few returns to show their surface. Points of segments that failed are kept.
    """
    good = ok[ids]
    signed = np.full(pts.shape[0], np.inf)
    signed[good] = np.hypot(*(pts[good] - centers[ids[good]]).T) - radii[ids[good]]
    res = np.abs(signed)
    mad = _segment_medians(res, ids, good & keep, k)
    if stub_trim > 0:
        # the stub trim: the scale from the inside half, the outside bound at stub_trim
        inner = good & keep & (signed < 0)
        enough = np.bincount(ids[inner], minlength=k) >= STUB_TRIM_MIN_INSIDE
        mad = np.where(enough, _segment_medians(res, ids, inner, k), mad)
    thr = np.maximum(window * 1.4826 * mad, 0.001)
    if stub_trim > 0 and stub_surface:
        # the outside bound from the local surface: inside as before, outside the stub
        # bound above the sector's surface; symmetric where the sector cannot tell
        out = np.maximum(min(stub_trim, window) * 1.4826 * mad, 0.001)
        lift = surface_lift(pts, ids, k, centers, radii, signed, good & (res <= thr[ids]))
        bound = np.where(enough[ids] & np.isfinite(lift), out[ids] + lift, thr[ids])
        new = good & (signed >= -thr[ids]) & (signed <= bound)
    else:
        new = good & (res <= thr[ids])
        if stub_trim > 0:
            # the outside bound where the inside half gave the scale (else symmetric)
            out = np.maximum(min(stub_trim, window) * 1.4826 * mad, 0.001)
            new &= signed <= np.where(enough, out, np.inf)[ids]
    new |= ~good  # segments that failed keep their points for the second try
    return np.asarray(new, dtype=bool)
