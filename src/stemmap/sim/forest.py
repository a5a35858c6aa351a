"""Simulated stands: tree positions and diameters, plus obstacles that are not trees.

A :class:`Stand` is pure geometry in the world frame (metres). Trees are circles at breast height;
clutter is more circles (bushes, rocks, thin branches) and line segments (walls, fences, polygonal
trunk outlines). Ground truth is ``stand.trees_xy`` / ``stand.diameters``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray

__all__ = ["Stand", "random_stand"]


@dataclass(frozen=True, eq=False)
class Stand:
    """Geometry of a simulated forest stand at scan height.

    Parameters
    ----------
    trees_xy : ndarray of shape (T, 2), metres
    diameters : ndarray of shape (T,), metres (DBH)
    clutter_xy, clutter_radius : circles that reflect but are not trees, shapes (C, 2), (C,)
    segments : ndarray of shape (S, 4), metres
        Line segments (x0, y0, x1, y1) that reflect: walls, fences, polygonal trunk outlines.
    segment_owner : ndarray of shape (S,), int
        Tree index a segment belongs to (polygonal, non-circular trunks), or -1 for clutter.
    bounds : (xmin, ymin, xmax, ymax)
    """

    trees_xy: FloatArray
    diameters: FloatArray
    clutter_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    clutter_radius: FloatArray = field(default_factory=lambda: np.zeros(0))
    segments: FloatArray = field(default_factory=lambda: np.zeros((0, 4)))
    segment_owner: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        xy = np.asarray(self.trees_xy, dtype=np.float64).reshape(-1, 2)
        d = np.asarray(self.diameters, dtype=np.float64).reshape(-1)
        if d.shape[0] != xy.shape[0]:
            raise InputError(f"{xy.shape[0]} tree positions but {d.shape[0]} diameters.")
        if np.any(~(d > 0)):
            raise InputError("every tree diameter must be positive.")
        cxy = np.asarray(self.clutter_xy, dtype=np.float64).reshape(-1, 2)
        cr = np.asarray(self.clutter_radius, dtype=np.float64).reshape(-1)
        if cr.shape[0] != cxy.shape[0]:
            raise InputError("clutter_xy and clutter_radius lengths differ.")
        seg = np.asarray(self.segments, dtype=np.float64).reshape(-1, 4)
        own = np.asarray(self.segment_owner, dtype=np.int64).reshape(-1)
        if own.shape[0] != seg.shape[0]:
            own = np.full(seg.shape[0], -1, dtype=np.int64)
        for name, arr in (
            ("trees_xy", xy),
            ("diameters", d),
            ("clutter_xy", cxy),
            ("clutter_radius", cr),
            ("segments", seg),
            ("segment_owner", own),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def radii(self) -> FloatArray:
        return self.diameters / 2.0

    @property
    def n_trees(self) -> int:
        return int(self.trees_xy.shape[0])


def random_stand(
    n_trees: int = 60,
    size: tuple[float, float] = (40.0, 40.0),
    *,
    dbh_mean: float = 0.30,
    dbh_std: float = 0.10,
    dbh_min: float = 0.08,
    min_spacing: float = 1.5,
    rng: np.random.Generator | int | None = None,
) -> Stand:
    """Uniform random (Poisson-disc-like) stand with a truncated-normal DBH distribution.

    Trees closer than ``min_spacing`` + their radii are rejected and redrawn.
    """
    if n_trees < 0:
        raise ConfigError(f"n_trees must be >= 0, got {n_trees}.")
    gen = np.random.default_rng(rng)
    w, h = size
    xy: list[FloatArray] = []
    dbh: list[float] = []
    attempts = 0
    while len(xy) < n_trees and attempts < 200 * max(n_trees, 1):
        attempts += 1
        p = gen.uniform((0.0, 0.0), (w, h))
        d = float(np.clip(gen.normal(dbh_mean, dbh_std), dbh_min, None))
        if xy:
            arr = np.asarray(xy)
            gap = np.hypot(*(arr - p).T) - (np.asarray(dbh) + d) / 2.0
            if np.min(gap) < min_spacing:
                continue
        xy.append(p)
        dbh.append(d)
    if len(xy) < n_trees:
        raise ConfigError(
            f"could place only {len(xy)} of {n_trees} trees in {w} x {h} m with spacing "
            f"{min_spacing} m; enlarge the stand or reduce min_spacing."
        )
    return Stand(np.asarray(xy).reshape(-1, 2), np.asarray(dbh), bounds=(0.0, 0.0, w, h))
