"""Girth (tape) and caliper diameters of a stem's breast-height section, by forestry convention.

A forester measures DBH with a tape (the girth over pi: the perimeter of the section's convex
envelope, since a tape bridges every hollow of the bark) or with calipers (the mean of two
perpendicular readings, each the section's width in one direction). On a round stem both equal
the diameter of its circle; on an out-of-round one (aRchi Tree_1: radii 23-39 cm about its
centre at 1.3 m) they differ from a least-squares circle and from each other. By Cauchy's
formula the mean width over all directions of a convex section is its perimeter over pi, so
a caliper pair at a random orientation estimates the girth DBH; its spread over orientations
is how much the caliper's orientation matters.

A convex hull of raw returns is not a tape: range noise pushes its vertices outward (the hull
takes the outermost points, not the surface), a branch stub or clutter point stretches it, and
a gap in the returns is bridged by a chord, shorter than the bark it hides (every pair of
neighbouring returns is such a chord: a sparse cloud's raw hull is short). :func:`section_girth`
guards against each (docs/algorithms/cloud.md "Out-of-round stems: tape and calipers"):

* only returns within ``[0.5 r, 1.5 r]`` of the fitted circle's centre enter (``r`` its
  radius): the inside of the stem and far clutter are out;
* the outline is the *median* radius of the returns in each angular sector about the centre
  (noise averages instead of being taken at its outermost; a minority of clutter points in a
  sector does not move it); the sector count adapts to the returns (:func:`_sector_count`);
  a sector standing out from both its neighbours (a twig, a branch stub: one sector wide) is
  replaced by the median of the three (a lobe of the wood spans several sectors);
* between sectors, and across empty sectors, the radius is interpolated linearly in angle, so
  a round stem's outline stays round over a gap instead of being cut by a chord;
* a section whose largest gap in angle exceeds ``max_gap_deg`` (default 90) is not measured
  (NaN): there the interpolated outline is a guess.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from stemmap.types import FloatArray

__all__ = [
    "GIRTH_MAX_GAP_DEG",
    "SectionGirth",
    "caliper_widths",
    "hull_perimeter",
    "section_girth",
]

#: largest angular gap (degrees) over which the outline is interpolated
GIRTH_MAX_GAP_DEG = 90.0
#: returns per sector aimed at, the fewest and most sectors (10 to 36: 36 to 10 degrees)
_PER_SECTOR = 5
_MIN_SECTORS = 10
_MAX_SECTORS = 36


@dataclass(frozen=True)
class SectionGirth:
    """Convention diameters (m) of one section, NaN when not measured (``reason`` says why).

    ``girth_dbh``: convex-hull perimeter of the outline / pi (tape). ``caliper_max_perp``:
    mean of the largest width and the width perpendicular to it. ``caliper_pair_min``,
    ``caliper_pair_max``: the smallest and largest mean of two perpendicular widths over all
    orientations (what a caliper pair can read). ``n_points`` returns used, ``n_sectors``
    sectors holding any, ``max_gap_deg`` the largest angular gap between returns."""

    girth_dbh: float
    caliper_max_perp: float
    caliper_pair_min: float
    caliper_pair_max: float
    n_points: int
    n_sectors: int
    max_gap_deg: float
    reason: str = ""


def hull_perimeter(pts: ArrayLike) -> float:
    """Perimeter (m) of the convex hull of 2D points (NaN for fewer than 3 or collinear)."""
    from scipy.spatial import ConvexHull, QhullError

    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] < 3:
        return math.nan
    try:
        return float(ConvexHull(p).area)  # in 2D, qhull's "area" is the perimeter
    except QhullError:
        return math.nan


def caliper_widths(pts: ArrayLike, n_dir: int = 180) -> tuple[FloatArray, FloatArray]:
    """(angles in radians over [0, pi), widths in m): the width of the points' extent along
    each of ``n_dir`` directions, as a caliper laid across them reads it."""
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    phi = np.arange(n_dir, dtype=np.float64) * (math.pi / n_dir)
    proj = p @ np.stack((np.cos(phi), np.sin(phi)))
    return phi, proj.max(axis=0) - proj.min(axis=0)


def _sector_count(n: int) -> int:
    """About :data:`_PER_SECTOR` returns per sector, between 10 and 36 sectors."""
    return int(np.clip(n // _PER_SECTOR, _MIN_SECTORS, _MAX_SECTORS))


def _max_gap_deg(theta: FloatArray) -> float:
    t = np.sort(np.mod(theta, 2 * math.pi))
    gaps = np.diff(np.concatenate((t, [t[0] + 2 * math.pi])))
    return float(np.degrees(gaps.max()))


def section_outline(
    xy: ArrayLike, center: tuple[float, float], radius: float
) -> tuple[FloatArray, int, int, float]:
    """The section's outline as a dense closed polygon (M, 2) (absolute coordinates), the
    returns used, the sectors holding any, and the largest angular gap (degrees); the polygon
    is empty for fewer than 3 sectors. See the module docstring."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.asarray(center, dtype=np.float64)
    rho = np.hypot(p[:, 0], p[:, 1])
    keep = (rho >= 0.5 * radius) & (rho <= 1.5 * radius)
    p, rho = p[keep], rho[keep]
    n = int(rho.size)
    if n < 3:
        return np.zeros((0, 2)), n, 0, 360.0
    theta = np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * math.pi)
    k = _sector_count(n)
    sec = np.minimum((theta / (2 * math.pi) * k).astype(np.int64), k - 1)
    order = np.argsort(sec, kind="stable")
    sec_s = sec[order]
    starts = np.flatnonzero(np.r_[True, np.diff(sec_s) > 0])
    groups = np.split(order, starts[1:])
    # per occupied sector: the median angle and the median radius of its returns
    ang = np.array([float(np.median(theta[g])) for g in groups])
    rad = np.array([float(np.median(rho[g])) for g in groups])
    if ang.size < 3:
        return np.zeros((0, 2)), n, int(ang.size), _max_gap_deg(theta)
    # a sector standing out alone from both neighbours is a twig or a stub, not wood: the
    # circular median of three neighbouring sectors (a lobe spans more than one sector)
    rad = np.median(np.stack((np.roll(rad, 1), rad, np.roll(rad, -1))), axis=0)
    # radius linear in angle between the sectors (closed: wrap the first after the last)
    a_ext = np.concatenate((ang, [ang[0] + 2 * math.pi]))
    r_ext = np.concatenate((rad, [rad[0]]))
    grid = np.linspace(ang[0], ang[0] + 2 * math.pi, 721)[:-1]
    r_grid = np.interp(grid, a_ext, r_ext)
    poly = np.column_stack((r_grid * np.cos(grid), r_grid * np.sin(grid)))
    return poly + np.asarray(center), n, int(ang.size), _max_gap_deg(theta)


def section_girth(
    xy: ArrayLike,
    center: tuple[float, float],
    radius: float,
    *,
    max_gap_deg: float = GIRTH_MAX_GAP_DEG,
) -> SectionGirth:
    """Tape and caliper diameters of one breast-height section: ``xy`` the section's returns
    (m), ``center`` and ``radius`` the stem's fitted circle there (which returns belong to the
    stem, and the centre the outline is traced about). See the module docstring."""
    poly, n, ns, gap = section_outline(xy, center, radius)
    nan = math.nan
    if poly.shape[0] == 0:
        return SectionGirth(nan, nan, nan, nan, n, ns, gap, "fewer than 3 sectors with returns")
    if gap > max_gap_deg:
        return SectionGirth(
            nan, nan, nan, nan, n, ns, gap, f"a gap of {gap:.0f} deg in the outline"
        )
    _, w = caliper_widths(poly)
    i = int(np.argmax(w))
    q = w.size // 2  # the perpendicular direction (n_dir even)
    pair = 0.5 * (w + np.roll(w, -q))
    return SectionGirth(
        hull_perimeter(poly) / math.pi,
        float(0.5 * (w[i] + w[(i + q) % w.size])),
        float(pair.min()),
        float(pair.max()),
        n,
        ns,
        gap,
    )
