"""What a 2D scanner at breast height sees besides the trunks: the ground and the understory
of the same real cloud, for the virtual scans of :mod:`stemmap.eval.real_slices` (issue 11,
fifteenth round).

A breast-height slice holds trunks (and on the TreeLS plot some shrubs) only, so a virtual
scan of it has no return where a beam misses every trunk, and the scan's own range-noise
estimate (:func:`stemmap.scan.plausibility.scan_noise`, ``sigma_from_scan``) has too few
continuous surfaces to read. A real scanner's plane is never exactly level: a mount pitched
down by a few degrees meets the ground at ``height / tan(pitch)`` ahead (24.8 m at 1.3 m and
3 degrees), nearer uphill, and on the way passes through the understory and the lower
branches. :class:`GroundSurface` holds that scene for one slice:

- the ground as a plane ``z = level + gx x + gy y`` (least squares over the cloud's ground
  points) where the cloud has ground (the TreeLS plot, pine and spruce), else a horizontal
  plane (the FORTLS and lidR files are slices already, the aRchi trees are segmented without
  ground): a documented flat-ground model;
- the cloud's own points below the slice (ground, understory, low branches), stems excluded
  (they are in the slice), as heights above that plane.

:func:`band_points` keeps the points the pitched beam plane passes through (within half a
``band`` of it, the beam's height and the cloud's vertical spacing), :func:`ground_ranges`
gives the range at which each beam meets the plane. The plane is a stand-in for the terrain
beyond the cloud (the TreeLS plot is 10 x 10 m, the single trees 2.5 x 2.5 m; the vantage
points lie up to 15 m from a trunk): where the cloud's points are, the real ground and
understory answer first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from stemmap.types import FloatArray

__all__ = [
    "RELIEF_CORR",
    "RELIEF_STD",
    "GroundSurface",
    "Mount",
    "Relief",
    "band_points",
    "ground_ranges",
    "ground_surface",
]

#: Micro-relief of the ground beyond the cloud, metres: std of the height about the plane and
#: correlation length (a Gaussian-filtered random field). Measured on the TreeLS plot's ground
#: points (|h| <= 15 cm about its 1 m ground raster, 18 858 points): height std 4.3 cm; half
#: the mean square height difference between two points at 0.05 / 0.1 / 0.2 / 0.3 / 0.5 / 1 m
#: apart 2.1 / 2.6 / 3.2 / 3.7 / 4.4 / 5.9 cm (square-rooted): rough at every scale.
RELIEF_STD = 0.04
RELIEF_CORR = 0.3


@dataclass(frozen=True)
class Mount:
    """A 2D scanner's mount: ``height`` of the scan centre above the ground at the vantage
    (metres; the slice's centre, 1.3 m), ``pitch_deg`` down towards the heading (the scan
    plane's tilt), ``band`` the full height of the beam's cut through the cloud (metres)."""

    height: float = 1.3
    pitch_deg: float = 3.0
    band: float = 0.1


@dataclass(frozen=True)
class GroundSurface:
    """The scene below a slice: ``gradient`` (dz/dx, dz/dy) of the ground plane (slice
    coordinates), ``points`` (M, 3): x, y and height above that plane of the cloud's points
    below the slice (no stems), ``source`` where both come from."""

    gradient: tuple[float, float]
    points: FloatArray
    source: str

    @staticmethod
    def flat(source: str) -> GroundSurface:
        """The flat-ground model of a cloud without ground: horizontal, no understory."""
        return GroundSurface((0.0, 0.0), np.zeros((0, 3)), source)


@dataclass(frozen=True)
class Relief:
    """A ground micro-relief: heights (metres, above the plane) on a grid of ``cell`` metres
    with its lower-left cell centre at ``origin``; bilinear in between, 0 outside."""

    z: FloatArray
    origin: tuple[float, float]
    cell: float

    @staticmethod
    def random(
        half_size: float,
        seed: int,
        std: float = RELIEF_STD,
        corr: float = RELIEF_CORR,
        cell: float = 0.1,
    ) -> Relief:
        """White noise on a (2 half_size)^2 grid smoothed by a Gaussian of ``corr`` metres and
        scaled to ``std``; ``std`` 0 gives a flat ground."""
        from scipy import ndimage

        n = math.ceil(2.0 * half_size / cell) + 1
        z = np.random.default_rng(seed).standard_normal((n, n))
        z = ndimage.gaussian_filter(z, corr / cell, mode="wrap")
        z *= std / max(float(z.std()), 1e-12)
        return Relief(z, (-half_size, -half_size), cell)

    def at(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Relief heights at positions ``x``, ``y`` (any equal shapes)."""
        from scipy import ndimage

        i = (np.asarray(x) - self.origin[0]) / self.cell
        j = (np.asarray(y) - self.origin[1]) / self.cell
        coords = np.stack((i.ravel(), j.ravel()))
        out = ndimage.map_coordinates(self.z, coords, order=1, mode="constant", cval=0.0)
        return np.asarray(out.reshape(np.shape(x)))


def _plane(xyz: FloatArray) -> tuple[float, float, float]:
    """Least-squares plane z = c + gx x + gy y, refitted once without points > 3 robust
    sigmas off (stumps, litter heaps, a stem base)."""
    a = np.column_stack((np.ones(xyz.shape[0]), xyz[:, 0], xyz[:, 1]))
    keep = np.ones(xyz.shape[0], dtype=bool)
    c = np.zeros(3)
    for _ in range(2):
        c = np.linalg.lstsq(a[keep], xyz[keep, 2], rcond=None)[0]
        res = xyz[:, 2] - a @ c
        s = 1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep]))))
        keep = np.abs(res) <= 3.0 * max(s, 0.01)
    return float(c[0]), float(c[1]), float(c[2])


def ground_surface(
    xyz: FloatArray,
    height: FloatArray,
    ground: NDArray[np.bool_],
    z_lo: float,
    stems: FloatArray,
) -> GroundSurface:
    """The ground plane and understory of a cloud with ground.

    Parameters
    ----------
    xyz : (N, 3) points, x and y in slice coordinates
    height : (N,) heights above the cloud's ground (a ground raster or the lowest point)
    ground : (N,) mask of the ground points the plane is fitted to
    z_lo : the slice's lower bound: the points below it are the understory
    stems : (K, 3) x, y, radius of every stem (reference and partial rings, or a single tree's
        stem base); points within radius + 10 cm of one are stem, in the slice already
    """
    c0, gx, gy = _plane(xyz[ground])
    low = height < z_lo
    for x, y, r in stems:
        low &= np.hypot(xyz[:, 0] - x, xyz[:, 1] - y) > r + 0.1
    p = xyz[low]
    h = p[:, 2] - (c0 + gx * p[:, 0] + gy * p[:, 1])
    return GroundSurface(
        (gx, gy),
        np.column_stack((p[:, :2], h)),
        f"cloud: ground plane from {int(ground.sum())} ground points, "
        f"{p.shape[0]} points below the slice",
    )


def _beam_tan(theta: FloatArray, heading: float, mount: Mount) -> FloatArray:
    """tan of the beam's elevation at bearing ``theta`` for a scan plane pitched down by
    ``mount.pitch_deg`` towards ``heading``: -tan(pitch) cos(theta - heading)."""
    return np.asarray(-math.tan(math.radians(mount.pitch_deg)) * np.cos(theta - heading))


def band_points(
    surface: GroundSurface, vantage: FloatArray, heading: float, mount: Mount
) -> FloatArray:
    """(M, 2) xy of the cloud's points below the slice that the pitched scan plane from
    ``vantage`` passes through: their height above the ground plane within ``mount.band / 2``
    of the beam's, ``height + s tan(elevation) - g . (p - vantage)`` at horizontal distance
    ``s`` (the plane's own rise towards the point taken out: heights are above the plane)."""
    if surface.points.shape[0] == 0:
        return np.zeros((0, 2))
    q = surface.points[:, :2] - np.asarray(vantage, dtype=np.float64)
    s = np.hypot(q[:, 0], q[:, 1])
    th = np.arctan2(q[:, 1], q[:, 0])
    g = np.asarray(surface.gradient)
    beam = mount.height + s * _beam_tan(th, heading, mount) - q @ g
    keep = np.abs(surface.points[:, 2] - beam) <= 0.5 * mount.band
    return np.asarray(surface.points[keep, :2])


def ground_ranges(
    surface: GroundSurface,
    bearings: FloatArray,
    heading: float,
    mount: Mount,
    max_range: float,
    vantage: FloatArray | None = None,
    relief: Relief | None = None,
    steps: int = 160,
) -> FloatArray:
    """Horizontal range at which each beam (``bearings``, radians) from ``vantage`` meets the
    ground, else inf (also beyond ``max_range``).

    The plane alone: ``height / (g . u - tan(elevation))`` where positive (the beam descends
    relative to the terrain). With ``relief``: the first of ``steps`` points along the beam,
    over the stretch where its height above the plane is within the relief's largest height, at
    which the beam is at or below the relief (a first echo from the first bump it grazes)."""
    u_g = surface.gradient[0] * np.cos(bearings) + surface.gradient[1] * np.sin(bearings)
    den = u_g - _beam_tan(bearings, heading, mount)
    pos = den > 0.0
    safe = np.where(pos, den, 1.0)
    amp = float(np.abs(relief.z).max()) if relief is not None and relief.z.size else 0.0
    if relief is None or amp == 0.0:
        s = np.where(pos, mount.height / safe, np.inf)
        return np.asarray(np.where(s <= max_range, s, np.inf))
    lo = np.clip((mount.height - amp) / safe, 0.0, max_range)
    hi = np.clip((mount.height + amp) / safe, 0.0, max_range)
    frac = np.linspace(0.0, 1.0, steps)
    s = lo[:, None] + (hi - lo)[:, None] * frac[None, :]
    o = np.zeros(2) if vantage is None else np.asarray(vantage, dtype=np.float64)
    x = o[0] + s * np.cos(bearings)[:, None]
    y = o[1] + s * np.sin(bearings)[:, None]
    below = mount.height - den[:, None] * s <= relief.at(x, y)
    below &= pos[:, None] & (hi > lo)[:, None]
    first = np.argmax(below, axis=1)
    got = below[np.arange(s.shape[0]), first]
    return np.asarray(np.where(got, s[np.arange(s.shape[0]), first], np.inf))
