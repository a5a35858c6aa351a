"""2D laser scanner simulation by exact ray casting against a :class:`~stemmap.sim.forest.Stand`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stemmap.errors import ConfigError
from stemmap.sim.forest import Stand
from stemmap.types import FloatArray, LaserScan, Pose2

__all__ = ["ScannerModel", "cast_rays", "simulate_scan"]


@dataclass(frozen=True)
class ScannerModel:
    """Geometry and noise of a 2D scanner.

    Parameters
    ----------
    angle_min, angle_max : float, radians (inclusive span of beams)
    angle_increment : float, radians
    range_min, range_max : float, metres
    range_noise : float, metres (1-sigma Gaussian)
    dropout : float in [0, 1), probability a beam returns nothing
    """

    angle_min: float = -math.pi / 2
    angle_max: float = math.pi / 2
    angle_increment: float = math.radians(0.5)
    range_min: float = 0.05
    range_max: float = 30.0
    range_noise: float = 0.01
    dropout: float = 0.0

    def __post_init__(self) -> None:
        if not self.angle_increment > 0:
            raise ConfigError("angle_increment must be > 0.")
        if not self.angle_max > self.angle_min:
            raise ConfigError("angle_max must exceed angle_min.")
        if not 0.0 <= self.dropout < 1.0:
            raise ConfigError("dropout must be in [0, 1).")

    @property
    def n_beams(self) -> int:
        return round((self.angle_max - self.angle_min) / self.angle_increment) + 1

    @property
    def angles(self) -> FloatArray:
        return self.angle_min + self.angle_increment * np.arange(self.n_beams, dtype=np.float64)


def cast_rays(
    origin: FloatArray, directions: FloatArray, stand: Stand, max_range: float
) -> tuple[FloatArray, np.ndarray]:
    """Exact first-hit distances of rays against the stand's circles and segments.

    Parameters
    ----------
    origin : (2,) world position of the sensor
    directions : (B,) world angles of the rays, radians
    stand : Stand
    max_range : float, metres

    Returns
    -------
    ranges : (B,) distance to first hit, ``inf`` where nothing is hit within ``max_range``
    hit_id : (B,) int -- tree index for trees (and polygon segments owned by a tree),
        -2 for clutter, -1 for no hit
    """
    o = np.asarray(origin, dtype=np.float64)
    u = np.column_stack((np.cos(directions), np.sin(directions)))  # (B, 2)
    n_b = u.shape[0]
    best = np.full(n_b, np.inf)
    hit = np.full(n_b, -1, dtype=np.int64)

    centers = np.vstack((stand.trees_xy, stand.clutter_xy))
    radii = np.concatenate((stand.radii, stand.clutter_radius))
    ids = np.concatenate(
        (np.arange(stand.n_trees, dtype=np.int64), np.full(len(stand.clutter_radius), -2))
    )
    if centers.shape[0]:
        rel = centers - o  # (C, 2)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        keep = dist - radii < max_range
        rel, radii_k, ids_k = rel[keep], radii[keep], ids[keep]
        if rel.shape[0]:
            # |t u - c|^2 = r^2  ->  t = b - sqrt(b^2 - (|c|^2 - r^2)), b = u.c
            b = u @ rel.T  # (B, C)
            cc = np.sum(rel * rel, axis=1) - radii_k**2  # (C,)
            disc = b * b - cc
            with np.errstate(invalid="ignore"):
                t = b - np.sqrt(disc)
            t = np.where((disc >= 0) & (t > 0), t, np.inf)
            j = np.argmin(t, axis=1)
            tj = t[np.arange(n_b), j]
            better = tj < best
            best = np.where(better, tj, best)
            hit = np.where(better, ids_k[j], hit)

    if stand.segments.shape[0]:
        seg = stand.segments
        p0 = seg[:, :2] - o
        d = seg[:, 2:] - seg[:, :2]  # (S, 2)
        # Solve t u = p0 + s d  ->  cross products
        den = u[:, :1] * d[:, 1] - u[:, 1:] * d[:, 0]  # (B, S)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (p0[:, 0] * d[:, 1] - p0[:, 1] * d[:, 0]) / den
            s = (p0[:, 0] * u[:, 1:] - p0[:, 1] * u[:, :1]) / den
        valid = (np.abs(den) > 1e-12) & (t > 0) & (s >= 0) & (s <= 1)
        t = np.where(valid, t, np.inf)
        j = np.argmin(t, axis=1)
        tj = t[np.arange(n_b), j]
        owner = np.where(stand.segment_owner >= 0, stand.segment_owner, -2)
        better = tj < best
        best = np.where(better, tj, best)
        hit = np.where(better, owner[j], hit)

    far = best >= max_range
    best[far] = np.inf
    hit[far] = -1
    return best, hit


def simulate_scan(
    stand: Stand,
    pose: Pose2,
    model: ScannerModel | None = None,
    *,
    time: float = 0.0,
    rng: np.random.Generator | int | None = None,
) -> tuple[LaserScan, np.ndarray]:
    """Simulate one scan from ``pose`` (sensor pose in the world frame).

    Returns the scan (in the sensor frame, "no return" as inf) and the per-beam hit id
    (tree index, -2 clutter, -1 nothing).
    """
    m = model or ScannerModel()
    gen = np.random.default_rng(rng)
    angles = m.angles
    ranges, hit = cast_rays(np.array([pose.x, pose.y]), angles + pose.theta, stand, m.range_max)
    finite = np.isfinite(ranges)
    ranges = ranges + np.where(finite, gen.normal(0.0, m.range_noise, ranges.shape), 0.0)
    if m.dropout > 0:
        drop = gen.random(ranges.shape) < m.dropout
        ranges[drop] = np.inf
        hit[drop] = -1
    scan = LaserScan(
        ranges,
        m.angle_min,
        m.angle_increment,
        time=time,
        range_min=m.range_min,
        range_max=m.range_max,
    )
    return scan, hit
