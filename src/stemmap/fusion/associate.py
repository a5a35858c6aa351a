"""Laser regions of interest and their association with image regions through G.

* :func:`laser_rois` -- Xue et al. (2018) §2.2 and §2.4.2: three-neighbour median filter,
  segmentation at range jumps (the "change rate of polar radius"), chord width (eq. 12). Built
  on the scan-detect area's functions (stemmap.scan.preprocess / segment / features).
* :func:`associate` -- each laser RoI's returns are projected into the image with the laser-to-
  image matrix G (eq. 3); a laser RoI and an image region correspond when their column spans
  overlap (Xue §3.2.4 pairs A-D with regions 9, 8, 4, 1 this way); one-to-one by the Hungarian
  method on the 1D intersection-over-union.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from stemmap.errors import ConfigError, InputError
from stemmap.scan.features import segment_widths
from stemmap.scan.preprocess import median_filter3
from stemmap.scan.segment import build_segments, extract_points, range_jump_breaks
from stemmap.types import FloatArray, LaserScan
from stemmap.vision.camera import apply_homography
from stemmap.vision.segment import Regions

__all__ = ["Association", "LaserRois", "associate", "laser_rois", "project_rois"]


@dataclass(frozen=True, eq=False)
class LaserRois:
    """Clusters of consecutive laser returns (candidate trunks), columnar.

    Attributes
    ----------
    points : (M, 2) metres, laser frame -- all returns, RoI after RoI
    beam : (M,) int -- beam index of each return
    start, stop : (K,) int -- RoI k is ``points[start[k]:stop[k]]``
    widths : (K,) metres -- chord width of the edge beams (Xue eq. 12)
    ranges : (K,) metres -- median range of the RoI
    centers : (K, 2) metres -- approximate trunk centre: on the bearing bisecting the edge
        beams, at the nearest return's range plus half the width (the nearest point of a
        circle is at D - r)
    partial : (K,) bool -- an end is occluded by a nearer return or truncated by the field of
        view: the width is only a lower bound
    """

    points: FloatArray
    beam: NDArray[np.int64]
    start: NDArray[np.int64]
    stop: NDArray[np.int64]
    widths: FloatArray
    ranges: FloatArray
    centers: FloatArray
    partial: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self) -> None:
        if self.partial.shape[0] != self.start.shape[0]:
            object.__setattr__(self, "partial", np.zeros(self.start.shape[0], bool))

    def __len__(self) -> int:
        return int(self.start.shape[0])

    @property
    def n_points(self) -> NDArray[np.int64]:
        out: NDArray[np.int64] = self.stop - self.start
        return out

    @property
    def labels(self) -> NDArray[np.int64]:
        return np.repeat(np.arange(len(self), dtype=np.int64), self.n_points)

    def select(self, keep: ArrayLike) -> LaserRois:
        k = np.flatnonzero(np.asarray(keep))
        if np.asarray(keep).dtype != bool:
            k = np.asarray(keep, dtype=np.int64)
        counts = self.n_points[k]
        idx = (
            np.concatenate(
                [np.arange(a, b) for a, b in zip(self.start[k], self.stop[k], strict=True)]
            )
            if len(k)
            else np.zeros(0, np.int64)
        )
        stop = np.cumsum(counts).astype(np.int64)
        return LaserRois(
            self.points[idx],
            self.beam[idx],
            stop - counts,
            stop,
            self.widths[k],
            self.ranges[k],
            self.centers[k],
            self.partial[k],
        )


def laser_rois(
    scan: LaserScan,
    *,
    max_jump: float = 0.2,
    median: bool = True,
    min_points: int = 3,
    fov_deg: tuple[float, float] | None = None,
) -> LaserRois:
    """Candidate trunk regions of one scan (Xue 2018 §2.2, §2.4.2).

    Parameters
    ----------
    max_jump : float, metres -- range change that separates two objects (Zheng eq. 2 style)
    median : bool -- three-neighbour median filter first (Xue §2.2)
    min_points : int -- drop smaller clusters
    fov_deg : (lo, hi), optional -- keep beams in this bearing window (Xue used 60-120 deg of a
        0-180 deg scanner: the camera's view)
    """
    if not isinstance(scan, LaserScan):
        raise InputError(f"laser_rois needs a LaserScan, got {type(scan).__name__}.")
    if max_jump <= 0 or min_points < 2:
        raise ConfigError(f"need max_jump > 0 and min_points >= 2, got {max_jump}, {min_points}.")
    r = np.where(scan.valid, scan.ranges, np.inf)
    if median:
        r = np.where(np.isfinite(r), median_filter3(r), np.inf)
        r = np.where(np.isfinite(r) & (r > scan.range_min) & (r < scan.range_max), r, np.inf)
    ang = scan.angles
    if fov_deg is not None:
        lo, hi = np.radians(fov_deg)
        r = np.where((ang >= lo) & (ang <= hi), r, np.inf)
    pts = extract_points(r, ang, scan.angle_increment)
    empty = LaserRois(
        np.zeros((0, 2)),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros(0),
        np.zeros(0),
        np.zeros((0, 2)),
    )
    if len(pts) == 0:
        return empty
    segs = build_segments(pts, range_jump_breaks(pts, max_jump), ranges=r[None, :])
    keep = segs.counts >= min_points
    segs = segs.select(keep)
    if len(segs) == 0:
        return empty
    widths = segment_widths(segs)
    p = segs.points
    idx = np.concatenate([np.arange(a, b) for a, b in zip(segs.start, segs.stop, strict=True)])
    xy = np.column_stack((p.x[idx], p.y[idx]))
    counts = segs.counts
    stop = np.cumsum(counts).astype(np.int64)
    start = stop - counts
    lab = np.repeat(np.arange(len(segs)), counts)
    rr = np.hypot(xy[:, 0], xy[:, 1])
    med = np.array([np.median(rr[lab == k]) for k in range(len(segs))])
    e0 = xy[start]
    e1 = xy[stop - 1]
    mid = 0.5 * (e0 + e1)
    u = mid / np.maximum(np.hypot(mid[:, 0], mid[:, 1]), 1e-12)[:, None]
    rmin = np.minimum.reduceat(rr, start)
    centers = u * (rmin + widths / 2.0)[:, None]
    return LaserRois(xy, p.beam[idx], start, stop, widths, med, centers, segs.partial.copy())


def project_rois(rois: LaserRois, G: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Column span and row of each laser RoI in the image: (u_min, u_max, v_median), (K,) each.

    NaN for RoIs whose projection is undefined (behind the camera: w <= 0)."""
    K = len(rois)
    umin, umax, vmed = np.full(K, np.nan), np.full(K, np.nan), np.full(K, np.nan)
    if K == 0:
        return umin, umax, vmed
    H = np.asarray(G, dtype=np.float64)
    w = rois.points @ H[2, :2] + H[2, 2]
    uv = apply_homography(H, rois.points)
    front = w > 0
    lab = rois.labels
    for k in range(K):
        m = (lab == k) & front
        if m.sum() == (lab == k).sum() and m.any():
            umin[k] = uv[m, 0].min()
            umax[k] = uv[m, 0].max()
            vmed[k] = np.median(uv[m, 1])
    return umin, umax, vmed


@dataclass(frozen=True, eq=False)
class Association:
    """Pairs (P, 2) of (laser RoI, region) indices, their 1D IoU, and the unmatched of each."""

    pairs: NDArray[np.int64]
    iou: FloatArray
    laser_only: NDArray[np.int64]
    vision_only: NDArray[np.int64]


def associate(
    rois: LaserRois,
    regions: Regions,
    G: ArrayLike,
    *,
    image_width: int | None = None,
    min_iou: float = 0.2,
) -> Association:
    """Match laser RoIs to image regions by the overlap of their column spans (via G).

    Laser RoIs that project outside ``[0, image_width)`` (or behind the camera) are neither
    matched nor listed as laser-only: the camera cannot judge them.
    """
    if not 0.0 < min_iou <= 1.0:
        raise ConfigError(f"min_iou must be in (0, 1], got {min_iou}.")
    umin, umax, _ = project_rois(rois, G)
    inside = np.isfinite(umin)
    if image_width is not None:
        inside &= (umax >= 0) & (umin < image_width)
    li = np.flatnonzero(inside)
    R = len(regions)
    if len(li) == 0 or R == 0:
        return Association(
            np.zeros((0, 2), np.int64),
            np.zeros(0),
            li.astype(np.int64),
            np.arange(R, dtype=np.int64),
        )
    a0, a1 = umin[li, None], umax[li, None] + 1.0
    b0 = regions.x[None, :].astype(np.float64)
    b1 = b0 + regions.w[None, :]
    inter = np.clip(np.minimum(a1, b1) - np.maximum(a0, b0), 0.0, None)
    union = np.maximum(a1, b1) - np.minimum(a0, b0)
    iou = inter / np.maximum(union, 1e-9)
    rows, cols = linear_sum_assignment(-iou)
    ok = iou[rows, cols] >= min_iou
    pairs = np.column_stack((li[rows[ok]], cols[ok])).astype(np.int64)
    laser_only = np.setdiff1d(li, pairs[:, 0]).astype(np.int64)
    vision_only = np.setdiff1d(np.arange(R), pairs[:, 1]).astype(np.int64)
    return Association(pairs, iou[rows[ok], cols[ok]], laser_only, vision_only)
