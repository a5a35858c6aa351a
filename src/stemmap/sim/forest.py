"""Simulated stands: tree positions and diameters, plus obstacles that are not trees.

A :class:`Stand` is pure geometry in the world frame (metres) at scan height. Trees are circles
(or, optionally, polygons owned by the tree: ellipses with rough bark); clutter is more circles
(bush stems) and line segments (walls, fences, fallen branches, rock outlines). Ground truth is
``stand.trees_xy`` / ``stand.diameters`` and, for the non-tree objects (needed to count true
rejects), ``stand.clutter_objects_xy`` / ``stand.clutter_kinds``.

Layouts: :func:`random_stand` (uniform with a minimum spacing), :func:`clustered_stand`
(Thomas cluster process), :func:`row_stand` (orchard / plantation rows). DBH values come from
:func:`sample_dbh`. :func:`stand_from_spec` builds a random stand (and its clutter) from the
declared scenario dict of a benchmark or the demo. :func:`add_clutter`, :func:`add_understory` and
:func:`make_trunks_noncircular` transform a stand; they live in :mod:`stemmap.sim.stand_features`
and are re-exported here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.sim.stand_features import (
    CLUTTER_KINDS,
    add_clutter,
    add_understory,
    make_trunks_noncircular,
)
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
    "stand_from_spec",
]

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


def _spaced_stand(
    candidates: FloatArray,
    size: tuple[float, float],
    n_trees: int,
    *,
    min_spacing: float,
    dbh: Mapping[str, Any],
    rng: np.random.Generator,
    too_dense: str,
) -> Stand:
    """A stand of the first ``n_trees`` candidate positions that keep ``min_spacing``, each with
    a DBH from :func:`sample_dbh` (``dbh``: its keyword arguments; one draw per candidate).

    Raises ConfigError "could place only k of n_trees <too_dense>" when fewer fit.
    """
    diam = sample_dbh(candidates.shape[0], rng=rng, **dbh)
    idx = _place_with_spacing(candidates, diam, min_spacing, n_trees)
    if idx.size < n_trees:
        raise ConfigError(f"could place only {idx.size} of {n_trees} {too_dense}")
    w, h = size
    return Stand(candidates[idx], diam[idx], bounds=(0.0, 0.0, w, h))


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
    dbh = {"distribution": dbh_distribution, "mean": dbh_mean, "std": dbh_std,
           "dbh_min": dbh_min, "dbh_max": dbh_max}  # fmt: skip
    too_dense = (
        f"trees in {w} x {h} m with spacing {min_spacing} m; enlarge the stand or reduce "
        "min_spacing."
    )
    return _spaced_stand(
        cand, (w, h), n_trees, min_spacing=min_spacing, dbh=dbh, rng=gen, too_dense=too_dense
    )


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
    dbh = {"distribution": dbh_distribution, "mean": dbh_mean, "std": dbh_std,
           "dbh_min": dbh_min, "dbh_max": dbh_max}  # fmt: skip
    too_dense = (
        f"clustered trees (n_clusters={n_clusters}, cluster_std={cluster_std} m, "
        f"min_spacing={min_spacing} m); use more or wider clusters."
    )
    return _spaced_stand(
        cand[inside], (w, h), n_trees, min_spacing=min_spacing, dbh=dbh, rng=gen,
        too_dense=too_dense,
    )  # fmt: skip


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


#: The keys of a stand spec and the :func:`random_stand` argument each one sets.
_STAND_SPEC_ARGS = {
    "dbh_mean_m": "dbh_mean",
    "dbh_std_m": "dbh_std",
    "dbh_min_m": "dbh_min",
    "dbh_max_m": "dbh_max",
    "min_spacing_m": "min_spacing",
}


def stand_from_spec(
    spec: Mapping[str, Any],
    clutter: Mapping[str, int] | None = None,
    *,
    n_trees: int | None = None,
    rng: RngLike = None,
) -> Stand:
    """The stand of a declared scenario: :func:`random_stand`, then :func:`add_clutter`.

    Benchmarks and ``stemmap demo`` declare every simulator parameter in one dict (the scenario,
    written into their outputs); this reads its ``"stand"`` and ``"clutter"`` parts.

    Parameters
    ----------
    spec : mapping
        ``"layout"`` (only ``"random"``), ``"size_m"`` (float: a square, or ``[width, height]``,
        metres), ``"n_trees"`` (int; may instead be given as ``n_trees``) and optionally
        ``"dbh_mean_m"``, ``"dbh_std_m"``, ``"dbh_min_m"``, ``"dbh_max_m"``,
        ``"min_spacing_m"`` (metres; absent keys take :func:`random_stand`'s defaults).
    clutter : mapping of str to int, optional
        The keyword arguments of :func:`add_clutter` (``n_bushes``, ``n_branches``, ...);
        ``None`` adds no clutter and draws nothing for it.
    n_trees : int, optional
        Trees in the stand; overrides ``spec["n_trees"]``.
    rng : numpy Generator or int seed
        One generator draws the stand, then the clutter. A Generator passed in is used (and
        advanced) as is, so a caller can go on drawing the drive from it.

    Returns
    -------
    Stand

    Raises
    ------
    ConfigError
        On another layout, an unknown key, no tree count, or a stand :func:`random_stand` /
        :func:`add_clutter` cannot place.

    Examples
    --------
    >>> spec = {"layout": "random", "size_m": 30.0, "n_trees": 20, "min_spacing_m": 1.0}
    >>> stand = stand_from_spec(spec, {"n_rocks": 2}, rng=1)
    >>> stand.n_trees, stand.clutter_kinds
    (20, ('rock', 'rock'))
    >>> stand_from_spec({"layout": "rows", "size_m": 30.0, "n_trees": 20})
    Traceback (most recent call last):
    ...
    stemmap.errors.ConfigError: stand layout 'rows' is not supported ...; use 'random'.
    """
    layout = spec.get("layout", "random")
    if layout != "random":
        raise ConfigError(
            f"stand layout {layout!r} is not supported by stand_from_spec; use 'random'."
        )
    unknown = set(spec) - {"layout", "size_m", "n_trees", *_STAND_SPEC_ARGS}
    if unknown:
        raise ConfigError(
            f"unknown stand spec keys {sorted(unknown)}; known: layout, size_m, n_trees, "
            f"{', '.join(_STAND_SPEC_ARGS)}."
        )
    n = spec.get("n_trees") if n_trees is None else n_trees
    if n is None:
        raise ConfigError("the stand spec has no 'n_trees'; give it there or as n_trees=.")
    size_m = spec["size_m"]
    size = (
        (float(size_m), float(size_m))
        if np.ndim(size_m) == 0
        else (float(size_m[0]), float(size_m[1]))
    )
    gen = np.random.default_rng(rng)
    kwargs = {arg: spec[key] for key, arg in _STAND_SPEC_ARGS.items() if key in spec}
    stand = random_stand(int(n), size, rng=gen, **kwargs)
    if clutter is not None:
        stand = add_clutter(stand, **clutter, rng=gen)
    return stand
