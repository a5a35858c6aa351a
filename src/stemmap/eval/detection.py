"""Detection metrics: detections vs ground-truth trees (and non-tree objects).

Definitions (Munjer et al. 2025, §4, after their reference [15]):

* **TA** (true accept): a tree that was detected -- a detection matched one-to-one to a truth
  tree within ``gate`` (Hungarian assignment, :func:`~stemmap.eval.matching.match_points`).
* **FA** (false accept): a detection not matched to any truth tree (a non-tree object or
  nothing classified as a tree).
* **FR** (false reject): a truth tree that was not detected.
* **TR** (true reject): a non-tree object that was correctly not reported as a tree: no
  unmatched detection lies within ``gate + extent`` of its centre. Needs the list of non-tree
  objects (``Stand.clutter_objects_xy``); without it TR is 0 and reported as such.

Precision = TA / (TA + FA), recall = TA / (TA + FR), F1 their harmonic mean, accuracy =
(TA + TR) / (TA + TR + FA + FR) (Munjer 2025 Table 2: EB-LiDAR 6, 2, 1, 0 -> 0.89); undefined
values are NaN (never 0). Centre error and diameter error are over TA pairs; diameter error is
``estimate - truth`` (bias > 0 = overestimate), reported overall and per range bin, the way
Öhman et al. 2007 §2.3 report diameter error growing with measurement distance.

"Don't care" truth: trees flagged not eligible (e.g. fewer than 5 returns, too far, too thin)
may be matched -- such a match is neither TA nor FA -- but are never counted as FR.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError
from stemmap.eval.matching import Matching, match_points
from stemmap.types import FloatArray, StemObservations

if TYPE_CHECKING:
    from stemmap.sim.trajectory import SimRun

__all__ = [
    "DEFAULT_RANGE_BINS",
    "DetectionMetrics",
    "RangeBinMetrics",
    "detectable_trees",
    "detection_metrics",
    "scan_detection_metrics",
    "score_scan_detections",
]

#: Range-bin edges (m) used by default: the issue's targets are set at <= 5 m and 5-10 m.
DEFAULT_RANGE_BINS: tuple[float, ...] = (0.0, 5.0, 10.0, 15.0, math.inf)


def _nan_to_none(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 else math.nan


def _rmse(x: FloatArray) -> float:
    return float(np.sqrt(np.mean(x * x))) if x.size else math.nan


def _mean(x: FloatArray) -> float:
    return float(np.mean(x)) if x.size else math.nan


@dataclass(frozen=True)
class RangeBinMetrics:
    """Metrics of the truth trees whose range falls in ``[range_lo, range_hi)`` (metres)."""

    range_lo: float
    range_hi: float
    n_truth: int
    ta: int
    fr: int
    recall: float
    center_rmse: float
    diameter_rmse: float
    diameter_bias: float

    def to_dict(self) -> dict[str, Any]:
        return {k: _nan_to_none(v) for k, v in self.__dict__.items()}


@dataclass(frozen=True, eq=False)
class DetectionMetrics:
    """Result of :func:`detection_metrics` / :func:`scan_detection_metrics`.

    Counts are integers; rates and errors are floats in metres (NaN where undefined).
    ``matching`` holds the last frame's assignment (single-frame use) or None (pooled);
    ``frame_counts`` (F, 3) holds (TA, FA, FR) of every frame, for per-scan recall.
    """

    gate: float
    ta: int
    fa: int
    fr: int
    tr: int
    n_detections: int
    n_truth_eligible: int
    n_ignored: int
    n_nontree: int
    precision: float
    recall: float
    f1: float
    center_rmse: float
    center_mean: float
    diameter_rmse: float
    diameter_bias: float
    diameter_mae: float
    by_range: tuple[RangeBinMetrics, ...] = ()
    n_frames: int = 1
    matching: Matching | None = field(default=None, repr=False)
    frame_counts: NDArray[np.int64] | None = field(default=None, repr=False)

    @property
    def accuracy(self) -> float:
        """(TA + TR) / (TA + TR + FA + FR), Munjer et al. 2025 §4 after their ref. [15]."""
        return _ratio(self.ta + self.tr, self.ta + self.tr + self.fa + self.fr)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (NaN -> None); lengths in metres."""
        out = {
            k: _nan_to_none(v)
            for k, v in self.__dict__.items()
            if k not in ("by_range", "matching", "frame_counts")
        }
        out["accuracy"] = _nan_to_none(self.accuracy)
        out["by_range"] = [b.to_dict() for b in self.by_range]
        return out


@dataclass
class _Pooled:
    """Per-pair and per-miss records pooled over frames."""

    center_err: list[FloatArray] = field(default_factory=list)
    diam_err: list[FloatArray] = field(default_factory=list)
    pair_range: list[FloatArray] = field(default_factory=list)
    miss_range: list[FloatArray] = field(default_factory=list)
    fa: int = 0
    tr: int = 0
    n_det: int = 0
    n_ignored: int = 0
    n_nontree: int = 0
    n_frames: int = 0
    last: Matching | None = None
    counts: list[tuple[int, int, int]] = field(default_factory=list)

    def add_frame(
        self,
        det_xy: FloatArray,
        det_diam: FloatArray,
        truth_xy: FloatArray,
        truth_diam: FloatArray,
        eligible: NDArray[np.bool_],
        truth_range: FloatArray,
        gate: float,
        nontree_xy: FloatArray,
        nontree_extent: FloatArray,
        scored_within: float = math.inf,
    ) -> None:
        m = match_points(det_xy, truth_xy, gate)
        di, ti = m.pairs[:, 0], m.pairs[:, 1]
        ok = eligible[ti]
        self.n_ignored += int(np.sum(~ok))
        di, ti = di[ok], ti[ok]
        self.center_err.append(np.hypot(*(det_xy[di] - truth_xy[ti]).T))
        self.diam_err.append(det_diam[di] - truth_diam[ti])
        self.pair_range.append(truth_range[ti])
        not_found = eligible.copy()
        not_found[ti] = False
        missed = np.flatnonzero(not_found)
        self.miss_range.append(truth_range[missed])
        fa_idx = m.unmatched_detections
        # an unmatched detection outside the scored domain is not a false alarm, as a match
        # to an ineligible tree is not a true one (score_scan_detections)
        far = np.hypot(*det_xy[fa_idx].T) > scored_within if fa_idx.size else np.zeros(0, bool)
        self.n_ignored += int(np.sum(far))
        self.fa += int(fa_idx.size - np.sum(far))
        self.n_det += int(det_xy.shape[0])
        if nontree_xy.shape[0]:
            if fa_idx.size:
                d = np.hypot(*(nontree_xy[:, None, :] - det_xy[fa_idx][None]).transpose(2, 0, 1))
                claimed = np.any(d <= gate + nontree_extent[:, None], axis=1)
            else:
                claimed = np.zeros(nontree_xy.shape[0], dtype=bool)
            self.tr += int(np.sum(~claimed))
            self.n_nontree += int(nontree_xy.shape[0])
        self.n_frames += 1
        self.last = m
        self.counts.append((int(di.size), int(fa_idx.size), int(missed.size)))

    def summary(self, gate: float, bins: Sequence[float]) -> DetectionMetrics:
        ce = np.concatenate(self.center_err) if self.center_err else np.zeros(0)
        de = np.concatenate(self.diam_err) if self.diam_err else np.zeros(0)
        pr = np.concatenate(self.pair_range) if self.pair_range else np.zeros(0)
        mr = np.concatenate(self.miss_range) if self.miss_range else np.zeros(0)
        ta, fr = int(ce.size), int(mr.size)
        precision = _ratio(ta, ta + self.fa)
        recall = _ratio(ta, ta + fr)
        f1 = (
            2 * precision * recall / (precision + recall)
            if math.isfinite(precision) and math.isfinite(recall) and precision + recall > 0
            else math.nan
        )
        by_range = []
        for lo, hi in itertools.pairwise(bins):
            inp = (pr >= lo) & (pr < hi)
            inm = (mr >= lo) & (mr < hi)
            n_ta, n_fr = int(inp.sum()), int(inm.sum())
            by_range.append(
                RangeBinMetrics(
                    range_lo=float(lo),
                    range_hi=float(hi),
                    n_truth=n_ta + n_fr,
                    ta=n_ta,
                    fr=n_fr,
                    recall=_ratio(n_ta, n_ta + n_fr),
                    center_rmse=_rmse(ce[inp]),
                    diameter_rmse=_rmse(de[inp]),
                    diameter_bias=_mean(de[inp]),
                )
            )
        return DetectionMetrics(
            gate=gate,
            ta=ta,
            fa=self.fa,
            fr=fr,
            tr=self.tr,
            n_detections=self.n_det,
            n_truth_eligible=ta + fr,
            n_ignored=self.n_ignored,
            n_nontree=self.n_nontree,
            precision=precision,
            recall=recall,
            f1=f1,
            center_rmse=_rmse(ce),
            center_mean=_mean(ce),
            diameter_rmse=_rmse(de),
            diameter_bias=_mean(de),
            diameter_mae=_mean(np.abs(de)),
            by_range=tuple(by_range),
            n_frames=self.n_frames,
            matching=self.last if self.n_frames == 1 else None,
            frame_counts=np.asarray(self.counts, dtype=np.int64).reshape(-1, 3),
        )


def _xy(a: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 2))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"{name} must have shape (N, 2) in metres, got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contains NaN or inf positions.")
    return arr


def _vec(a: ArrayLike, n: int, name: str) -> FloatArray:
    arr = np.asarray(a, dtype=np.float64).reshape(-1)
    if arr.shape[0] != n:
        raise InputError(f"{name} has {arr.shape[0]} values but {n} positions were given.")
    return arr


def _bins(range_bins: Sequence[float]) -> tuple[float, ...]:
    b = tuple(float(x) for x in range_bins)
    if len(b) < 2 or any(not (hi > lo) for lo, hi in itertools.pairwise(b)):
        raise InputError(f"range_bins must be >= 2 strictly increasing edges, got {b}.")
    return b


def detection_metrics(
    det_xy: ArrayLike,
    det_diam: ArrayLike,
    truth_xy: ArrayLike,
    truth_diam: ArrayLike,
    *,
    gate: float,
    truth_eligible: ArrayLike | None = None,
    sensor_xy: ArrayLike | None = None,
    truth_range: ArrayLike | None = None,
    range_bins: Sequence[float] = DEFAULT_RANGE_BINS,
    nontree_xy: ArrayLike | None = None,
    nontree_extent: ArrayLike | None = None,
) -> DetectionMetrics:
    """Score one set of detections against ground truth (one frame or one map).

    Parameters
    ----------
    det_xy : array_like of shape (D, 2), metres
    det_diam : array_like of shape (D,), metres
    truth_xy : array_like of shape (T, 2), metres, same frame as ``det_xy``
    truth_diam : array_like of shape (T,), metres
    gate : float, metres, > 0
        Maximum centre distance of a match.
    truth_eligible : array_like of shape (T,), bool, optional
        Truth trees that count (default all). Matches to ineligible trees are ignored; missed
        ineligible trees are not false rejects. See :func:`detectable_trees`.
    sensor_xy : array_like of shape (2,), optional
        Sensor position; truth ranges for the range bins are measured from it.
    truth_range : array_like of shape (T,), optional
        Truth ranges given directly (overrides ``sensor_xy``). Default: ranges from the origin.
    range_bins : sequence of float
        Bin edges (m) for :attr:`DetectionMetrics.by_range`.
    nontree_xy : array_like of shape (K, 2), optional
        Centres of non-tree objects (for TR); ``nontree_extent`` (K,) their radii (default 0).

    Returns
    -------
    DetectionMetrics

    Raises
    ------
    InputError
        On mismatched lengths, non-finite positions or a non-positive gate.

    References
    ----------
    .. [1] M. A. Munjer, T. C. Jie, E. Hayashi, "Comparative Analysis of LiDAR-Based and
       Depth-Assisted Image-Based Tree Mapping for Autonomous Forestry Robots", 2025, §4.
    .. [2] M. Öhman et al., Forestrix, 2007, §2.3 (diameter error by measurement range).

    Examples
    --------
    >>> m = detection_metrics([[0, 0], [5, 5]], [0.3, 0.2], [[0.1, 0], [9, 9]], [0.28, 0.3],
    ...                       gate=0.5)
    >>> (m.ta, m.fa, m.fr), round(m.diameter_bias, 3)
    ((1, 1, 1), 0.02)
    """
    if not (gate > 0 and math.isfinite(gate)):
        raise InputError(f"gate must be a finite distance > 0 m, got {gate}.")
    dxy = _xy(det_xy, "det_xy")
    ddi = _vec(det_diam, dxy.shape[0], "det_diam")
    txy = _xy(truth_xy, "truth_xy")
    tdi = _vec(truth_diam, txy.shape[0], "truth_diam")
    n_t = txy.shape[0]
    elig = (
        np.ones(n_t, dtype=bool)
        if truth_eligible is None
        else np.asarray(truth_eligible, dtype=bool).reshape(-1)
    )
    if elig.shape[0] != n_t:
        raise InputError(f"truth_eligible has {elig.shape[0]} flags for {n_t} truth trees.")
    if truth_range is not None:
        rng_t = _vec(truth_range, n_t, "truth_range")
    else:
        s = np.zeros(2) if sensor_xy is None else np.asarray(sensor_xy, dtype=np.float64)
        rng_t = np.hypot(*(txy - s.reshape(2)).T) if n_t else np.zeros(0)
    nxy = _xy(nontree_xy, "nontree_xy") if nontree_xy is not None else np.zeros((0, 2))
    next_ = (
        np.zeros(nxy.shape[0])
        if nontree_extent is None
        else _vec(nontree_extent, nxy.shape[0], "nontree_extent")
    )
    pool = _Pooled()
    pool.add_frame(dxy, ddi, txy, tdi, elig, rng_t, float(gate), nxy, next_)
    return pool.summary(float(gate), _bins(range_bins))


def detectable_trees(
    hit_ids: ArrayLike,
    n_trees: int,
    *,
    min_returns: int = 5,
    truth_range: ArrayLike | None = None,
    max_range: float | None = None,
    diameters: ArrayLike | None = None,
    min_diameter: float | None = None,
) -> NDArray[np.bool_]:
    """Which truth trees a scan could detect: >= ``min_returns`` beams hit them, within range.

    Parameters
    ----------
    hit_ids : array_like of shape (N,) or (S, N), int
        Per-beam ground truth from the simulator (tree index, negatives for non-trees).
    n_trees : int
    min_returns : int
        Minimum number of beams on the trunk.
    truth_range : array_like of shape (T,) or (S, T), optional
        Sensor-to-tree distance (m); with ``max_range``, farther trees are not detectable.
    diameters : array_like of shape (T,), optional
        With ``min_diameter`` (m), thinner trees are not detectable.

    Returns
    -------
    ndarray of bool, shape (T,) or (S, T)
    """
    h = np.asarray(hit_ids)
    if not np.issubdtype(h.dtype, np.integer):
        raise InputError(f"hit_ids must be integers, got dtype {h.dtype}.")
    single = h.ndim == 1
    h2 = h.reshape(1, -1) if single else h
    if h2.ndim != 2:
        raise InputError(f"hit_ids must have shape (N,) or (S, N), got {h.shape}.")
    s = h2.shape[0]
    if h2.size and h2.max() >= n_trees:
        raise InputError(f"hit_ids names tree {int(h2.max())} but there are {n_trees} trees.")
    rows = np.repeat(np.arange(s), h2.shape[1])
    flat = h2.reshape(-1)
    tree = flat >= 0
    counts = np.bincount(rows[tree] * n_trees + flat[tree], minlength=s * n_trees).reshape(
        s, n_trees
    )
    ok = counts >= min_returns
    if max_range is not None and truth_range is not None:
        r = np.asarray(truth_range, dtype=np.float64).reshape(-1, n_trees)
        ok &= r <= max_range
    if min_diameter is not None and diameters is not None:
        ok &= np.asarray(diameters, dtype=np.float64).reshape(1, n_trees) >= min_diameter
    return ok[0] if single else ok


def scan_detection_metrics(
    detections: StemObservations,
    run: SimRun,
    *,
    gate: float = 0.5,
    min_returns: int = 5,
    max_range: float = 15.0,
    min_diameter: float = 0.10,
    range_bins: Sequence[float] = DEFAULT_RANGE_BINS,
) -> DetectionMetrics:
    """Per-scan detection metrics pooled over every scan of a simulated run.

    For each scan the truth trees are moved into the sensor frame; a tree counts (is
    eligible) if it is detectable in that scan (:func:`detectable_trees`: ``>= min_returns``
    beams, within ``max_range``, DBH ``>= min_diameter``). Non-tree objects count for TR if
    their centre is within ``max_range`` and inside the scanner's field of view.

    The scored domain is the same for both sides of precision: a detection matched to a tree
    that is not eligible is ignored (neither TA nor FA), and so is an unmatched detection
    whose centre lies beyond ``max_range + gate`` from the sensor (the farthest a match to an
    eligible tree can lie); both are counted in ``n_ignored``. Unmatched detections within it
    are false alarms. (Before Dec 5 an unmatched detection counted as a false alarm at any
    range while a correct one beyond ``max_range`` was ignored; the benchmark drive of
    benchmarks/scan_detection.py already dropped detections beyond 15.5 m, so only the demo
    drive's scores change: docs/algorithms/sim-eval.md.)

    Parameters
    ----------
    detections : StemObservations
        Detections in the sensor frame; ``index`` is the scan index.
    run : SimRun
    gate, min_returns, max_range, min_diameter, range_bins : see above and
        :func:`detection_metrics`.

    Returns
    -------
    DetectionMetrics
        Pooled counts and errors; ``n_frames`` is the number of scans; ``frame_counts``
        holds (TA, FA, FR) per scan.
    """
    sc = run.scanner
    return score_scan_detections(
        detections,
        trees_xy=run.stand.trees_xy,
        diameters=run.stand.diameters,
        sensor_poses=run.true_poses.poses,
        hit_ids=run.hit_ids,
        nontree_xy=run.stand.clutter_objects_xy,
        nontree_extent=run.stand.clutter_objects_extent,
        fov=(sc.angle_min, sc.angle_max, sc.angle_increment),
        gate=gate,
        min_returns=min_returns,
        max_range=max_range,
        min_diameter=min_diameter,
        range_bins=range_bins,
    )


def score_scan_detections(
    detections: StemObservations,
    *,
    trees_xy: ArrayLike,
    diameters: ArrayLike,
    sensor_poses: ArrayLike,
    hit_ids: ArrayLike,
    nontree_xy: ArrayLike | None = None,
    nontree_extent: ArrayLike | None = None,
    fov: tuple[float, float, float] | None = None,
    gate: float = 0.5,
    min_returns: int = 5,
    max_range: float = 15.0,
    min_diameter: float = 0.10,
    range_bins: Sequence[float] = DEFAULT_RANGE_BINS,
) -> DetectionMetrics:
    """:func:`scan_detection_metrics` on plain arrays (e.g. read back from ``stemmap sim`` files).

    Parameters
    ----------
    detections : StemObservations
        Sensor-frame detections; ``index`` is the scan index.
    trees_xy : array_like of shape (T, 2), world frame, metres
    diameters : array_like of shape (T,), metres
    sensor_poses : array_like of shape (S, 3)
        True sensor pose (x, y, theta) of every scan, world frame.
    hit_ids : array_like of shape (S, N), int
        Per-beam ground truth (tree index, negatives for non-trees / nothing).
    nontree_xy, nontree_extent : array_like of shape (K, 2), (K,), optional
        Non-tree objects (world frame) for true rejects.
    fov : (angle_min, angle_max, angle_increment), radians, optional
        Scanner field of view: non-tree objects outside it are not counted. ``None``: 360°.
    gate, min_returns, max_range, min_diameter, range_bins
        As in :func:`scan_detection_metrics`.
    """
    if not (gate > 0 and math.isfinite(gate)):
        raise InputError(f"gate must be a finite distance > 0 m, got {gate}.")
    txy = _xy(trees_xy, "trees_xy")
    tdiam = _vec(diameters, txy.shape[0], "diameters")
    poses = np.asarray(sensor_poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise InputError(f"sensor_poses must have shape (S, 3), got {poses.shape}.")
    hits = np.asarray(hit_ids)
    n_s = poses.shape[0]
    if hits.ndim != 2 or hits.shape[0] != n_s:
        raise InputError(f"hit_ids must have shape (S, N) with S = {n_s} scans, got {hits.shape}.")
    if len(detections) and (detections.index.min() < 0 or detections.index.max() >= n_s):
        raise InputError(
            f"detection scan indices must lie in [0, {n_s}), got "
            f"[{detections.index.min()}, {detections.index.max()}]."
        )
    nxy = _xy(nontree_xy, "nontree_xy") if nontree_xy is not None else np.zeros((0, 2))
    next_ = (
        np.zeros(nxy.shape[0])
        if nontree_extent is None
        else _vec(nontree_extent, nxy.shape[0], "nontree_extent")
    )
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])

    def to_sensor(xy: FloatArray) -> FloatArray:
        d = xy[None, :, :] - poses[:, None, :2]  # (S, T, 2)
        return np.stack(
            (
                c[:, None] * d[..., 0] + s[:, None] * d[..., 1],
                -s[:, None] * d[..., 0] + c[:, None] * d[..., 1],
            ),
            axis=-1,
        )

    t_local = to_sensor(txy)
    t_range = np.hypot(t_local[..., 0], t_local[..., 1])
    eligible = detectable_trees(
        hits,
        txy.shape[0],
        min_returns=min_returns,
        truth_range=t_range,
        max_range=max_range,
        diameters=tdiam,
        min_diameter=min_diameter,
    )
    o_local = to_sensor(nxy)
    o_range = np.hypot(o_local[..., 0], o_local[..., 1])
    if fov is None:
        in_fov = np.ones(o_range.shape, dtype=bool)
    else:
        a_min, a_max, a_inc = fov
        o_bear = np.arctan2(o_local[..., 1], o_local[..., 0])
        in_fov = (o_bear >= a_min) & (o_bear <= a_max) | (
            a_max - a_min >= 2 * math.pi - 2 * abs(a_inc)
        )
    o_ok = (o_range <= max_range) & in_fov
    order = np.argsort(detections.index, kind="stable")
    starts = np.searchsorted(detections.index[order], np.arange(n_s + 1))
    bins = _bins(range_bins)
    pool = _Pooled()
    for k in range(n_s):
        sel = order[starts[k] : starts[k + 1]]
        pool.add_frame(
            detections.centers[sel],
            detections.diameters[sel],
            t_local[k],
            tdiam,
            eligible[k],
            t_range[k],
            float(gate),
            o_local[k][o_ok[k]],
            next_[o_ok[k]],
            scored_within=float(max_range + gate),
        )
    return pool.summary(float(gate), bins)
