"""Forestry products from stems found in a cloud: stem profile, stem volume, per-tree point
labels and the plot summary (what 3DFin, FSCT, TreeLS and ITSMe users expect).

* :func:`stem_profiles` -- diameter every 0.5 m up (and down to 0.5 m) the visible stem, with
  its 1-sigma from the fit covariance, tracking the stem's centre from one level to the next.
* :func:`stem_volume` -- volume of the stem from its profile (Smalian's formula per section)
  plus a cone from the last measured section to the tree top when the height is known.
* :func:`tree_labels` -- a tree id per point: the nearest stem axis in the horizontal plane.
* :func:`plot_summary` -- stems/ha, basal area m2/ha, quadratic mean diameter, DBH histogram.

Heights are measured from each stem's base, ``z - dbh_height`` of :class:`CloudStems` (the
ground under the stem, or a ground-less tree's lowest stem points).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.cloud.canonical import canonical_order
from stemmap.cloud.result import CloudStems
from stemmap.cloud.slicefit import _fit_segments, _segment_arcs, _segment_covariances
from stemmap.errors import ConfigError
from stemmap.types import FloatArray

__all__ = [
    "StemProfile",
    "occupied_area",
    "plot_summary",
    "stem_profiles",
    "stem_volume",
    "tree_labels",
]

log = logging.getLogger(__name__)

PROFILE_STEP = 0.5  # m between profile levels (3DFin, FSCT: 0.5 m sections)
PROFILE_HALF = 0.1  # m, half thickness of a profile slice
PROFILE_MIN_POINTS = 8
PROFILE_MIN_ARC = 60.0  # deg: a narrower arc does not fix a diameter to a centimetre
PROFILE_MAX_MISSES = 2  # consecutive failed levels that end the visible stem


@dataclass(frozen=True)
class StemProfile:
    """Diameters up one stem.

    Attributes
    ----------
    tree : int -- row of the stem in its CloudStems
    height : ndarray (L,), m above the stem's base
    diameter, diameter_std : ndarray (L,), m
    xy : ndarray (L, 2), m -- centre of each section (cloud frame)
    """

    tree: int
    height: FloatArray
    diameter: FloatArray
    diameter_std: FloatArray
    xy: FloatArray


def _bases(stems: CloudStems) -> FloatArray:
    """Absolute z of each stem's base: the breast-height cross-section's z minus its height."""
    h = np.where(np.isfinite(stems.dbh_height), stems.dbh_height, 1.3)
    return np.asarray(stems.z - h, dtype=np.float64)


def _nearest_stem(xy: FloatArray, stems: CloudStems, max_dist: float) -> NDArray[np.int64]:
    from scipy.spatial import cKDTree

    if len(stems) == 0 or xy.shape[0] == 0:
        return np.full(xy.shape[0], -1, dtype=np.int64)
    d, i = cKDTree(stems.xy).query(xy, k=1)
    return np.where(d <= max_dist, i, -1).astype(np.int64)


def stem_profiles(
    xyz: ArrayLike,
    stems: CloudStems,
    *,
    step: float = PROFILE_STEP,
    reach: float = 3.0,
) -> list[StemProfile]:
    """Diameter every ``step`` metres along each stem, as far as the stem is seen.

    Each point goes to the nearest stem (breast-height centre) within ``reach`` metres, and
    gets its height above that stem's base. Levels ``step, 2 step, ...`` are fitted in turn
    from breast height upwards (and downwards to ``step``): a slice of +-0.1 m around the
    level, the points within ``r + max(r, 0.15 m)`` of the centre found at the previous level
    (a leaning stem is followed), the robust circle fit of the band slices
    (:func:`~stemmap.cloud.slicefit._fit_segments`) with its covariance
    (:func:`~stemmap.cloud.slicefit._segment_covariances`). A level is kept when it has
    >= 8 inliers over >= 60 degrees, a residual RMS below 3 x the stem's band RMS (or 2 % of
    r) and a radius between 0.5 and 1.2 x the previous one plus 1 cm going up (a stem narrows
    upward; a branch whorl or the crown does not look like the next section), up to 2 x the
    breast-height radius going down (root flare). Two failed levels in a row end the visible
    stem.
    """
    if not step > 0:
        raise ConfigError(f"profile step must be > 0 m, got {step}.")
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    k = len(stems)
    if k == 0:
        return []
    owner = _nearest_stem(p[:, :2], stems, reach)
    sel = owner >= 0
    p, owner = p[sel], owner[sel]
    hrel = p[:, 2] - _bases(stems)[owner]
    bh = np.where(np.isfinite(stems.dbh_height), stems.dbh_height, 1.3)
    top = float(np.nanmax(hrel)) if hrel.size else 0.0
    levels = np.arange(step, top + step, step)
    if levels.size == 0:
        return [StemProfile(j, *(np.zeros(0),) * 3, np.zeros((0, 2))) for j in range(k)]
    rows: dict[int, dict[float, tuple[float, float, float, float]]] = {j: {} for j in range(k)}
    band_rms = np.where(np.isfinite(stems.rms), stems.rms, 0.01)
    # upwards from the level nearest breast height, then downwards from it
    start = np.argmin(np.abs(levels[None, :] - bh[:, None]), axis=1)
    for direction in (1, -1):
        cen = stems.xy.copy()
        rad = stems.diameter / 2
        misses = np.zeros(k, dtype=np.int64)
        alive = np.ones(k, dtype=bool)
        li = start.copy() if direction == 1 else start - 1
        while alive.any():
            alive &= (li >= 0) & (li < levels.size)
            if not alive.any():
                break
            lev = np.where(alive, levels[np.clip(li, 0, levels.size - 1)], np.nan)
            m = alive[owner] & (np.abs(hrel - lev[owner]) <= PROFILE_HALF)
            d = np.hypot(*(p[m, :2] - cen[owner[m]]).T)
            reach_s = rad + np.maximum(rad, 0.15)
            near = d <= reach_s[owner[m]]
            idx = np.flatnonzero(m)[near]
            # the level's points in an order of their own (x, y, z), not the file's: the
            # fits' RANSAC draws and sums follow it (stemmap.cloud.canonical)
            idx = idx[canonical_order(p[idx, 0], p[idx, 1], p[idx, 2])]
            ids = owner[idx]
            c, r, rms, ok, nin = _fit_segments(
                p[idx, :2],
                ids,
                k,
                "ours",
                ransac_tol=0.005,
                radius_window=(0.01, 1.0),
            )
            cov = _segment_covariances(p[idx, :2], ids, k, c, r, rms)
            arcs = _segment_arcs(p[idx, :2], ids, k, np.where(ok[:, None], c, 0.0))
            good = (
                alive
                & ok
                & (nin >= PROFILE_MIN_POINTS)
                & (arcs >= PROFILE_MIN_ARC)
                & (rms <= np.maximum(3 * band_rms, 0.02 * r))
                & (r >= 0.5 * rad)
                & (r <= (1.2 if direction == 1 else 2.0) * rad + 0.01)
                & (np.hypot(*(c - cen).T) <= rad)
            )
            for jj in np.flatnonzero(good):
                j = int(jj)
                sd = 2 * math.sqrt(cov[j, 2, 2]) if np.isfinite(cov[j, 2, 2]) else math.nan
                rows[j][float(lev[j])] = (2 * float(r[j]), sd, float(c[j, 0]), float(c[j, 1]))
            cen = np.where(good[:, None], c, cen)
            if direction == 1:
                rad = np.where(good, r, rad)
            misses = np.where(good, 0, misses + alive)
            alive &= misses < PROFILE_MAX_MISSES
            li += direction
    out = []
    for t in range(k):
        hs = np.array(sorted(rows[t]))
        vals = np.array([rows[t][h] for h in hs]).reshape(-1, 4)
        out.append(StemProfile(t, hs, vals[:, 0], vals[:, 1], vals[:, 2:4]))
    return out


def stem_volume(profile: StemProfile, height: float = math.nan) -> tuple[float, float]:
    """Stem volume (m3) from a profile, and the height (m) up to which it was measured.

    Smalian's formula per section between measured levels, ``L (A_i + A_{i+1}) / 2`` with
    ``A = pi d^2 / 4``; from the ground to the first level a cylinder of the first diameter
    (the stump); above the last level, when the tree height is known, a cone to the top.
    Returns (NaN, 0) without any level.
    """
    h, d = profile.height, profile.diameter
    if h.size == 0:
        return math.nan, 0.0
    a = math.pi * d**2 / 4
    v = float(a[0] * h[0])
    if h.size > 1:
        v += float(np.sum(np.diff(h) * (a[1:] + a[:-1]) / 2))
    if math.isfinite(height) and height > h[-1]:
        v += float(a[-1] * (height - h[-1]) / 3)
    return v, float(h[-1])


def tree_labels(xyz: ArrayLike, stems: CloudStems, *, reach: float = 10.0) -> NDArray[np.int32]:
    """Tree id per point: 1 + the row of the nearest stem in the horizontal plane within
    ``reach`` metres (a Voronoi partition of the plot by stem positions), 0 for points below
    0.3 m above that stem's base (ground, litter) or farther than ``reach``.

    A crown that reaches past the midline to its neighbour is cut at the midline: this is a
    stem-based partition, not a crown segmentation.
    """
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    owner = _nearest_stem(p[:, :2], stems, reach)
    lab = owner + 1
    if len(stems):
        low = owner >= 0
        base = _bases(stems)
        lab[low] = np.where(p[low, 2] - base[owner[low]] < 0.3, 0, lab[low])
    return lab.astype(np.int32)


def plot_summary(
    stems: CloudStems,
    area_m2: float,
    *,
    bin_width: float = 0.05,
    area_method: str = "",
) -> dict[str, Any]:
    """Plot statistics from the stems' DBH.

    ``stems_per_ha = n / area * 1e4``; ``basal_area_m2_ha = sum(pi dbh^2 / 4) / area * 1e4``;
    ``qmd_m = sqrt(sum dbh^2 / n)`` (quadratic mean diameter); a DBH histogram with
    ``bin_width`` (m) bins from 0. ``area_m2`` is the plot's ground area.
    """
    if not area_m2 > 0:
        raise ConfigError(f"plot area must be > 0 m2, got {area_m2}.")
    d = stems.diameter[np.isfinite(stems.diameter)]
    n = int(d.size)
    edges = np.arange(0.0, (float(d.max()) if n else 0.0) + bin_width + 1e-9, bin_width)
    counts, _ = np.histogram(d, bins=edges)
    return {
        "n_stems": n,
        "area_m2": round(float(area_m2), 2),
        "area_method": area_method,
        "stems_per_ha": round(n / area_m2 * 1e4, 1),
        "basal_area_m2_ha": round(float(np.sum(math.pi * d**2 / 4)) / area_m2 * 1e4, 3),
        "qmd_m": round(math.sqrt(float(np.mean(d**2))), 4) if n else None,
        "mean_dbh_m": round(float(np.mean(d)), 4) if n else None,
        "dbh_histogram": {
            "bin_edges_m": [round(float(e), 3) for e in edges],
            "counts": [int(c) for c in counts],
        },
    }


def occupied_area(xy: ArrayLike, cell: float = 1.0) -> float:
    """Ground area (m2) of the ``cell`` x ``cell`` cells holding points: the plot's footprint,
    whatever its shape (a circular plot is not its bounding box)."""
    q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if q.shape[0] == 0:
        return 0.0
    ij = np.floor(q / cell).astype(np.int64)
    return float(np.unique(ij, axis=0).shape[0]) * cell * cell
