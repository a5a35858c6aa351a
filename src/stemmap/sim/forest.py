"""Simulated stands: tree positions and diameters, plus obstacles that are not trees.

A :class:`Stand` is pure geometry in the world frame (metres) at scan height. Trees are circles
(or, optionally, polygons owned by the tree: ellipses with rough bark); clutter is more circles
(bush stems) and line segments (walls, fences, fallen branches, rock outlines). Ground truth is
``stand.trees_xy`` / ``stand.diameters`` and, for the non-tree objects (needed to count true
rejects), ``stand.clutter_objects_xy`` / ``stand.clutter_kinds``.

Layouts: :func:`random_stand` (uniform with a minimum spacing), :func:`clustered_stand`
(Thomas cluster process), :func:`row_stand` (orchard / plantation rows). DBH values come from
:func:`sample_dbh`. :func:`add_clutter` and :func:`make_trunks_noncircular` transform a stand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.outline import rough_radius, trunk_outline
from stemmap.types import FloatArray, StemMap, Tree

__all__ = [
    "CLUTTER_KINDS",
    "Stand",
    "add_clutter",
    "add_understory",
    "clustered_stand",
    "make_trunks_noncircular",
    "random_stand",
    "row_stand",
    "sample_dbh",
]

#: Kinds of non-tree objects the simulator places.
CLUTTER_KINDS = ("bush", "branch", "wall", "fence", "rock", "understory")

RngLike = np.random.Generator | int | None


@dataclass(frozen=True, eq=False)
class Stand:
    """Geometry of a simulated forest stand at scan height.

    Parameters
    ----------
    trees_xy : ndarray of shape (T, 2), metres
    diameters : ndarray of shape (T,), metres (DBH)
        For non-circular trunks: the mean of the longest and shortest caliper diameter
        (the ellipse's two axes), the usual two-caliper forestry convention.
    clutter_xy, clutter_radius : circles that reflect but are not trees, shapes (C, 2), (C,)
    segments : ndarray of shape (S, 4), metres
        Line segments (x0, y0, x1, y1) that reflect: walls, fences, branches, rock and
        polygonal trunk outlines.
    segment_owner : ndarray of shape (S,), int
        Tree index a segment belongs to (polygonal, non-circular trunks), or -1 for clutter.
    bounds : (xmin, ymin, xmax, ymax)
    tree_is_polygon : ndarray of shape (T,), bool
        Trees drawn by their owned segments instead of a circle.
    clutter_objects_xy : ndarray of shape (K, 2), metres
        Centre of every non-tree object (one per bush, wall, rock, ...), for true-reject counts.
    clutter_kinds : tuple of str, length K
        Kind of each non-tree object (see :data:`CLUTTER_KINDS`).
    clutter_objects_extent : ndarray of shape (K,), metres
        Radius around each object centre that the object occupies (half a wall's length).

    Raises
    ------
    InputError
        If lengths disagree or a diameter is not positive.
    """

    trees_xy: FloatArray
    diameters: FloatArray
    clutter_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    clutter_radius: FloatArray = field(default_factory=lambda: np.zeros(0))
    segments: FloatArray = field(default_factory=lambda: np.zeros((0, 4)))
    segment_owner: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    tree_is_polygon: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    clutter_objects_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    clutter_kinds: tuple[str, ...] = ()
    clutter_objects_extent: FloatArray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        xy = np.array(self.trees_xy, dtype=np.float64).reshape(-1, 2)
        d = np.array(self.diameters, dtype=np.float64).reshape(-1)
        if d.shape[0] != xy.shape[0]:
            raise InputError(f"Stand has {xy.shape[0]} tree positions but {d.shape[0]} diameters.")
        if np.any(~(d > 0)):
            raise InputError("every tree diameter in a Stand must be positive.")
        if not np.all(np.isfinite(xy)):
            raise InputError("every tree position in a Stand must be finite.")
        cxy = np.array(self.clutter_xy, dtype=np.float64).reshape(-1, 2)
        cr = np.array(self.clutter_radius, dtype=np.float64).reshape(-1)
        if cr.shape[0] != cxy.shape[0]:
            raise InputError(
                f"Stand.clutter_xy has {cxy.shape[0]} rows but clutter_radius {cr.shape[0]}."
            )
        seg = np.array(self.segments, dtype=np.float64).reshape(-1, 4)
        own = np.array(self.segment_owner, dtype=np.int64).reshape(-1)
        if own.shape[0] != seg.shape[0]:
            if own.shape[0] != 0:
                raise InputError(
                    f"Stand.segment_owner has {own.shape[0]} values for {seg.shape[0]} segments."
                )
            own = np.full(seg.shape[0], -1, dtype=np.int64)
        if np.any(own >= xy.shape[0]):
            raise InputError("Stand.segment_owner names a tree index that does not exist.")
        if not (np.all(np.isfinite(cxy)) and np.all(np.isfinite(seg))):
            raise InputError("Stand clutter positions and segment end points must be finite.")
        if np.any(~(cr > 0)):
            raise InputError("every clutter circle radius in a Stand must be positive.")
        poly = np.array(self.tree_is_polygon, dtype=bool).reshape(-1)
        if poly.shape[0] == 0:
            poly = np.zeros(xy.shape[0], dtype=bool)
        if poly.shape[0] != xy.shape[0]:
            raise InputError(
                f"Stand.tree_is_polygon has {poly.shape[0]} values for {xy.shape[0]} trees."
            )
        oxy = np.array(self.clutter_objects_xy, dtype=np.float64).reshape(-1, 2)
        kinds = tuple(self.clutter_kinds)
        if len(kinds) != oxy.shape[0]:
            raise InputError(
                f"Stand.clutter_kinds has {len(kinds)} entries for {oxy.shape[0]} objects."
            )
        ext = np.array(self.clutter_objects_extent, dtype=np.float64).reshape(-1)
        if ext.shape[0] == 0:
            ext = np.zeros(oxy.shape[0])
        if ext.shape[0] != oxy.shape[0]:
            raise InputError(
                f"Stand.clutter_objects_extent has {ext.shape[0]} values for "
                f"{oxy.shape[0]} objects."
            )
        for name, arr in (
            ("clutter_objects_extent", ext),
            ("trees_xy", xy),
            ("diameters", d),
            ("clutter_xy", cxy),
            ("clutter_radius", cr),
            ("segments", seg),
            ("segment_owner", own),
            ("tree_is_polygon", poly),
            ("clutter_objects_xy", oxy),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "clutter_kinds", kinds)
        object.__setattr__(self, "bounds", tuple(float(b) for b in self.bounds))

    @property
    def radii(self) -> FloatArray:
        return self.diameters / 2.0

    @property
    def n_trees(self) -> int:
        return int(self.trees_xy.shape[0])

    @property
    def n_clutter_objects(self) -> int:
        return int(self.clutter_objects_xy.shape[0])

    def to_stem_map(self, frame: str = "world") -> StemMap:
        """The ground truth as a :class:`~stemmap.types.StemMap` (ids = tree indices)."""
        return StemMap(
            tuple(
                Tree(i, float(x), float(y), float(d), cov=np.zeros((2, 2)), confidence=1.0)
                for i, ((x, y), d) in enumerate(zip(self.trees_xy, self.diameters, strict=True))
            ),
            frame=frame,
        )

    def subset_trees(self, keep: ArrayLike) -> Stand:
        """A stand with only the trees selected by a boolean mask (clutter kept, ids renumbered)."""
        mask = np.asarray(keep, dtype=bool).reshape(-1)
        if mask.shape[0] != self.n_trees:
            raise InputError(f"subset_trees needs {self.n_trees} flags, got {mask.shape[0]}.")
        new_index = np.cumsum(mask) - 1
        own = self.segment_owner
        seg_keep = (own < 0) | mask[np.clip(own, 0, None)]
        new_own = np.where(own >= 0, new_index[np.clip(own, 0, None)], -1)[seg_keep]
        return replace(
            self,
            trees_xy=self.trees_xy[mask],
            diameters=self.diameters[mask],
            tree_is_polygon=self.tree_is_polygon[mask],
            segments=self.segments[seg_keep],
            segment_owner=new_own,
        )


# --------------------------------------------------------------------------------------------
# DBH distribution
# --------------------------------------------------------------------------------------------


def sample_dbh(
    n: int,
    *,
    distribution: Literal["normal", "weibull", "uniform"] = "normal",
    mean: float = 0.30,
    std: float = 0.10,
    dbh_min: float = 0.08,
    dbh_max: float = 1.2,
    rng: RngLike = None,
) -> FloatArray:
    """Draw ``n`` breast-height diameters (metres) from a truncated distribution.

    Parameters
    ----------
    n : int, >= 0
    distribution : {"normal", "weibull", "uniform"}
        ``normal``: N(mean, std). ``weibull``: two-parameter Weibull with the given mean and
        standard deviation (shape found by moment matching), the usual diameter distribution
        of even-aged stands. ``uniform``: U(dbh_min, dbh_max).
    mean, std : float, metres, > 0
    dbh_min, dbh_max : float, metres
        Truncation window; values outside are redrawn (not clipped, so no spike at the limits).
    rng : numpy Generator or int seed

    Returns
    -------
    ndarray of shape (n,), metres
    """
    if n < 0:
        raise ConfigError(f"sample_dbh needs n >= 0, got {n}.")
    if not (0 < dbh_min < dbh_max):
        raise ConfigError(f"need 0 < dbh_min < dbh_max, got {dbh_min}, {dbh_max}.")
    if not (mean > 0 and std > 0):
        raise ConfigError(f"DBH mean and std must be > 0, got {mean}, {std}.")
    gen = np.random.default_rng(rng)
    if distribution == "weibull":
        cv = std / mean
        # mean = s Gamma(1 + 1/k); cv^2 = Gamma(1 + 2/k) / Gamma(1 + 1/k)^2 - 1: solve for k
        ks = np.linspace(0.5, 20.0, 4000)
        g1 = np.exp([math.lgamma(1 + 1 / k) for k in ks])
        g2 = np.exp([math.lgamma(1 + 2 / k) for k in ks])
        k = float(ks[np.argmin(np.abs(g2 / g1**2 - 1 - cv**2))])
        scale = mean / math.exp(math.lgamma(1 + 1 / k))
    elif distribution not in ("normal", "uniform"):
        raise ConfigError(
            f"unknown DBH distribution {distribution!r}; use 'normal', 'weibull' or 'uniform'."
        )
    out = np.empty(0)
    for _ in range(100):
        need = n - out.size
        if need <= 0:
            break
        m = 2 * need + 8
        if distribution == "normal":
            draw = gen.normal(mean, std, m)
        elif distribution == "weibull":
            draw = scale * gen.weibull(k, m)
        else:
            draw = gen.uniform(dbh_min, dbh_max, m)
        draw = draw[(draw >= dbh_min) & (draw <= dbh_max)]
        out = np.concatenate((out, draw[:need]))
    if out.size < n:
        raise ConfigError(
            f"the DBH window [{dbh_min}, {dbh_max}] m holds almost none of the {distribution} "
            f"distribution with mean {mean} m and std {std} m; widen the window."
        )
    return out


# --------------------------------------------------------------------------------------------
# Layouts
# --------------------------------------------------------------------------------------------


def _place_with_spacing(
    candidates: FloatArray, dbh: FloatArray, min_spacing: float, n_trees: int
) -> NDArray[np.int64]:
    """Greedy acceptance of candidate positions keeping surface-to-surface gaps >= min_spacing."""
    keep: list[int] = []
    kept_xy = np.empty((n_trees, 2))
    kept_r = np.empty(n_trees)
    for i in range(candidates.shape[0]):
        if len(keep) == n_trees:
            break
        k = len(keep)
        if k:
            gap = np.hypot(*(kept_xy[:k] - candidates[i]).T) - kept_r[:k] - dbh[i] / 2.0
            if gap.min() < min_spacing:
                continue
        kept_xy[k] = candidates[i]
        kept_r[k] = dbh[i] / 2.0
        keep.append(i)
    return np.asarray(keep, dtype=np.int64)


def random_stand(
    n_trees: int = 60,
    size: tuple[float, float] = (40.0, 40.0),
    *,
    dbh_mean: float = 0.30,
    dbh_std: float = 0.10,
    dbh_min: float = 0.08,
    min_spacing: float = 1.5,
    dbh_distribution: Literal["normal", "weibull", "uniform"] = "normal",
    dbh_max: float = 1.2,
    rng: RngLike = None,
) -> Stand:
    """Uniform random (Poisson-disc-like) stand with a truncated DBH distribution.

    Trees whose surface-to-surface gap to an accepted tree is below ``min_spacing`` (m) are
    rejected and redrawn.

    Raises
    ------
    ConfigError
        If ``n_trees`` is negative or the trees do not fit.
    """
    if n_trees < 0:
        raise ConfigError(f"n_trees must be >= 0, got {n_trees}.")
    gen = np.random.default_rng(rng)
    w, h = size
    n_cand = 200 * max(n_trees, 1)
    cand = gen.uniform((0.0, 0.0), (w, h), size=(n_cand, 2))
    dbh = sample_dbh(
        n_cand,
        distribution=dbh_distribution,
        mean=dbh_mean,
        std=dbh_std,
        dbh_min=dbh_min,
        dbh_max=dbh_max,
        rng=gen,
    )
    idx = _place_with_spacing(cand, dbh, min_spacing, n_trees)
    if idx.size < n_trees:
        raise ConfigError(
            f"could place only {idx.size} of {n_trees} trees in {w} x {h} m with spacing "
            f"{min_spacing} m; enlarge the stand or reduce min_spacing."
        )
    return Stand(cand[idx], dbh[idx], bounds=(0.0, 0.0, w, h))


def clustered_stand(
    n_trees: int = 60,
    size: tuple[float, float] = (40.0, 40.0),
    *,
    n_clusters: int = 6,
    cluster_std: float = 3.0,
    min_spacing: float = 0.8,
    dbh_mean: float = 0.30,
    dbh_std: float = 0.10,
    dbh_min: float = 0.08,
    dbh_max: float = 1.2,
    dbh_distribution: Literal["normal", "weibull", "uniform"] = "normal",
    rng: RngLike = None,
) -> Stand:
    """Clustered stand (Thomas process): Gaussian groups of trees around random parents.

    Parameters
    ----------
    n_trees : int
    size : (width, height), metres
    n_clusters : int, >= 1
        Number of parent points, uniform in the stand.
    cluster_std : float, metres
        Standard deviation of the offspring around each parent.
    min_spacing : float, metres
        Minimum surface-to-surface gap between trunks.
    dbh_* : see :func:`sample_dbh`
    rng : numpy Generator or int seed
    """
    if n_trees < 0 or n_clusters < 1:
        raise ConfigError(f"need n_trees >= 0 and n_clusters >= 1, got {n_trees}, {n_clusters}.")
    gen = np.random.default_rng(rng)
    w, h = size
    parents = gen.uniform((0.0, 0.0), (w, h), size=(n_clusters, 2))
    n_cand = 200 * max(n_trees, 1)
    cand = parents[gen.integers(0, n_clusters, n_cand)] + gen.normal(0, cluster_std, (n_cand, 2))
    inside = (cand[:, 0] >= 0) & (cand[:, 0] <= w) & (cand[:, 1] >= 0) & (cand[:, 1] <= h)
    cand = cand[inside]
    dbh = sample_dbh(
        cand.shape[0],
        distribution=dbh_distribution,
        mean=dbh_mean,
        std=dbh_std,
        dbh_min=dbh_min,
        dbh_max=dbh_max,
        rng=gen,
    )
    idx = _place_with_spacing(cand, dbh, min_spacing, n_trees)
    if idx.size < n_trees:
        raise ConfigError(
            f"could place only {idx.size} of {n_trees} clustered trees (n_clusters="
            f"{n_clusters}, cluster_std={cluster_std} m, min_spacing={min_spacing} m); "
            "use more or wider clusters."
        )
    return Stand(cand[idx], dbh[idx], bounds=(0.0, 0.0, w, h))


def row_stand(
    n_rows: int = 5,
    trees_per_row: int = 12,
    *,
    row_spacing: float = 4.0,
    tree_spacing: float = 3.0,
    jitter: float = 0.1,
    missing: float = 0.0,
    origin: tuple[float, float] = (0.0, 0.0),
    heading: float = 0.0,
    dbh_mean: float = 0.25,
    dbh_std: float = 0.05,
    dbh_min: float = 0.08,
    dbh_max: float = 1.2,
    dbh_distribution: Literal["normal", "weibull", "uniform"] = "normal",
    rng: RngLike = None,
) -> Stand:
    """Orchard / plantation rows: a regular grid with planting jitter and missing trees.

    Row ``i`` runs along ``heading`` (rad) through ``origin + i * row_spacing`` in the
    perpendicular direction; trees are ``tree_spacing`` apart along it, each moved by
    ``N(0, jitter^2)`` per axis and removed with probability ``missing``.
    """
    if n_rows < 1 or trees_per_row < 1:
        raise ConfigError(
            f"need n_rows >= 1 and trees_per_row >= 1, got {n_rows}, {trees_per_row}."
        )
    if not (row_spacing > 0 and tree_spacing > 0 and jitter >= 0 and 0 <= missing < 1):
        raise ConfigError(
            "row_stand needs row_spacing > 0, tree_spacing > 0, jitter >= 0, 0 <= missing < 1."
        )
    gen = np.random.default_rng(rng)
    jj, ii = np.meshgrid(np.arange(trees_per_row), np.arange(n_rows))
    local = np.column_stack((jj.ravel() * tree_spacing, ii.ravel() * row_spacing))
    local = local + gen.normal(0.0, jitter, local.shape)
    c, s = math.cos(heading), math.sin(heading)
    xy = local @ np.array([[c, s], [-s, c]]) + np.asarray(origin, dtype=np.float64)
    keep = gen.random(xy.shape[0]) >= missing
    dbh = sample_dbh(
        xy.shape[0],
        distribution=dbh_distribution,
        mean=dbh_mean,
        std=dbh_std,
        dbh_min=dbh_min,
        dbh_max=min(dbh_max, 0.9 * min(tree_spacing, row_spacing)),
        rng=gen,
    )
    xy, dbh = xy[keep], dbh[keep]
    lo = xy.min(axis=0) - tree_spacing if xy.size else np.zeros(2)
    hi = xy.max(axis=0) + tree_spacing if xy.size else np.zeros(2)
    return Stand(xy, dbh, bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])))


# --------------------------------------------------------------------------------------------
# Clutter and non-circular trunks
# --------------------------------------------------------------------------------------------


def _polygon_segments(xy: FloatArray) -> FloatArray:
    """Closed polygon (V, 2) -> (V, 4) segments."""
    return np.column_stack((xy, np.roll(xy, -1, axis=0)))


def _with_clutter(
    stand: Stand,
    circ_xy: list[FloatArray],
    circ_r: list[FloatArray],
    segs: list[FloatArray],
    owners: list[NDArray[np.int64]],
    obj_xy: list[FloatArray],
    kinds: list[str],
    extents: list[float],
) -> Stand:
    """``stand`` with the accumulated clutter lists (each starting with the stand's own)."""
    return replace(
        stand,
        clutter_xy=np.vstack(circ_xy),
        clutter_radius=np.concatenate(circ_r),
        segments=np.vstack(segs),
        segment_owner=np.concatenate(owners),
        clutter_objects_xy=np.vstack(obj_xy),
        clutter_kinds=tuple(kinds),
        clutter_objects_extent=np.asarray(extents, dtype=np.float64),
    )


def add_clutter(
    stand: Stand,
    *,
    n_bushes: int = 0,
    n_branches: int = 0,
    n_walls: int = 0,
    n_fences: int = 0,
    n_rocks: int = 0,
    clearance: float = 0.3,
    rng: RngLike = None,
) -> Stand:
    """Add non-tree objects that reflect laser beams.

    Parameters
    ----------
    stand : Stand
    n_bushes : int
        Bushes: 6-15 thin stems (circles of radius 0.5-2.5 cm) scattered within 0.2-0.6 m of a
        centre -- many small, jumpy returns.
    n_branches : int
        Thin branches at scan height: straight segments 0.4-2.0 m long, random orientation.
    n_walls : int
        Walls: straight segments 4-12 m long.
    n_fences : int
        Fences: a rail (segment 5-15 m) with posts (circles of radius 5 cm) every 2 m.
    n_rocks : int
        Rocks: irregular polygons of mean radius 0.25-0.7 m (strongly non-circular outline).
    clearance : float, metres
        Minimum gap between a new object's centre region and any trunk surface.
    rng : numpy Generator or int seed

    Returns
    -------
    Stand
        A new stand with the clutter appended (``segment_owner = -1``) and one entry per object
        in ``clutter_objects_xy`` / ``clutter_kinds``.
    """
    for name, v in (
        ("n_bushes", n_bushes),
        ("n_branches", n_branches),
        ("n_walls", n_walls),
        ("n_fences", n_fences),
        ("n_rocks", n_rocks),
    ):
        if v < 0:
            raise ConfigError(f"{name} must be >= 0, got {v}.")
    gen = np.random.default_rng(rng)
    x0, y0, x1, y1 = stand.bounds
    if not (x1 > x0 and y1 > y0):
        if stand.n_trees:
            x0, y0 = stand.trees_xy.min(axis=0) - 2
            x1, y1 = stand.trees_xy.max(axis=0) + 2
        else:
            x0, y0, x1, y1 = 0.0, 0.0, 20.0, 20.0

    def free_point(extent: float) -> FloatArray:
        for _ in range(500):
            p = gen.uniform((x0, y0), (x1, y1))
            if stand.n_trees == 0:
                return p
            gap = np.hypot(*(stand.trees_xy - p).T) - stand.radii
            if gap.min() > extent + clearance:
                return p
        raise ConfigError(
            "add_clutter could not find free space for an object; the stand is too dense."
        )

    def free_segment(lo: float, hi: float) -> tuple[FloatArray, FloatArray]:
        """Centre and half-vector of a segment whose every point clears the trunks."""
        for _ in range(500):
            length = gen.uniform(lo, hi)
            c = gen.uniform((x0, y0), (x1, y1))
            a = gen.uniform(0, np.pi)
            d = 0.5 * length * np.array([math.cos(a), math.sin(a)])
            if stand.n_trees == 0:
                return c, d
            rel = stand.trees_xy - c
            t = np.clip(rel @ d / (d @ d), -1.0, 1.0)
            dist = np.hypot(*(rel - t[:, None] * d).T) - stand.radii
            if dist.min() > clearance:
                return c, d
        raise ConfigError(
            f"add_clutter could not fit a {lo}-{hi} m long object between the trunks; the "
            "stand is too dense for walls/fences/branches."
        )

    circ_xy: list[FloatArray] = [stand.clutter_xy]
    circ_r: list[FloatArray] = [stand.clutter_radius]
    segs: list[FloatArray] = [stand.segments]
    owners: list[NDArray[np.int64]] = [stand.segment_owner]
    obj_xy: list[FloatArray] = [stand.clutter_objects_xy]
    kinds: list[str] = list(stand.clutter_kinds)
    extents: list[float] = list(stand.clutter_objects_extent)

    def add_segments(s: FloatArray) -> None:
        segs.append(s.reshape(-1, 4))
        owners.append(np.full(s.reshape(-1, 4).shape[0], -1, dtype=np.int64))

    for _ in range(n_bushes):
        spread = gen.uniform(0.2, 0.6)
        c = free_point(spread)
        m = int(gen.integers(6, 16))
        ang = gen.uniform(0, 2 * np.pi, m)
        rad = spread * np.sqrt(gen.random(m))
        circ_xy.append(c + np.column_stack((rad * np.cos(ang), rad * np.sin(ang))))
        circ_r.append(gen.uniform(0.005, 0.025, m))
        obj_xy.append(c[None])
        kinds.append("bush")
        extents.append(spread)
    for _ in range(n_branches):
        c, d = free_segment(0.4, 2.0)
        length = 2 * float(np.hypot(*d))
        add_segments(np.concatenate((c - d, c + d)))
        obj_xy.append(c[None])
        kinds.append("branch")
        extents.append(length / 2)
    for _ in range(n_walls):
        c, d = free_segment(4.0, 12.0)
        length = 2 * float(np.hypot(*d))
        add_segments(np.concatenate((c - d, c + d)))
        obj_xy.append(c[None])
        kinds.append("wall")
        extents.append(length / 2)
    for _ in range(n_fences):
        c, d = free_segment(5.0, 15.0)
        length = 2 * float(np.hypot(*d))
        u = d / np.hypot(*d)
        add_segments(np.concatenate((c - 0.5 * length * u, c + 0.5 * length * u)))
        posts = c + np.outer(np.arange(-length / 2, length / 2 + 1e-9, 2.0), u)
        # posts stand just beside the rail so both reflect
        n_vec = np.array([-u[1], u[0]])
        circ_xy.append(posts + 0.06 * n_vec)
        circ_r.append(np.full(posts.shape[0], 0.05))
        obj_xy.append(c[None])
        kinds.append("fence")
        extents.append(length / 2)
    for _ in range(n_rocks):
        radius = gen.uniform(0.25, 0.7)
        c = free_point(radius * 1.5)
        nv = 24
        rr = rough_radius(nv, radius, 0.3, gen)
        phi = 2 * np.pi * np.arange(nv) / nv
        poly = c + np.column_stack((rr * np.cos(phi), rr * np.sin(phi)))
        add_segments(_polygon_segments(poly))
        obj_xy.append(c[None])
        kinds.append("rock")
        extents.append(float(rr.max()))

    return _with_clutter(stand, circ_xy, circ_r, segs, owners, obj_xy, kinds, extents)


def add_understory(
    stand: Stand,
    *,
    stems_per_tree: float = 1.0,
    branches_per_tree: float = 0.5,
    rng: RngLike = None,
) -> Stand:
    """Add what grows against real trunks at scan height (issue 11): thin understory stems
    beside the trunks and low branches leaving them.

    Parameters
    ----------
    stand : Stand
    stems_per_tree : float, >= 0
        Mean number (Poisson) of thin stems per tree: circles of radius 0.5-2.5 cm whose surface
        is 2-50 cm from the trunk's surface (a sapling, a sucker, a shrub stem: the
        segmentation may merge them with the trunk).
    branches_per_tree : float, >= 0
        Mean number (Poisson) of low branches per tree: straight segments 0.2-1.0 m long
        starting on the trunk surface (its circle of DBH) at a random azimuth, pointing outward
        within +-60 degrees of the radial direction (the lidR dbh slice's trunk has one: the
        trunk and the branch are one segment from most directions).
    rng : numpy Generator or int seed

    Returns
    -------
    Stand
        A new stand with the additions as clutter (kinds ``"understory"`` and ``"branch"``).
    """
    if not (stems_per_tree >= 0 and branches_per_tree >= 0):
        raise ConfigError(
            "add_understory needs stems_per_tree >= 0 and branches_per_tree >= 0, got "
            f"{stems_per_tree}, {branches_per_tree}."
        )
    gen = np.random.default_rng(rng)
    circ_xy: list[FloatArray] = [stand.clutter_xy]
    circ_r: list[FloatArray] = [stand.clutter_radius]
    segs: list[FloatArray] = [stand.segments]
    owners: list[NDArray[np.int64]] = [stand.segment_owner]
    obj_xy: list[FloatArray] = [stand.clutter_objects_xy]
    kinds = list(stand.clutter_kinds)
    extents = list(stand.clutter_objects_extent)
    for c, r in zip(stand.trees_xy, stand.radii, strict=True):
        for _ in range(int(gen.poisson(stems_per_tree))):
            rs = float(gen.uniform(0.005, 0.025))
            az = float(gen.uniform(0, 2 * np.pi))
            d = r + float(gen.uniform(0.02, 0.5)) + rs
            p = c + d * np.array([math.cos(az), math.sin(az)])
            circ_xy.append(p[None])
            circ_r.append(np.array([rs]))
            obj_xy.append(p[None])
            kinds.append("understory")
            extents.append(rs)
        for _ in range(int(gen.poisson(branches_per_tree))):
            az = float(gen.uniform(0, 2 * np.pi))
            length = float(gen.uniform(0.2, 1.0))
            out = az + float(gen.uniform(-math.pi / 3, math.pi / 3))
            p0 = c + r * np.array([math.cos(az), math.sin(az)])
            p1 = p0 + length * np.array([math.cos(out), math.sin(out)])
            segs.append(np.concatenate((p0, p1))[None])
            owners.append(np.full(1, -1, dtype=np.int64))
            obj_xy.append((0.5 * (p0 + p1))[None])
            kinds.append("branch")
            extents.append(length / 2)
    return _with_clutter(stand, circ_xy, circ_r, segs, owners, obj_xy, kinds, extents)


def make_trunks_noncircular(
    stand: Stand,
    *,
    ellipticity: float = 0.1,
    roughness: float = 0.02,
    n_vertices: int = 48,
    fraction: float = 1.0,
    bark_rms: float = 0.0,
    lean_deg: float = 0.0,
    buttress: float = 0.0,
    n_lobes: int = 4,
    rng: RngLike = None,
) -> Stand:
    """Replace round trunks by polygons (:func:`stemmap.sim.outline.trunk_outline`), owned by
    the tree: an ellipse with rough bark, optionally bark ridges, lean and buttress lobes.

    Parameters
    ----------
    stand : Stand
    ellipticity : float in [0, 0.5)
        Semi-axes are ``r (1 + e)`` and ``r (1 - e)`` with a random orientation, so the mean of
        the two caliper diameters stays the tree's DBH (``stand.diameters`` is unchanged).
    roughness : float, >= 0
        Relative RMS of a smooth random radius perturbation (out-of-roundness), e.g. 0.02 = 2 %.
    n_vertices : int, >= 8
        Polygon vertices per trunk (48 keeps the polygon chord error below 0.3 % of r; bark
        ridges need more, e.g. 240).
    fraction : float in [0, 1]
        Share of trees made non-circular (chosen at random).
    bark_rms : float, metres
        RMS of cm-scale bark ridges (harmonics 9 to n_vertices/4, 1/k spectrum).
    lean_deg : float, degrees
        Largest stem lean; each chosen tree leans uniformly in [0, lean_deg] (random azimuth),
        which stretches its horizontal section by 1/cos(lean). ``stand.diameters`` stays the
        diameter across the stem axis.
    buttress : float
        Relative height of buttress lobes (``n_lobes`` of them) at scan height.
    rng : numpy Generator or int seed
    """
    if not (0 <= ellipticity < 0.5 and roughness >= 0 and n_vertices >= 8 and 0 <= fraction <= 1):
        raise ConfigError(
            "make_trunks_noncircular needs 0 <= ellipticity < 0.5, roughness >= 0, "
            f"n_vertices >= 8, 0 <= fraction <= 1; got {ellipticity}, {roughness}, "
            f"{n_vertices}, {fraction}."
        )
    gen = np.random.default_rng(rng)
    chosen = (gen.random(stand.n_trees) < fraction) & ~stand.tree_is_polygon
    segs = [stand.segments]
    owners = [stand.segment_owner]
    for i in np.flatnonzero(chosen):
        lean = float(gen.uniform(0.0, lean_deg)) if lean_deg > 0 else 0.0
        outline = trunk_outline(
            float(stand.radii[i]),
            gen,
            n_vertices=n_vertices,
            ellipticity=ellipticity,
            roughness=roughness,
            bark_rms=bark_rms,
            lean_deg=lean,
            buttress=buttress,
            n_lobes=n_lobes,
        )
        segs.append(_polygon_segments(stand.trees_xy[i] + outline))
        owners.append(np.full(n_vertices, i, dtype=np.int64))
    return replace(
        stand,
        segments=np.vstack(segs),
        segment_owner=np.concatenate(owners),
        tree_is_polygon=stand.tree_is_polygon | chosen,
    )
