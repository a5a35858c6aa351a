"""Segmentation of 2D laser scans into clusters of consecutive returns.

All functions work on the *valid returns of a whole batch of scans at once*: a
:class:`ScanPoints` holds the returns of an ``(S, N)`` range array flattened in scan-then-beam
order, and a segmentation is a boolean "a new segment starts here" array over those points. No
per-scan or per-segment Python loop is involved, so 10,000 scans segment as fast as one big one.

Paper methods
-------------
* :func:`range_jump_breaks` -- range-jump clustering, Zheng et al. 2012 eq. 2 (threshold 0.2 m).
* :func:`euclidean_breaks` -- Euclidean distance between adjacent returns (the visual-lidar
  paper's "consecutive points based on distance are grouped", §2.2), with an optional
  range-proportional term (ours, :func:`adaptive_gap`).
* :func:`build_segments` -- segment table with occlusion flags: an end is *occluded* when the
  neighbouring beam returned from nearer than the segment's end (the trunk may continue behind
  it), and *truncated* when it touches the edge of the field of view.
* :func:`concave_corners` -- where a segment holds two touching objects (ours, issue 11).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = [
    "ScanPoints",
    "Segments",
    "adaptive_gap",
    "build_segments",
    "concave_corners",
    "euclidean_breaks",
    "extract_points",
    "range_jump_breaks",
]

IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class ScanPoints:
    """Valid returns of a batch of scans, flattened in scan-then-beam order.

    Attributes
    ----------
    scan, beam : ndarray of shape (M,), int
        Scan index and beam index of every return.
    r : ndarray of shape (M,), metres
        Range (horizontal range after a tilt projection).
    x, y : ndarray of shape (M,), metres, sensor frame
    n_scans, n_beams : int
    angle_increment : float, radians (signed)
    noise : ndarray of shape (n_scans,), metres, or None
        Range-noise scale of each scan estimated from all its returns
        (:func:`stemmap.scan.plausibility.scan_noise`; set with ``sigma_from_scan``).
    step_noise : ndarray of shape (n_scans,), metres, or None
        The same with the batch's pooled estimate where a scan has none of its own (set with
        ``step_split`` and ``step_noise_pool``: the step threshold of
        :func:`stemmap.scan._step_split.step_refit`).
    fit_noise : ndarray of shape (n_scans,), metres, or None
        The range noise each scan's circle fits weight the returns by, before the floor of
        ``fit_noise_floor`` and the cap of the tests' sigma: the scan's own estimate, or the
        estimate over every scan of the batch where it has none (set with
        ``fit_noise_floor`` on first-echo fits).
    floor : ndarray of shape (n_scans,), metres, or None
        The range-noise floor of each scan in place of the config's ``sigma``: read from the
        outlines of the batch's well-sampled candidates (set with ``outline_floor_points``:
        :mod:`stemmap.scan._outline_floor`).
    """

    scan: IntArray
    beam: IntArray
    r: FloatArray
    x: FloatArray
    y: FloatArray
    n_scans: int
    n_beams: int
    angle_increment: float
    noise: FloatArray | None = None
    step_noise: FloatArray | None = None
    fit_noise: FloatArray | None = None
    floor: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.r.shape[0])

    def take(self, sel: ArrayLike) -> ScanPoints:
        """Subset of the returns (boolean mask or sorted index), order preserved."""
        s = np.asarray(sel)
        return ScanPoints(
            self.scan[s],
            self.beam[s],
            self.r[s],
            self.x[s],
            self.y[s],
            self.n_scans,
            self.n_beams,
            self.angle_increment,
            self.noise,
            self.step_noise,
            self.fit_noise,
            self.floor,
        )


def extract_points(ranges: ArrayLike, angles: ArrayLike, angle_increment: float) -> ScanPoints:
    """Flatten the finite returns of ``ranges`` (N,) or (S, N) into a :class:`ScanPoints`.

    Parameters
    ----------
    ranges : array_like of shape (N,) or (S, N), metres, NaN/inf = no return (already gated)
    angles : array_like of shape (N,) or the shape of ``ranges``, radians
    angle_increment : float, radians, non-zero

    Raises
    ------
    InputError
        On mismatched shapes.
    """
    r2 = np.asarray(ranges, dtype=np.float64)
    if r2.ndim == 1:
        r2 = r2[None, :]
    if r2.ndim != 2:
        raise InputError(f"ranges must have shape (N,) or (S, N), got {r2.shape}.")
    a = np.asarray(angles, dtype=np.float64)
    if a.ndim == 1:
        if a.shape[0] != r2.shape[1]:
            raise InputError(f"{a.shape[0]} beam angles for scans of {r2.shape[1]} beams.")
    elif a.size != r2.size:
        raise InputError(f"angles has shape {a.shape}, ranges has shape {r2.shape}.")
    if angle_increment == 0.0 or not np.isfinite(angle_increment):
        raise InputError(f"angle_increment must be finite and non-zero, got {angle_increment}.")
    s_count, n = r2.shape
    flat = np.flatnonzero(np.isfinite(r2))
    scan = flat // n
    beam = flat - scan * n
    r = r2.reshape(-1)[flat]
    ang = a[beam] if a.ndim == 1 else a.reshape(-1)[flat]
    return ScanPoints(
        scan.astype(np.int64),
        beam.astype(np.int64),
        r,
        r * np.cos(ang),
        r * np.sin(ang),
        s_count,
        n,
        float(angle_increment),
    )


def _new_scan_or_gap(pts: ScanPoints, max_skip: int) -> BoolArray:
    """True where a return starts a new scan or follows more than ``max_skip`` missing beams."""
    if max_skip < 0:
        raise ConfigError(f"max_skip must be >= 0 missing beams, got {max_skip}.")
    brk = np.ones(len(pts), dtype=bool)
    if len(pts) > 1:
        brk[1:] = (pts.scan[1:] != pts.scan[:-1]) | (pts.beam[1:] - pts.beam[:-1] > max_skip + 1)
    return brk


def range_jump_breaks(pts: ScanPoints, max_jump: float = 0.2, *, max_skip: int = 0) -> BoolArray:
    """Segment starts by range jump (Zheng et al. 2012, eq. 2).

    A new cluster starts at return ``i`` when ``|l_i - l_{i-1}| > max_jump``, when it is the
    first return of a scan, or when more than ``max_skip`` beams between ``i-1`` and ``i``
    returned nothing.

    Parameters
    ----------
    pts : ScanPoints
    max_jump : float, metres, > 0 (Zheng: 0.2 m)
    max_skip : int, >= 0
        Missing beams bridged inside a segment (0 = every "no return" splits, as in the paper).

    Returns
    -------
    ndarray of shape (M,), bool
    """
    if not max_jump > 0:
        raise ConfigError(f"max_jump must be > 0 m, got {max_jump}.")
    brk = _new_scan_or_gap(pts, max_skip)
    if len(pts) > 1:
        brk[1:] |= np.abs(np.diff(pts.r)) > max_jump
    return brk


def adaptive_gap(
    r: ArrayLike, beam_gap: ArrayLike, angle_increment: float, base: float, k: float
) -> FloatArray:
    """Distance threshold ``base + k * r * |angle_increment| * beam_gap`` (ours).

    The spacing of returns on a surface grows with range and with the number of beams between
    them; a fixed threshold either splits far trunks or merges near objects.
    """
    out: FloatArray = base + k * np.asarray(r) * abs(angle_increment) * np.asarray(beam_gap)
    return out


def euclidean_breaks(
    pts: ScanPoints, max_gap: float = 0.2, *, max_skip: int = 0, range_factor: float = 0.0
) -> BoolArray:
    """Segment starts by the Euclidean distance between consecutive returns.

    A new segment starts at return ``i`` when ``|p_i - p_{i-1}| > max_gap + range_factor *
    r_i * |dtheta| * (beam_i - beam_{i-1})`` (``range_factor = 0``: a fixed threshold, as in
    the visual-lidar paper §2.2; ``range_factor > 0``: our range-adaptive variant), at scan
    starts, and after more than ``max_skip`` missing beams.

    Parameters
    ----------
    pts : ScanPoints
    max_gap : float, metres, > 0
    max_skip : int, >= 0
    range_factor : float, >= 0

    Returns
    -------
    ndarray of shape (M,), bool
    """
    if not max_gap > 0 or range_factor < 0:
        raise ConfigError(f"need max_gap > 0 and range_factor >= 0, got {max_gap}, {range_factor}.")
    brk = _new_scan_or_gap(pts, max_skip)
    if len(pts) > 1:
        d = np.hypot(np.diff(pts.x), np.diff(pts.y))
        if range_factor > 0:
            thr = adaptive_gap(
                np.minimum(pts.r[1:], pts.r[:-1]),
                np.diff(pts.beam),
                pts.angle_increment,
                max_gap,
                range_factor,
            )
        else:
            thr = np.full(d.shape, max_gap)
        brk[1:] |= d > thr
    return brk


@dataclass(frozen=True, eq=False)
class Segments:
    """Segments of a :class:`ScanPoints`, as a columnar table.

    Segment ``k`` is ``points[start[k]:stop[k]]`` (consecutive returns of one scan).

    Attributes
    ----------
    points : ScanPoints
    start, stop : ndarray of shape (K,), int (``stop`` exclusive)
    scan : ndarray of shape (K,), int
    occluded_start, occluded_end : ndarray of shape (K,), bool
        The beam next to the segment's first / last return hit something nearer: the object
        may continue behind the occluder (partial trunk).
    truncated_start, truncated_end : ndarray of shape (K,), bool
        The segment touches the first / last beam of the field of view.
    """

    points: ScanPoints
    start: IntArray
    stop: IntArray
    scan: IntArray
    occluded_start: BoolArray
    occluded_end: BoolArray
    truncated_start: BoolArray
    truncated_end: BoolArray

    def __len__(self) -> int:
        return int(self.start.shape[0])

    @property
    def counts(self) -> IntArray:
        out: IntArray = self.stop - self.start
        return out

    @property
    def labels(self) -> IntArray:
        """Segment index of every point, shape (M,)."""
        return np.repeat(np.arange(len(self), dtype=np.int64), self.counts)

    @property
    def partial(self) -> BoolArray:
        """Either end occluded or truncated."""
        out: BoolArray = (
            self.occluded_start | self.occluded_end | self.truncated_start | self.truncated_end
        )
        return out

    def select(self, keep: ArrayLike) -> Segments:
        """Keep the segments where ``keep`` (K,) is True; their returns are compacted so the
        result again covers its points contiguously."""
        k = np.asarray(keep, dtype=bool)
        if k.shape != (len(self),):
            raise InputError(f"keep has shape {k.shape}, expected ({len(self)},).")
        counts = self.counts[k]
        pts = self.points.take(np.repeat(k, self.counts))
        stop = np.cumsum(counts).astype(np.int64)
        return Segments(
            pts,
            stop - counts,
            stop,
            self.scan[k],
            self.occluded_start[k],
            self.occluded_end[k],
            self.truncated_start[k],
            self.truncated_end[k],
        )

    def drop(self, keep_points: ArrayLike) -> Segments:
        """Remove the returns where ``keep_points`` (M,) is False; every segment stays one
        segment (segments left without returns disappear). Flags are unchanged."""
        kp = np.asarray(keep_points, dtype=bool)
        if kp.shape != (len(self.points),):
            raise InputError(f"keep_points has shape {kp.shape}, expected ({len(self.points)},).")
        counts = np.bincount(self.labels[kp], minlength=len(self)).astype(np.int64)
        alive = counts > 0
        stop = np.cumsum(counts[alive]).astype(np.int64)
        return Segments(
            self.points.take(kp),
            stop - counts[alive],
            stop,
            self.scan[alive],
            self.occluded_start[alive],
            self.occluded_end[alive],
            self.truncated_start[alive],
            self.truncated_end[alive],
        )

    def cut(self, flags: ArrayLike) -> Segments:
        """Split every segment wherever the boolean ``flags`` (M,) changes value between two
        consecutive returns; no return is removed. Inner cut ends are marked occluded."""
        fl = np.asarray(flags, dtype=bool)
        if fl.shape != (len(self.points),):
            raise InputError(f"flags has shape {fl.shape}, expected ({len(self.points)},).")
        m = len(self.points)
        brk = np.zeros(m, dtype=bool)
        brk[self.start] = True
        if m > 1:
            brk[1:] |= fl[1:] != fl[:-1]
        starts = np.flatnonzero(brk).astype(np.int64)
        stops = (np.append(starts[1:], m) if starts.size else starts).astype(np.int64)
        seg_of = self.labels[starts] if m else starts
        first_piece = starts == self.start[seg_of]
        last_piece = stops == self.stop[seg_of]
        return Segments(
            self.points,
            starts,
            stops,
            self.scan[seg_of],
            np.where(first_piece, self.occluded_start[seg_of], True),
            np.where(last_piece, self.occluded_end[seg_of], True),
            first_piece & self.truncated_start[seg_of],
            last_piece & self.truncated_end[seg_of],
        )

    def split(self, keep_points: ArrayLike, *, min_points: int = 1) -> Segments:
        """Drop the returns where ``keep_points`` (M,) is False and split every segment where a
        run of dropped returns interrupted it; pieces shorter than ``min_points`` are dropped.

        Flags carry over to the pieces: occlusion/truncation of the first piece's start and
        the last piece's end are the original segment's; inner cut ends are marked occluded
        (the piece continued into another object).
        """
        kp = np.asarray(keep_points, dtype=bool)
        if kp.shape != (len(self.points),):
            raise InputError(f"keep_points has shape {kp.shape}, expected ({len(self.points)},).")
        m = len(self.points)
        lab = self.labels
        # a kept point starts a piece if it starts a segment or its predecessor was dropped
        pstart = np.zeros(m, dtype=bool)
        pstart[self.start] = True
        if m > 1:
            pstart[1:] |= ~kp[:-1]
        pstart &= kp
        idx = np.flatnonzero(kp)
        new_start_flag = pstart[idx]
        starts = np.flatnonzero(new_start_flag).astype(np.int64)
        stops = (np.append(starts[1:], idx.shape[0]) if starts.size else starts).astype(np.int64)
        seg_of = lab[idx[starts]]
        first_piece = idx[starts] == self.start[seg_of]
        last_piece = idx[stops - 1] == self.stop[seg_of] - 1
        pieces = Segments(
            self.points.take(idx),
            starts,
            stops,
            self.scan[seg_of],
            np.where(first_piece, self.occluded_start[seg_of], True),
            np.where(last_piece, self.occluded_end[seg_of], True),
            first_piece & self.truncated_start[seg_of],
            last_piece & self.truncated_end[seg_of],
        )
        if min_points > 1:
            pieces = pieces.select(pieces.counts >= min_points)
        return pieces


def build_segments(
    pts: ScanPoints,
    breaks: ArrayLike,
    *,
    ranges: ArrayLike | None = None,
    occlusion_margin: float = 0.2,
    first_beam: int = 0,
    last_beam: int | None = None,
) -> Segments:
    """Turn break flags into a :class:`Segments` table with occlusion flags.

    Parameters
    ----------
    pts : ScanPoints
    breaks : array_like of shape (M,), bool -- True where a segment starts (``breaks[0]`` must
        be True when there are points).
    ranges : array_like of shape (S, N), optional
        The (gated) range grid the points came from. When given, an end is occluded if the
        *adjacent beam* returned from more than ``occlusion_margin`` nearer; otherwise the
        neighbouring return in ``pts`` is used (same test, but only if it is the adjacent beam).
    occlusion_margin : float, metres, >= 0
    first_beam, last_beam : int
        First and last beam of the field of view (``last_beam`` default ``n_beams - 1``).

    Returns
    -------
    Segments
    """
    b = np.asarray(breaks, dtype=bool)
    if b.shape != (len(pts),):
        raise InputError(f"breaks has shape {b.shape}, expected ({len(pts)},).")
    if len(pts) and not b[0]:
        raise InputError("breaks[0] must be True: the first return always starts a segment.")
    last = pts.n_beams - 1 if last_beam is None else int(last_beam)
    start = np.flatnonzero(b).astype(np.int64)
    stop = (np.append(start[1:], len(pts)) if start.size else start).astype(np.int64)
    seg_scan = pts.scan[start]
    b0 = pts.beam[start]
    b1 = pts.beam[stop - 1]
    r0 = pts.r[start]
    r1 = pts.r[stop - 1]
    if ranges is not None:
        grid = np.asarray(ranges, dtype=np.float64).reshape(pts.n_scans, pts.n_beams)
        prev_r = grid[seg_scan, np.maximum(b0 - 1, 0)]
        next_r = grid[seg_scan, np.minimum(b1 + 1, pts.n_beams - 1)]
        with np.errstate(invalid="ignore"):
            occ0 = (b0 > first_beam) & (prev_r < r0 - occlusion_margin)
            occ1 = (b1 < last) & (next_r < r1 - occlusion_margin)
    else:
        m = len(pts)
        pi = np.maximum(start - 1, 0)
        ni = np.minimum(stop, max(m - 1, 0))
        occ0 = (start > 0) & (pts.scan[pi] == seg_scan) & (pts.beam[pi] == b0 - 1)
        occ0 &= pts.r[pi] < r0 - occlusion_margin
        occ1 = (stop < m) & (pts.scan[ni] == seg_scan) & (pts.beam[ni] == b1 + 1)
        occ1 &= pts.r[ni] < r1 - occlusion_margin
    return Segments(
        pts,
        start,
        stop,
        seg_scan,
        occ0,
        occ1,
        b0 <= first_beam,
        b1 >= last,
    )


def concave_corners(segs: Segments, span: int = 2, depth: ArrayLike = 0.03) -> BoolArray:
    """Returns where a segment turns concave (seen from the sensor): the junction of two
    touching objects, where the segment is cut (ours, issue 11).

    The visible outline of one convex object (a trunk) is convex from the sensor; that of two
    touching convex objects (a trunk and a branch, a bush or a second stem merged into one
    segment by the segmentation) is convex except at their junction, which lies *behind* the
    chord of its neighbours. For return ``i`` of a segment with ``span`` returns on each side,
    its concave depth is its distance behind the chord from return ``i - span`` to
    ``i + span``, positive on the far side from the sensor (at the origin). A return is a
    corner when that depth exceeds ``depth`` and is a local maximum (``>=`` the previous,
    ``>`` the next return's depth).

    Parameters
    ----------
    segs : Segments
    span : int, >= 1
        Chord neighbour offset, returns.
    depth : float or array (M,), metres, > 0
        Least concave depth of a corner (above the range noise and bark roughness), one value
        or one per return (``inf``: no corner).

    Returns
    -------
    ndarray (M,), bool -- True at the returns that start a new piece
    (``segs.cut(np.cumsum(corners) % 2 == 1)`` cuts there; :mod:`stemmap.scan._corners` is
    the compiled twin, same arithmetic).
    """
    if span < 1:
        raise ConfigError(f"corner span must be >= 1 return, got {span}.")
    p = segs.points
    m = len(p)
    thr = np.broadcast_to(np.asarray(depth, dtype=np.float64), (m,))
    if not np.all(thr > 0):
        raise ConfigError(f"corner depth must be > 0 m, got {np.min(thr)}.")
    d = np.full(m, -np.inf)
    out = np.zeros(m, dtype=bool)
    if m == 0:
        return out
    lab = segs.labels
    i = np.arange(m)
    valid = (i - span >= segs.start[lab]) & (i + span < segs.stop[lab])
    iv = i[valid]
    a = iv - span
    c = iv + span
    cx = p.x[c] - p.x[a]
    cy = p.y[c] - p.y[a]
    side_p = cx * (p.y[iv] - p.y[a]) - cy * (p.x[iv] - p.x[a])
    side_o = cy * p.x[a] - cx * p.y[a]
    length = np.hypot(cx, cy)
    with np.errstate(invalid="ignore", divide="ignore"):
        dv = np.where(side_o > 0.0, -side_p, side_p) / length
    d[iv] = np.where(length > 0.0, dv, 0.0)
    prev = np.concatenate(([-np.inf], d[:-1]))
    nxt = np.concatenate((d[1:], [-np.inf]))
    # the neighbours of a valid return are in its segment (span >= 1)
    out[:] = (d > thr) & (d >= prev) & (d > nxt)
    return out


def largest_gap_cuts(
    segs: Segments, which: ArrayLike, ratio: float = 0.0, min_excess: ArrayLike = 0.0
) -> BoolArray:
    """The return after the largest gap (Euclidean distance between consecutive returns) of
    every segment where ``which`` (K,) is True and that has >= 2 returns (first maximum on
    ties), if that gap exceeds ``ratio`` x the median gap of the segment (the median of the
    sorted gaps, the mean of the middle two for an even count) and the median gap by more than
    ``min_excess`` (one value or one per segment, metres: above the range noise). Returns a bool
    (M,) that is
    True at the first return of each second piece (ours, issue 11: :func:`split_largest_gap`;
    ``_gaps.gap_cut_flags`` is the compiled twin)."""
    p = segs.points
    out = np.zeros(len(p), dtype=bool)
    w = np.asarray(which, dtype=bool) & (segs.counts >= 2)
    if not np.any(w):
        return out
    gap = np.hypot(np.diff(p.x), np.diff(p.y))
    excess = np.broadcast_to(np.asarray(min_excess, dtype=np.float64), (len(segs),))[w]
    for a, b, ex in zip(segs.start[w], segs.stop[w], excess, strict=True):
        g = gap[a : b - 1]
        k = int(np.argmax(g))
        srt = np.sort(g)
        h = srt.shape[0] // 2
        med = srt[h] if srt.shape[0] % 2 == 1 else 0.5 * (srt[h - 1] + srt[h])
        if g[k] > ratio * med and g[k] - med > ex:
            out[a + 1 + k] = True
    return out


def split_largest_gap(
    segs: Segments,
    which: ArrayLike,
    occlusion_margin: float,
    ratio: float = 0.0,
    min_excess: ArrayLike = 0.0,
) -> Segments:
    """Cut every segment where ``which`` is True at its largest gap between consecutive returns
    (ours, issue 11): a segment that is not a convex arc is often two objects side by side,
    a trunk and a stem, bush or branch behind or before it, that the (range-adaptive)
    segmentation threshold merged; the junction is where consecutive returns lie farthest
    apart. Unlike :meth:`Segments.cut`, a cut end is occluded only when the return across the
    cut is nearer by more than ``occlusion_margin`` (the rule of :func:`build_segments`): a
    trunk beside a farther object is whole. ``ratio``, ``min_excess``: see
    :func:`largest_gap_cuts`."""
    cuts = largest_gap_cuts(segs, which, ratio, min_excess)
    if not np.any(cuts):
        return segs
    out = segs.cut(np.cumsum(cuts) % 2 == 1)
    r = segs.points.r
    m = r.shape[0]
    occ_s = out.occluded_start.copy()
    inner = cuts[out.start]
    s = out.start[inner]
    occ_s[inner] = r[s - 1] < r[s] - occlusion_margin
    occ_e = out.occluded_end.copy()
    nxt = out.stop < m
    inner = np.zeros(len(out), dtype=bool)
    inner[nxt] = cuts[out.stop[nxt]]
    e = out.stop[inner]
    occ_e[inner] = r[e] < r[e - 1] - occlusion_margin
    return Segments(
        out.points,
        out.start,
        out.stop,
        out.scan,
        occ_s,
        occ_e,
        out.truncated_start,
        out.truncated_end,
    )
