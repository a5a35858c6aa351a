"""A scanner's return threshold from beam counts of trunks seen at many ranges.

A footprint-averaging scanner (SICK LMS-class) returns an echo when some share ``q`` of its
footprint (full angular width ``w``) hits a surface. At a silhouette edge the last returning
beam then lies ``(1/2 - q) w`` outside the silhouette, so a convex object of silhouette angle
``Phi`` spans on average ``(Phi + e) / delta`` beams (beam step ``delta``, uniformly random
beam phase) with the **angular excess**

    e = (1 - 2 q) w                                                                   (1)

A fixed angle: in metres it grows with range. Beam-count tree detectors such as the one that
produced the Victoria Park detections (Guivant & Nebot's ``DetecTrees``: diameter = number of
beams spanned x beam step x mean edge range) therefore report ``D + e r`` for a trunk of
diameter ``D`` at range ``r``, and the within-trunk slope of the reported diameter on range is
``e``. Written as angles (``A = N delta``, the beams spanned, against ``x = 1 / r``) one pass
of one trunk gives ``A = e + D x``; :func:`width_excess` fits ``e`` common to all passes and a
``D`` per pass (fixed effects), with a bootstrap over passes.

Pieces:

* :func:`beam_tree_detections`: the beam-count detector written from the description of
  ``DetecTrees`` (segments split at range jumps, ambiguity and shape gates; diameter =
  spanned beams x step x mean edge range, range = centre range + half the diameter), so the
  simulator's scans go through the same detector as the real log.
* :func:`beams_spanned`: the beam count ``N`` recovered from such a detection's range and
  diameter (for the Victoria Park file ``d / (delta (r - d/2))`` lies within 0.005 of an
  integer for one and two beams: the file is this detector's output).
* :func:`link_passes`: detections of consecutive scans linked into passes (mutual nearest
  neighbours in a world frame, dead reckoning suffices over a few scans).
* :func:`usable_detections`: the ranges at which a pass cannot lose beams to the detector's
  own quantisation (predicted span >= ``min_beams``), so that ``E[N] = (Phi + e) / delta``
  holds without censoring.
* :func:`width_excess`: the pooled estimate of ``e`` with its bootstrap interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError
from stemmap.types import FloatArray

IntArray = NDArray[np.int64]

__all__ = [
    "BeamTreeDetections",
    "WidthExcess",
    "beam_tree_detections",
    "beams_spanned",
    "link_passes",
    "usable_detections",
    "width_excess",
]


@dataclass(frozen=True)
class BeamTreeDetections:
    """Detections of :func:`beam_tree_detections`, one row each.

    Attributes
    ----------
    scan : ndarray (K,), int — scan index
    range : ndarray (K,), m — centre-beam range + half the diameter (the trunk centre)
    bearing : ndarray (K,), rad — mid angle of the first and last beam, in the scan's own
        angle frame (``angle_min + i * delta``)
    diameter : ndarray (K,), m — beams spanned x ``delta`` x mean of the two edge ranges
    beams : ndarray (K,), int — beams spanned (last index - first index + 1)
    """

    scan: IntArray
    range: FloatArray
    bearing: FloatArray
    diameter: FloatArray
    beams: IntArray


def _segments(r: FloatArray, idx: IntArray, jump: float, gap_beams: float) -> list[tuple[int, int]]:
    """Runs of consecutive valid beams (positions into ``idx``) split where the range jumps by
    more than ``jump`` or the valid beams are more than ``gap_beams`` apart."""
    if idx.size == 0:
        return []
    cut = (np.abs(np.diff(r)) > jump) | (np.diff(idx) > gap_beams)
    starts = np.concatenate(([0], np.flatnonzero(cut) + 1))
    ends = np.concatenate((np.flatnonzero(cut), [idx.size - 1]))
    return list(zip(starts.tolist(), ends.tolist(), strict=True))


def beam_tree_detections(
    ranges: ArrayLike,
    angle_min: float,
    angle_increment: float,
    *,
    max_range: float = 75.0,
    min_range: float = 1.0,
    edge_guard: float = math.radians(2.5),
    jump: float = 1.5,
    angle_gap: float = math.radians(5.0),
    min_separation: float = 3.0,
    min_angular_separation: float = math.radians(1.0),
    max_diameter: float = 1.0,
) -> BeamTreeDetections:
    """Beam-count trunk detector in the manner of the Victoria Park ``DetecTrees``.

    Parameters
    ----------
    ranges : array_like (S, N), m
        Scans; ``inf`` / NaN / ``>= max_range`` = no return.
    angle_min, angle_increment : float, rad
        Beam ``i`` points at ``angle_min + i * angle_increment``.
    max_range, min_range : float, m
        Returns at or beyond ``max_range`` are dropped; a segment whose first beam is nearer
        than ``min_range`` is dropped.
    edge_guard : float, rad
        Segments touching the first or last ``edge_guard`` of the field of view are dropped.
    jump, angle_gap : float
        A segment ends where the range jumps by more than ``jump`` (m) or the next valid beam
        is more than ``angle_gap`` (rad) away.
    min_separation, min_angular_separation : float
        Ambiguity gates: a segment whose last point lies within ``min_separation`` (m) of the
        first point of any later segment is dropped; of two segments closer than
        ``min_angular_separation`` in angle the farther is dropped.
    max_diameter : float, m
        Segments whose edge-to-edge chord reaches this are not trunks.

    Returns
    -------
    BeamTreeDetections
        Diameter ``N * delta * (r_first + r_last) / 2`` (``N`` beams spanned), kept when the
        two edge ranges differ by less than a third of it; range = mean of the one or two
        centre beams + half the diameter.
    """
    arr = np.asarray(ranges, dtype=np.float64)
    if arr.ndim != 2:
        raise InputError(f"beam_tree_detections needs (S, N) ranges, got shape {arr.shape}.")
    if not angle_increment > 0:
        raise InputError(f"angle_increment must be > 0, got {angle_increment}.")
    n_b = arr.shape[1]
    ang_all = angle_min + angle_increment * np.arange(n_b)
    lo_ang, hi_ang = angle_min + edge_guard, angle_min + angle_increment * (n_b - 1) - edge_guard
    gap_beams = angle_gap / angle_increment
    out: list[tuple[int, float, float, float, int]] = []
    for s in range(arr.shape[0]):
        row = arr[s]
        with np.errstate(invalid="ignore"):
            idx = np.flatnonzero(np.isfinite(row) & (row < max_range))
        r = row[idx]
        segs = _segments(r, idx, jump, gap_beams)
        if not segs:
            continue
        a = ang_all[idx]
        xy = np.column_stack((r * np.cos(a), r * np.sin(a)))
        first = np.array([p for p, _ in segs])
        last = np.array([q for _, q in segs])
        ok = np.ones(len(segs), dtype=bool)
        for i in range(len(segs) - 1):
            d2 = np.sum((xy[first[i + 1 :]] - xy[last[i]]) ** 2, axis=1)
            if np.any(d2 < min_separation**2):
                ok[i] = False
        gap = a[first[1:]] - a[last[:-1]]
        for j in np.flatnonzero(gap < min_angular_separation).tolist():
            ok[j + 1 if r[first[j + 1]] > r[last[j]] else j] = False
        for k in np.flatnonzero(ok):
            p, q = int(first[k]), int(last[k])
            if np.sum((xy[p] - xy[q]) ** 2) >= max_diameter**2:
                continue
            if not (r[p] > min_range and a[p] > lo_ang and a[q] < hi_ang):
                continue
            beams = int(idx[q] - idx[p]) + 1
            diam = beams * angle_increment * 0.5 * (r[p] + r[q])
            if not abs(r[q] - r[p]) < diam / 3.0:
                continue
            mid = 0.5 * (p + q)
            rc = 0.5 * (r[math.floor(mid)] + r[math.ceil(mid)])
            out.append((s, rc + 0.5 * diam, 0.5 * (a[p] + a[q]), diam, beams))
    if not out:
        e = np.empty(0)
        return BeamTreeDetections(e.astype(np.int64), e, e, e, e.astype(np.int64))
    cols = list(zip(*out, strict=True))
    return BeamTreeDetections(
        np.asarray(cols[0], dtype=np.int64),
        np.asarray(cols[1], dtype=np.float64),
        np.asarray(cols[2], dtype=np.float64),
        np.asarray(cols[3], dtype=np.float64),
        np.asarray(cols[4], dtype=np.int64),
    )


def beams_spanned(ranges: ArrayLike, diameters: ArrayLike, angle_increment: float) -> IntArray:
    """Beams spanned by beam-count detections from their reported range and diameter.

    The detector reports ``d = N delta r_edge`` and ``r = r_centre + d / 2``. For one or two
    beams the centre beams are the edge beams, ``r_edge = r - d / 2`` exactly. For more, the
    centre beam sees the front of a trunk of radius ``R ~ d / 2`` and the edge beams, about
    ``(N - 1) / N`` of the radius off its axis, hit ``R (1 - sqrt(1 - ((N - 1) / N)^2))``
    behind the front; ``N`` is the rounded ratio, refined twice (at least 1).
    """
    r = np.asarray(ranges, dtype=np.float64)
    d = np.asarray(diameters, dtype=np.float64)
    if r.shape != d.shape:
        raise InputError(f"ranges {r.shape} and diameters {d.shape} differ in shape.")
    front = r - 0.5 * d
    n = np.maximum(np.rint(d / (angle_increment * front)), 1.0)
    for _ in range(2):
        off = (n - 1.0) / n
        edge = front + 0.5 * d * (1.0 - np.sqrt(1.0 - off * off))
        n = np.where(n > 2, np.maximum(np.rint(d / (angle_increment * edge)), 1.0), n)
    return np.maximum(n, 1).astype(np.int64)


def link_passes(
    frame: ArrayLike, xy: ArrayLike, *, gate: float = 1.0, max_gap: int = 3
) -> IntArray:
    """Pass id per detection: detections of scans at most ``max_gap`` apart linked when they
    are mutual nearest neighbours within ``gate`` (m) in a common world frame.

    ``frame`` (K,) non-decreasing scan indices, ``xy`` (K, 2) world positions. A pass ends
    when no detection continues it within ``max_gap`` scans.
    """
    from scipy.spatial import cKDTree

    f = np.asarray(frame, dtype=np.int64)
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if f.shape[0] != p.shape[0]:
        raise InputError(f"link_passes: {f.shape[0]} frames but {p.shape[0]} positions.")
    if f.size and np.any(np.diff(f) < 0):
        raise InputError("link_passes: frame indices must be non-decreasing.")
    ids = np.full(f.size, -1, dtype=np.int64)
    bounds = np.flatnonzero(np.diff(f)) + 1
    starts = np.concatenate(([0], bounds)) if f.size else np.empty(0, dtype=np.int64)
    ends = np.concatenate((bounds, [f.size])) if f.size else np.empty(0, dtype=np.int64)
    # active passes: id -> (last frame, detection index)
    active: dict[int, tuple[int, int]] = {}
    next_id = 0
    for s0, s1 in zip(starts.tolist(), ends.tolist(), strict=True):
        fr = int(f[s0])
        for pid in [k for k, (lf, _) in active.items() if fr - lf > max_gap]:
            del active[pid]
        cur = np.arange(s0, s1)
        if active:
            pids = np.array(list(active))
            prev = np.array([active[k][1] for k in pids])
            d_cp, j_cp = cKDTree(p[prev]).query(p[cur])
            _, j_pc = cKDTree(p[cur]).query(p[prev])
            for c in range(cur.size):
                j = int(j_cp[c])
                if d_cp[c] < gate and int(j_pc[j]) == c:
                    ids[cur[c]] = int(pids[j])
        for c in cur:
            if ids[c] < 0:
                ids[c] = next_id
                next_id += 1
            active[int(ids[c])] = (fr, int(c))
    return ids


def usable_detections(
    pass_id: ArrayLike,
    ranges: ArrayLike,
    widths: ArrayLike,
    angle_increment: float,
    *,
    min_beams: float = 2.0,
    max_beams: float = math.inf,
    min_range: float = 2.0,
) -> NDArray[np.bool_]:
    """Detections at ranges where their pass spans at least ``min_beams`` beams (and at most
    ``max_beams``).

    A trunk narrower than one beam step is seen by one beam or none, and a beam-count
    detector keeps only the scans where it is seen: its mean count is censored. Per pass the
    diameter ``D = median(width * range)`` predicts the span ``D / (range delta)``; a
    detection is kept when that is in ``[min_beams, max_beams]`` and the range
    ``>= min_range``. The rule looks at the pass, never at the detection's own count (a cut
    on the count would censor it). ``max_beams`` keeps counts that
    :func:`beams_spanned` recovers without ambiguity from a file of detections.
    """
    pid = np.asarray(pass_id, dtype=np.int64)
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(widths, dtype=np.float64)
    keep = np.zeros(pid.size, dtype=bool)
    if pid.size == 0:
        return keep
    order = np.argsort(pid, kind="stable")
    cuts = np.flatnonzero(np.diff(pid[order])) + 1
    for grp in np.split(order, cuts):
        dhat = float(np.median(a[grp] * r[grp]))
        span = dhat / (r[grp] * angle_increment)
        keep[grp] = (r[grp] >= min_range) & (span >= min_beams) & (span <= max_beams)
    return keep


@dataclass(frozen=True)
class WidthExcess:
    """Pooled angular excess ``e`` (rad) of :func:`width_excess`.

    Attributes
    ----------
    excess : float — fixed-effects estimate over all passes
    ci : (float, float) — bootstrap percentile interval over passes
    se : float — bootstrap standard error
    median_pass : float — median of the per-pass intercepts (own line per pass)
    passes, detections : int — used
    """

    excess: float
    ci: tuple[float, float]
    se: float
    median_pass: float
    passes: int
    detections: int


def _fe_terms(a: FloatArray, x: FloatArray, pid: IntArray) -> tuple[FloatArray, FloatArray]:
    """Per pass: numerator and denominator of the fixed-effects intercept (model
    ``a = e + D_pass x``: after projecting out ``D_pass``, ``e`` is a ratio of sums)."""
    n_p = int(pid.max()) + 1
    n = np.bincount(pid, minlength=n_p).astype(np.float64)
    sx = np.bincount(pid, x, minlength=n_p)
    sa = np.bincount(pid, a, minlength=n_p)
    sxx = np.bincount(pid, x * x, minlength=n_p)
    sxa = np.bincount(pid, x * a, minlength=n_p)
    with np.errstate(invalid="ignore", divide="ignore"):
        num = sa - sx * sxa / sxx
        den = n - sx * sx / sxx
    return np.nan_to_num(num), np.nan_to_num(den)


def width_excess(
    pass_id: ArrayLike,
    ranges: ArrayLike,
    widths: ArrayLike,
    *,
    min_detections: int = 10,
    min_spread: float = 1.5,
    n_boot: int = 1000,
    rng: np.random.Generator | int | None = 0,
) -> WidthExcess:
    """Angular excess ``e`` (rad) common to all passes, from ``widths = e + D_pass / range``.

    Parameters
    ----------
    pass_id : array_like (K,), int
    ranges : array_like (K,), m
    widths : array_like (K,), rad
        Apparent angular width of each detection (beams spanned x beam step).
    min_detections : int
        Passes with fewer detections are left out.
    min_spread : float
        Passes whose farthest / nearest range ratio is below this are left out (no leverage
        to separate ``D`` from ``e``).
    n_boot : int
        Bootstrap resamples of whole passes (detections within a pass are not independent).

    Returns
    -------
    WidthExcess

    Raises
    ------
    InputError
        If no pass qualifies.
    """
    pid0 = np.asarray(pass_id, dtype=np.int64)
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(widths, dtype=np.float64)
    if not (pid0.shape == r.shape == a.shape):
        raise InputError("width_excess: pass_id, ranges and widths differ in shape.")
    _, pid = np.unique(pid0, return_inverse=True)
    n_p = int(pid.max()) + 1 if pid.size else 0
    cnt = np.bincount(pid, minlength=n_p)
    rmin = np.full(n_p, np.inf)
    rmax = np.zeros(n_p)
    np.minimum.at(rmin, pid, r)
    np.maximum.at(rmax, pid, r)
    good = (cnt >= min_detections) & (rmax >= min_spread * rmin)
    if not good.any():
        raise InputError(
            f"width_excess: no pass has >= {min_detections} detections over a range ratio "
            f">= {min_spread}."
        )
    sel = good[pid]
    _, pid = np.unique(pid[sel], return_inverse=True)
    r, a = r[sel], a[sel]
    x = 1.0 / r
    num, den = _fe_terms(a, x, pid)
    e = float(num.sum() / den.sum())
    # per-pass own line a = e_p + D_p x
    n_p = num.size
    e_pass = num / np.where(den > 0, den, np.nan)
    gen = np.random.default_rng(rng)
    boots = np.empty(n_boot)
    for b in range(n_boot):
        w = np.bincount(gen.integers(0, n_p, n_p), minlength=n_p)
        boots[b] = float(w @ num / (w @ den))
    lo, hi = np.percentile(boots, [2.5, 97.5]) if n_boot else (math.nan, math.nan)
    return WidthExcess(
        excess=e,
        ci=(float(lo), float(hi)),
        se=float(np.std(boots, ddof=1)) if n_boot > 1 else math.nan,
        median_pass=float(np.nanmedian(e_pass)),
        passes=n_p,
        detections=int(a.size),
    )
