"""Forestrix feature-based SLAM (Öhman et al. 2007, §2): tree-group matching and a tree graph.

Per scan (their Fig. 2):

1. *Echoes* (the trees detected in one scan) are projected to the map with the odometry-predicted
   pose.
2. **Tree-group matching** (§2.1, :func:`match_tree_groups`): a tree and its nearest neighbours
   form a group (groups of six to eleven were tested); echo groups are matched to tree groups of
   the map on *inter-tree distances*, which are invariant to translation and rotation -- relative
   angles are redundant and not used. Matching proceeds a group at a time, closest echo first.
3. **Pose from the matches** (§2.1, :func:`pose_from_matches`): translate the echo set so the two
   centres of gravity coincide, then rotate it by the average angle between all echo-tree pairs
   (taken on the correct cycle).
4. **Tree-graph update** (§2.2, :class:`TreeGraph`): echoes become new trees or accumulate
   diameter information in old ones ("the closer the scan is taken, the better the diameter
   information": weights 1/range²); edges between co-observed trees record their measured
   distances.
5. **Relaxation** (§2.2, :func:`relax_tree_graph`): the mismatch between Cartesian node positions
   and edge lengths is distributed by a simple iterative algorithm when a loop closes.

False trees are removed afterwards with negative information (:mod:`stemmap.slam.negative`).

Decisions where the paper is silent (docs/algorithms/slam-frontends.md): the matching tolerance
and search radius, the support needed to accept a group match, updating old trees' positions by
a running mean, and the loop-closure trigger (an old tree -- last seen more than
``loop_gap_s`` ago -- is re-matched).

References
----------
.. [Ohman2007] M. Öhman, M. Miettinen, K. Kannas, J. Jutila, A. Visala, P. Forsman, "Tree
   Measurement and Simultaneous Localization and Mapping System for Forest Harvesters",
   FSR 2007, §2.1-2.2.
"""

from __future__ import annotations

import logging
import math
import time as _time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from stemmap.errors import ConfigError, InputError
from stemmap.slam.relaxation import (
    LoopClosure,
    RigidFit,
    fit_rigid_robust,
    loop_constraint,
    relax_trajectory,
    remap_trees,
)
from stemmap.types import FloatArray, ScanBatch, StemMap, Tree, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem, SlamResult

__all__ = [
    "PRESETS",
    "ForestrixSlam",
    "LoopMatch",
    "PoseFit",
    "TreeGraph",
    "find_loop_closure",
    "match_tree_groups",
    "pose_from_matches",
    "relax_tree_graph",
]

log = logging.getLogger(__name__)
IntArray = NDArray[np.int64]

#: The paper's method: mean-angle pose (Öhman 2007 §2.1); group sizes 6..11 were tested.
PRESETS: dict[str, dict[str, int | str]] = {
    "ohman2007": {"group_size": 8, "pose_method": "ohman2007"},
    "ohman2007_g6": {"group_size": 6, "pose_method": "ohman2007"},
    "ohman2007_g11": {"group_size": 11, "pose_method": "ohman2007"},
}


# --------------------------------------------------------------------------------------------
# Tree-group matching on inter-tree distances
# --------------------------------------------------------------------------------------------


def _neighbours(xy: FloatArray, k: int) -> tuple[IntArray, FloatArray]:
    """Indices (N, k) and distances (N, k) of each point's k nearest others (-1 / inf padding)."""
    n = xy.shape[0]
    idx = np.full((n, k), -1, dtype=np.int64)
    dist = np.full((n, k), np.inf)
    if n < 2 or k < 1:
        return idx, dist
    kk = min(k + 1, n)
    d, i = cKDTree(xy).query(xy, k=kk)
    d = np.asarray(d).reshape(n, kk)[:, 1:]
    i = np.asarray(i).reshape(n, kk)[:, 1:]
    idx[:, : kk - 1] = i
    dist[:, : kk - 1] = d
    return idx, dist


def match_tree_groups(
    echo_xy: ArrayLike,
    tree_xy: ArrayLike,
    *,
    group_size: int = 8,
    dist_tol: float = 0.3,
    search_radius: float = 2.0,
    min_support: int = 2,
    echo_order: ArrayLike | None = None,
) -> IntArray:
    """Match the echoes of one scan to map trees by tree groups (Öhman 2007 §2.1).

    A *group* is a tree and its ``group_size - 1`` nearest neighbours (echo groups within the
    scan; tree groups among the map trees that are a candidate of some echo, i.e. that may be in
    view -- the paper's "the tree graph is usually incomplete" problem turned around). A
    candidate pair (echo i, tree j) -- tree j within ``search_radius`` of echo i's predicted
    position -- gets one vote of *support* for every
    neighbour i' of i for which some neighbour j' of j is a candidate for i' and
    ``|d(i, i') - d(j, j')| <= dist_tol``: only inter-tree distances are compared (they are
    invariant to the unknown pose error). Echoes are matched one group at a time, in
    ``echo_order`` (default: as given; the back-end passes closest first), each to its
    best-supported free tree if the support reaches ``min_support``.

    Parameters
    ----------
    echo_xy : ndarray (K, 2), m
        Echoes in map coordinates (predicted pose).
    tree_xy : ndarray (N, 2), m
        Map trees.
    group_size : int in [2, 20]
        Trees per group including the centre (paper: 6..11 tested).
    dist_tol : float, m
        Tolerance on matching inter-tree distances.
    search_radius : float, m
        How far a tree may be from an echo's predicted position to be a candidate (bounds the
        pose error the matcher can absorb).
    min_support : int
        Distance agreements needed to accept a match.
    echo_order : ndarray (K,), int, optional

    Returns
    -------
    ndarray (K,), int
        Matched tree index per echo, -1 where unmatched.

    Raises
    ------
    InputError
        On malformed coordinates; ConfigError on bad parameters.
    """
    e = np.asarray(echo_xy, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(t))):
        raise InputError("match_tree_groups: echo and tree coordinates must be finite.")
    if not 2 <= int(group_size) <= 20:
        raise ConfigError(f"group_size must be in [2, 20], got {group_size}.")
    if not (dist_tol > 0 and search_radius > 0 and min_support >= 1):
        raise ConfigError("dist_tol and search_radius must be > 0 and min_support >= 1.")
    k, n = e.shape[0], t.shape[0]
    out = np.full(k, -1, dtype=np.int64)
    if k == 0 or n == 0:
        return out
    cand = np.hypot(e[:, None, 0] - t[None, :, 0], e[:, None, 1] - t[None, :, 1]) <= search_radius
    ci, cj = np.nonzero(cand)
    if ci.size == 0:
        return out
    g = int(group_size) - 1
    ne, de = _neighbours(e, g)  # (K, g)
    # Tree groups are formed among the trees that could be in this scan (a candidate of some
    # echo): the map around the scan is usually denser than what the scan sees (blind areas),
    # and groups over all map trees would hold neighbours no echo group can contain.
    inview = np.flatnonzero(cand.any(axis=0))
    nt_sub, dt_sub = _neighbours(t[inview], g)
    nt = np.full((n, g), -1, dtype=np.int64)
    dt = np.full((n, g), np.inf)
    nt[inview] = np.where(nt_sub >= 0, inview[np.clip(nt_sub, 0, None)], -1)
    dt[inview] = dt_sub
    # (Q, g, g): neighbour a of echo ci vs neighbour b of tree cj
    ea = ne[ci]
    tb = nt[cj]
    ok = (ea[:, :, None] >= 0) & (tb[:, None, :] >= 0)
    with np.errstate(invalid="ignore"):  # inf - inf on padded (missing) neighbours
        agree = np.abs(de[ci][:, :, None] - dt[cj][:, None, :]) <= dist_tol
    pair_is_cand = cand[np.clip(ea, 0, None)[:, :, None], np.clip(tb, 0, None)[:, None, :]]
    support = np.sum(np.any(ok & agree & pair_is_cand, axis=2), axis=1)  # (Q,)
    # tie-break by distance to the predicted position
    dist = np.hypot(e[ci, 0] - t[cj, 0], e[ci, 1] - t[cj, 1])
    order = np.arange(k) if echo_order is None else np.asarray(echo_order, dtype=np.int64)
    used = np.zeros(n, dtype=bool)
    for i in order:
        sel = np.flatnonzero((ci == i) & (support >= min_support))
        if sel.size == 0:
            continue
        sel = sel[~used[cj[sel]]]
        if sel.size == 0:
            continue
        best = sel[np.lexsort((dist[sel], -support[sel]))[0]]
        out[i] = cj[best]
        used[cj[best]] = True
    return out


@dataclass(frozen=True)
class PoseFit:
    """A rigid correction ``p -> R(dtheta) (p - centre) + centre + shift`` of map points.

    Falsy with a ``reason`` when it could not be estimated.
    """

    dtheta: float = 0.0
    centre: tuple[float, float] = (0.0, 0.0)
    shift: tuple[float, float] = (0.0, 0.0)
    n_pairs: int = 0
    reason: str = ""

    def __bool__(self) -> bool:
        return not self.reason

    def apply_points(self, xy: ArrayLike) -> FloatArray:
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.dtheta), math.sin(self.dtheta)
        q = p - np.asarray(self.centre)
        out: FloatArray = q @ np.array([[c, s], [-s, c]]) + np.asarray(self.centre)
        return out + np.asarray(self.shift)

    def apply_pose(self, pose: ArrayLike) -> FloatArray:
        p = np.asarray(pose, dtype=np.float64).reshape(3)
        xy = self.apply_points(p[:2])[0]
        return np.array([xy[0], xy[1], wrap_angle(p[2] + self.dtheta)])


def pose_from_matches(
    echo_xy: ArrayLike,
    tree_xy: ArrayLike,
    *,
    method: Literal["ohman2007", "procrustes"] = "ohman2007",
) -> PoseFit:
    """Rigid correction that moves matched echoes onto their trees (Öhman 2007 §2.1).

    ``"ohman2007"``: translate so the centres of gravity coincide, then rotate about it by the
    circular mean of the angles between every echo-tree pair (each pair's angle
    ``atan2(t - cog_t) - atan2(e - cog_e)``, wrapped so all are "on the correct cycle").
    ``"procrustes"`` (ours): the least-squares rotation (pairs weighted by their distances from
    the centre, ``atan2(Σ e × t, Σ e · t)``), which down-weights pairs near the centre whose
    angles are unreliable.

    Parameters
    ----------
    echo_xy, tree_xy : ndarray (M, 2), m -- matched pairs, row by row
    method : {"ohman2007", "procrustes"}

    Returns
    -------
    PoseFit
        Falsy (reason set) with fewer than 2 pairs or coincident points.

    Examples
    --------
    >>> fit = pose_from_matches([[0, 0], [1, 0]], [[1, 1], [1, 2]])
    >>> round(fit.dtheta, 6), bool(fit)
    (1.570796, True)
    """
    e = np.asarray(echo_xy, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    if e.shape != t.shape:
        raise InputError(f"pose_from_matches: {e.shape[0]} echoes but {t.shape[0]} trees.")
    if method not in ("ohman2007", "procrustes"):
        raise ConfigError(f"unknown pose method {method!r}; use 'ohman2007' or 'procrustes'.")
    m = e.shape[0]
    if m < 2:
        return PoseFit(n_pairs=m, reason=f"need at least 2 matched pairs, got {m}")
    ce, ct = e.mean(axis=0), t.mean(axis=0)
    qe, qt = e - ce, t - ct
    ne = np.hypot(qe[:, 0], qe[:, 1])
    nt = np.hypot(qt[:, 0], qt[:, 1])
    good = (ne > 1e-9) & (nt > 1e-9)
    if not np.any(good):
        return PoseFit(n_pairs=m, reason="all matched points coincide with their centre")
    if method == "ohman2007":
        ang = wrap_angle(
            np.arctan2(qt[good, 1], qt[good, 0]) - np.arctan2(qe[good, 1], qe[good, 0])
        )
        dth = float(np.arctan2(np.mean(np.sin(ang)), np.mean(np.cos(ang))))
    else:
        cross = np.sum(qe[:, 0] * qt[:, 1] - qe[:, 1] * qt[:, 0])
        dot = np.sum(qe[:, 0] * qt[:, 0] + qe[:, 1] * qt[:, 1])
        dth = float(np.arctan2(cross, dot))
    shift = ct - ce
    return PoseFit(dth, (float(ce[0]), float(ce[1])), (float(shift[0]), float(shift[1])), m)


# --------------------------------------------------------------------------------------------
# Tree graph and relaxation
# --------------------------------------------------------------------------------------------


class TreeGraph:
    """Hybrid graph of the map (Öhman 2007 §2.2): nodes with Cartesian positions, diameters and
    counts; edges with measured lengths (mean of the in-scan distances between co-observed trees).

    Node attributes are numpy arrays with amortised growth (``xy[:len(graph)]`` are valid).
    """

    def __init__(self) -> None:
        self._n = 0
        self._xy = np.zeros((64, 2))
        self._count = np.zeros(64, dtype=np.int64)
        self._dia_wsum = np.zeros(64)
        self._dia_w = np.zeros(64)
        self._first = np.zeros(64)
        self._last = np.zeros(64)
        self._alive = np.zeros(64, dtype=bool)
        self.edges: dict[tuple[int, int], list[float]] = {}

    def __len__(self) -> int:
        return self._n

    @property
    def xy(self) -> FloatArray:
        """Node positions (N, 2), a view (do not resize)."""
        return self._xy[: self._n]

    @property
    def count(self) -> IntArray:
        return self._count[: self._n]

    @property
    def alive(self) -> NDArray[np.bool_]:
        """False for nodes merged into another (:meth:`merge`)."""
        return self._alive[: self._n]

    @property
    def first_time(self) -> FloatArray:
        return self._first[: self._n]

    @property
    def last_time(self) -> FloatArray:
        return self._last[: self._n]

    def positions(self) -> FloatArray:
        """A copy of the node positions (N, 2)."""
        return self._xy[: self._n].copy()

    def set_positions(self, xy: FloatArray) -> None:
        self._xy[: self._n] = np.asarray(xy, dtype=np.float64).reshape(self._n, 2)

    def _grow(self) -> None:
        cap = 2 * self._xy.shape[0]
        for name in ("_xy", "_count", "_dia_wsum", "_dia_w", "_first", "_last", "_alive"):
            old = getattr(self, name)
            new = np.zeros((cap, *old.shape[1:]), dtype=old.dtype)
            new[: old.shape[0]] = old
            setattr(self, name, new)

    def add_tree(self, xy: FloatArray, diameter: float, weight: float, time: float) -> int:
        if self._n == self._xy.shape[0]:
            self._grow()
        j = self._n
        self._xy[j] = xy
        self._count[j] = 1
        ok = math.isfinite(diameter)
        self._dia_wsum[j] = weight * diameter if ok else 0.0
        self._dia_w[j] = weight if ok else 0.0
        self._first[j] = time
        self._last[j] = time
        self._alive[j] = True
        self._n += 1
        return j

    def merge(self, src: int, dst: int) -> None:
        """Node ``src`` is the same tree as ``dst``: pool counts, diameters and times into
        ``dst`` and retire ``src`` (positions are re-mapped by the caller)."""
        if src == dst:
            return
        self._count[dst] += self._count[src]
        self._dia_wsum[dst] += self._dia_wsum[src]
        self._dia_w[dst] += self._dia_w[src]
        self._first[dst] = min(self._first[dst], self._first[src])
        self._last[dst] = max(self._last[dst], self._last[src])
        self._count[src] = 0
        self._alive[src] = False

    def set_counts(self, count: ArrayLike) -> None:
        self._count[: self._n] = np.asarray(count, dtype=np.int64).reshape(self._n)

    def update_tree(
        self, j: int, xy: FloatArray, diameter: float, weight: float, time: float
    ) -> None:
        c = float(self._count[j])
        self._xy[j] = (c * self._xy[j] + xy) / (c + 1.0)
        self._count[j] += 1
        if math.isfinite(diameter):
            self._dia_wsum[j] += weight * diameter
            self._dia_w[j] += weight
        self._last[j] = time

    def add_edge(self, i: int, j: int, length: float) -> None:
        if i == j:
            return
        key = (i, j) if i < j else (j, i)
        e = self.edges.get(key)
        if e is None:
            self.edges[key] = [length, 1.0]
        else:
            e[0] += length
            e[1] += 1.0

    def edge_arrays(self) -> tuple[IntArray, FloatArray, FloatArray]:
        """(E, 2) node pairs, (E,) mean lengths, (E,) observation counts."""
        if not self.edges:
            return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
        keys = np.array(list(self.edges.keys()), dtype=np.int64)
        vals = np.array(list(self.edges.values()), dtype=np.float64)
        return keys, vals[:, 0] / vals[:, 1], vals[:, 1]

    def diameters(self) -> FloatArray:
        w = self._dia_w[: self._n]
        s = self._dia_wsum[: self._n]
        return np.where(w > 0, s / np.where(w > 0, w, 1.0), np.nan)


def relax_tree_graph(
    xy: ArrayLike,
    edges: ArrayLike,
    lengths: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    iterations: int = 200,
    step: float = 0.5,
    fixed: ArrayLike | None = None,
) -> FloatArray:
    """Distribute the tension of a tree graph (Öhman 2007 §2.2) by iterative spring relaxation.

    Each edge (i, j) with measured length ``l`` pulls or pushes its nodes along the edge by half
    of ``(|x_j - x_i| - l)``; every node moves by the weighted mean of its edges' pulls times
    ``step`` (Jacobi iteration). This lowers ``Σ w (|x_i - x_j| - l)²`` and spreads a loop's
    accumulated error over the whole loop instead of leaving it at the closing edge.

    Parameters
    ----------
    xy : ndarray (N, 2), m
    edges : ndarray (E, 2), int
    lengths : ndarray (E,), m
    weights : ndarray (E,), optional (e.g. observation counts)
    iterations : int
    step : float in (0, 1]
    fixed : ndarray (N,) bool, optional -- nodes that do not move

    Returns
    -------
    ndarray (N, 2): relaxed positions (the input is not modified).
    """
    x = np.array(xy, dtype=np.float64).reshape(-1, 2)
    ed = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ln = np.asarray(lengths, dtype=np.float64).reshape(-1)
    if ed.shape[0] != ln.shape[0]:
        raise InputError(f"relax_tree_graph: {ed.shape[0]} edges but {ln.shape[0]} lengths.")
    if ed.size and (ed.min() < 0 or ed.max() >= x.shape[0]):
        raise InputError("relax_tree_graph: edge endpoints must index the nodes.")
    if not 0 < step <= 1:
        raise ConfigError(f"relax_tree_graph: step must be in (0, 1], got {step}.")
    w = np.ones(ln.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    n = x.shape[0]
    if ed.shape[0] == 0 or n == 0:
        return x
    i, j = ed[:, 0], ed[:, 1]
    wsum = np.bincount(i, weights=w, minlength=n) + np.bincount(j, weights=w, minlength=n)
    wsum = np.where(wsum > 0, wsum, 1.0)
    movable = np.ones(n) if fixed is None else (~np.asarray(fixed, dtype=bool)).astype(float)
    for _ in range(int(iterations)):
        d = x[j] - x[i]
        cur = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        pull = (0.5 * (cur - ln) / cur * w)[:, None] * d  # move i towards j if too long
        move = np.column_stack(
            (
                np.bincount(i, pull[:, 0], n) - np.bincount(j, pull[:, 0], n),
                np.bincount(i, pull[:, 1], n) - np.bincount(j, pull[:, 1], n),
            )
        )
        x += step * movable[:, None] * move / wsum[:, None]
    return x


# --------------------------------------------------------------------------------------------
# Back-end
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Loop detection by tree-group matching against the older map
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LoopMatch:
    """A loop closure found by :func:`find_loop_closure`: ``recent[k]`` revisits ``old[k]``
    (indices into the arrays given), and ``fit`` moves the recent trees onto the old ones."""

    recent: IntArray
    old: IntArray
    fit: RigidFit

    def __bool__(self) -> bool:
        return bool(self.fit) and self.recent.size > 0


def find_loop_closure(
    recent_xy: ArrayLike,
    old_xy: ArrayLike,
    *,
    group_size: int = 8,
    dist_tol: float = 0.3,
    search_radius: float = 10.0,
    min_support: int = 3,
    min_matches: int = 5,
    inlier_dist: float = 1.0,
    max_rms: float = 0.4,
    order_from: ArrayLike | None = None,
) -> LoopMatch:
    """Recognise a revisit: match the recently mapped trees to the older map by tree groups.

    Öhman 2007 §2.1 matches echo groups to tree groups on inter-tree distances, which do not
    depend on the (drifted) pose; here the "echoes" are the trees mapped in the last seconds and
    the tree graph is the part of the map not seen for a while, so a drift far beyond the
    scan-to-map search radius is still recognised (``search_radius``: how far the recent trees
    may have drifted). The matched pairs must agree on one rigid motion
    (:func:`~stemmap.slam.relaxation.fit_rigid_robust`: at least ``min_matches`` pairs within
    ``inlier_dist`` after the fit, RMS <= ``max_rms``) -- the verification the paper leaves to
    its pose estimate.

    Parameters
    ----------
    recent_xy : ndarray (R, 2), m
    old_xy : ndarray (O, 2), m
    order_from : (2,), optional
        Match the recent trees closest to this point first (the sensor).

    Returns
    -------
    LoopMatch
        Falsy when no consistent revisit was found.
    """
    r = np.asarray(recent_xy, dtype=np.float64).reshape(-1, 2)
    o = np.asarray(old_xy, dtype=np.float64).reshape(-1, 2)
    empty = np.zeros(0, dtype=np.int64)
    if r.shape[0] < min_matches or o.shape[0] < min_matches:
        return LoopMatch(empty, empty, RigidFit(reason="too few trees to match"))
    order = None
    if order_from is not None:
        c = np.asarray(order_from, dtype=np.float64).reshape(2)
        order = np.argsort(np.hypot(r[:, 0] - c[0], r[:, 1] - c[1]))
    m = match_tree_groups(
        r,
        o,
        group_size=group_size,
        dist_tol=dist_tol,
        search_radius=search_radius,
        min_support=min_support,
        echo_order=order,
    )
    ri = np.flatnonzero(m >= 0)
    oi = m[ri]
    fit = fit_rigid_robust(
        r[ri], o[oi], inlier_dist=inlier_dist, min_inliers=min_matches, max_rms=max_rms
    )
    if not fit or fit.inliers is None:
        return LoopMatch(empty, empty, fit)
    return LoopMatch(ri[fit.inliers], oi[fit.inliers], fit)


# --------------------------------------------------------------------------------------------
# Back-end
# --------------------------------------------------------------------------------------------


@dataclass
class ForestrixSlam:
    """Forestrix SLAM back-end (Öhman et al. 2007 §2).

    Per frame: predict with the odometry, match the scan's echoes by tree groups to the trees
    seen in the last ``loop_gap_s`` (scan-to-map odometry), correct the pose, add or update
    trees. Every ``loop_every_s``, the trees first mapped in the last ``loop_window_s`` are
    matched by tree groups to the *older* map (:func:`find_loop_closure`); a revisit adds a loop
    constraint, merges the revisited trees, relaxes the trajectory
    (:func:`~stemmap.slam.relaxation.relax_trajectory`, GTSAM) and re-maps every tree from the
    relaxed poses (``relaxation="pose_graph"``, default). ``relaxation="tree_graph"`` is the
    older behaviour: one map, matched whole, and the paper's spring iteration on the tree graph
    (:func:`relax_tree_graph`) when an old tree is re-matched; it moves map nodes only.

    Parameters
    ----------
    preset : str, optional
        ``"ohman2007"`` (group size 8), ``"ohman2007_g6"``, ``"ohman2007_g11"``: the paper's
        mean-angle pose estimate with that group size.
    group_size : int
        Trees per group (paper: 6..11 tested; default 8).
    dist_tol : float, m
    search_radius : float, m
    min_support : int
    min_matches : int
        Matched echoes needed to correct the pose (>= 2).
    pose_method : {"ohman2007", "procrustes"}
        Default ``"procrustes"`` (ours; see :func:`pose_from_matches`); the presets select the
        paper's mean angle.
    new_tree_gate : float, m
        After the pose correction, an unmatched echo this close to a (recent) map tree is that
        tree; otherwise it is a new tree.
    new_tree_gate_per_m : float, m per m of range
        Ours: widen that gate with range, ``max(new_tree_gate, new_tree_gate_per_m * r)``.
    loop_gap_s : float, s
        Trees not seen for this long are the "older map": the scan matcher ignores them and the
        loop detector matches against them.
    relaxation : {"pose_graph", "tree_graph", "none"}
    loop_every_s, loop_window_s : float, s
        How often loop detection runs, and how far back "recent" trees go.
    loop_search_radius : float, m
        Drift a revisit may have accumulated and still be recognised.
    loop_min_support, loop_min_matches : int
        Distance agreements per tree pair and agreeing pairs needed for a loop closure.
    loop_sigmas : (m, m, rad)
        Standard deviations of a loop constraint.
    relax_iterations : int
        Spring iterations (``"tree_graph"``) or LM iterations (``"pose_graph"``).
    relax_cooldown_s : float, s
        Minimum time between two tree-graph relaxations (``"tree_graph"`` only).
    keyframe_dist : float, m
        Pose-graph nodes every this many metres (or 0.1 rad of turn).
    min_observations : int
        Trees seen fewer times are left out of the output map.
    max_range : float, m
        Detections farther than this are not used (neither for the pose nor the map).
    merge_dist, merge_ddiam : float, m
        Output trees closer than ``merge_dist`` with diameters within ``merge_ddiam`` (or
        overlapping trunks) are one tree (iSAM2's rule). 0 disables.
    false_trees : {"none", "rays", "detections"}
        Öhman's false-tree removal (§2.2, Fig. 5) on the output map: ``"rays"`` casts the raw
        scan rays (``run(..., scans=...)``) through the mapped trees
        (:func:`~stemmap.slam.negative.remove_false_trees_by_rays`); ``"detections"`` counts
        frames that should have seen a tree but did not
        (:func:`~stemmap.slam.negative.remove_false_trees_after`). Default ``"rays"``: used when
        raw scans are given, skipped (and said so in ``stats``) otherwise.
    """

    preset: str | None = None
    group_size: int = 8
    dist_tol: float = 0.3
    search_radius: float = 2.0
    min_support: int = 2
    min_matches: int = 2
    pose_method: Literal["ohman2007", "procrustes"] = "procrustes"
    new_tree_gate: float = 0.7
    new_tree_gate_per_m: float = 0.02
    loop_gap_s: float = 60.0
    relaxation: Literal["pose_graph", "tree_graph", "none"] = "pose_graph"
    loop_every_s: float = 1.0
    loop_window_s: float = 20.0
    loop_search_radius: float = 10.0
    loop_min_support: int = 3
    loop_min_matches: int = 5
    loop_sigmas: tuple[float, float, float] = (0.3, 0.3, math.radians(1.0))
    relax_iterations: int = 200
    relax_cooldown_s: float = 10.0
    keyframe_dist: float = 2.0
    min_observations: int = 5
    max_range: float = 50.0
    merge_dist: float = 1.0
    merge_ddiam: float = 0.42
    false_trees: Literal["none", "rays", "detections"] = "rays"
    name: str = "forestrix"

    def __post_init__(self) -> None:
        if self.preset is not None:
            if self.preset not in PRESETS:
                raise ConfigError(
                    f"unknown ForestrixSlam preset {self.preset!r}; choose from {sorted(PRESETS)}."
                )
            cfg = PRESETS[self.preset]
            self.group_size = int(cfg["group_size"])
            self.pose_method = "ohman2007" if cfg["pose_method"] == "ohman2007" else "procrustes"
        if not 2 <= int(self.group_size) <= 20:
            raise ConfigError(
                f"ForestrixSlam.group_size must be in [2, 20], got {self.group_size}."
            )
        if int(self.min_matches) < 2:
            raise ConfigError("ForestrixSlam.min_matches must be >= 2 (a rotation needs 2 pairs).")
        if self.pose_method not in ("ohman2007", "procrustes"):
            raise ConfigError(f"unknown pose_method {self.pose_method!r}.")
        if self.relaxation not in ("pose_graph", "tree_graph", "none"):
            raise ConfigError(
                f"unknown relaxation {self.relaxation!r}; use 'pose_graph', 'tree_graph' or 'none'."
            )
        if self.false_trees not in ("none", "rays", "detections"):
            raise ConfigError(
                f"unknown false_trees {self.false_trees!r}; use 'none', 'rays' or 'detections'."
            )
        if not (self.dist_tol > 0 and self.search_radius > 0 and self.new_tree_gate > 0):
            raise ConfigError("ForestrixSlam: dist_tol, search_radius, new_tree_gate must be > 0.")
        if not (self.loop_search_radius > 0 and self.loop_every_s > 0 and self.keyframe_dist > 0):
            raise ConfigError(
                "ForestrixSlam: loop_search_radius, loop_every_s and keyframe_dist must be > 0."
            )
        if int(self.loop_min_matches) < 3:
            raise ConfigError("ForestrixSlam.loop_min_matches must be >= 3.")
        if not (self.merge_dist >= 0 and self.merge_ddiam >= 0):
            raise ConfigError(
                f"ForestrixSlam: merge_dist and merge_ddiam must be >= 0 m, got "
                f"{self.merge_dist}, {self.merge_ddiam}."
            )

    def run(
        self,
        problem: SlamProblem,
        *,
        progress: Callable[[int, int], None] | None = None,
        scans: ScanBatch | None = None,
    ) -> SlamResult:
        """Run Forestrix over ``problem``; see the class docstring.

        ``scans``: the raw scans, one per frame of ``problem`` (same order), for the ray-cast
        false-tree removal (``false_trees="rays"``).
        """
        from stemmap.slam.base import SlamResult, frame_trajectory

        t_start = _time.perf_counter()
        frames = problem.frames
        if scans is not None and np.atleast_2d(scans.ranges).shape[0] != len(frames):
            raise InputError(
                f"ForestrixSlam.run: {np.atleast_2d(scans.ranges).shape[0]} scans for "
                f"{len(frames)} frames; give one raw scan per frame."
            )
        st = _RunState(self, problem)
        for f in range(len(frames)):
            st.step(f)
            if progress is not None and (f % 200 == 0 or f == len(frames) - 1):
                progress(f + 1, len(frames))
        st.finish()
        stem_map, n_merged = self._output_map(st)
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "graph_nodes": len(st.graph),
            "graph_edges": len(st.graph.edges),
            "trees_merged": n_merged,
            "frames_corrected": st.n_corrected,
            "loop_closures": len(st.loops) if self.relaxation == "pose_graph" else st.n_loops,
            "relaxations": st.n_relax,
            "trees_merged_at_loops": st.n_loop_merged,
            "trees_merged_after_relaxation": st.n_close_merged,
        }
        stem_map = self._remove_false_trees(stem_map, st, problem, scans, stats)
        stats["trees_mapped"] = len(stem_map)
        stats["runtime_s"] = float(_time.perf_counter() - t_start)
        return SlamResult(frame_trajectory(frames.times, st.poses), stem_map, stats)

    # ---- output ------------------------------------------------------------------------

    def _output_map(self, st: _RunState) -> tuple[StemMap, int]:
        g = st.graph
        keep = np.flatnonzero(g.alive & (g.count >= self.min_observations))
        xy = g.positions()[keep]
        dia = g.diameters()[keep]
        cnt = g.count[keep].astype(np.float64)
        t_first = np.asarray(g.first_time, dtype=np.float64)[keep]
        t_last = np.asarray(g.last_time, dtype=np.float64)[keep]
        n_merged = 0
        if self.merge_dist > 0 and keep.size > 1:
            from stemmap.slam.graph import _merge_duplicates

            rep = _merge_duplicates(
                xy, np.nan_to_num(dia, nan=0.0), cnt, self.merge_dist, self.merge_ddiam
            )
            groups, inv = np.unique(rep, return_inverse=True)
            n_merged = keep.size - groups.size
            w = np.bincount(inv, weights=cnt)
            xy = np.column_stack([np.bincount(inv, weights=cnt * xy[:, i]) / w for i in range(2)])
            fin = np.isfinite(dia)
            wd = np.bincount(inv, weights=np.where(fin, cnt, 0.0))
            dsum = np.bincount(inv, weights=np.where(fin, cnt * np.nan_to_num(dia), 0.0))
            dia = np.where(wd > 0, dsum / np.where(wd > 0, wd, 1.0), np.nan)
            first = np.full(groups.size, np.inf)
            np.minimum.at(first, inv, t_first)
            last = np.full(groups.size, -np.inf)
            np.maximum.at(last, inv, t_last)
            cnt = np.asarray(w, dtype=np.float64)
            t_first, t_last = first, last
        trees = [
            Tree(
                id=i,
                x=float(xy[i, 0]),
                y=float(xy[i, 1]),
                diameter=float(dia[i]),
                n_obs=int(cnt[i]),
                first_time=float(t_first[i]),
                last_time=float(t_last[i]),
            )
            for i in range(xy.shape[0])
        ]
        return StemMap(tuple(trees)), n_merged

    def _remove_false_trees(
        self,
        stem_map: StemMap,
        st: _RunState,
        problem: SlamProblem,
        scans: ScanBatch | None,
        stats: dict[str, float | int | str],
    ) -> StemMap:
        """Öhman §2.2 / Fig. 5 on the output map, at the final poses."""
        from stemmap.slam.base import SlamResult, frame_trajectory, sensor_poses

        mode = self.false_trees
        if mode == "rays" and scans is None:
            stats["false_trees"] = "skipped: no raw scans"
            return stem_map
        stats["false_trees"] = mode
        if mode == "none" or len(stem_map) == 0:
            stats["false_trees_removed"] = 0
            return stem_map
        if mode == "rays":
            from stemmap.slam.negative import remove_false_trees_by_rays

            sp = sensor_poses(st.poses, problem.sensor_offset)
            cleaned, res = remove_false_trees_by_rays(stem_map, sp, scans)  # type: ignore[arg-type]
        else:
            from stemmap.slam.negative import remove_false_trees_after

            tmp = SlamResult(frame_trajectory(problem.frames.times, st.poses), stem_map, {})
            cleaned, res = remove_false_trees_after(tmp, problem)
        stats["false_trees_removed"] = res.n_removed
        return cleaned


class _RunState:
    """Mutable state of one :meth:`ForestrixSlam.run` (front-end, loop closures, relaxation)."""

    def __init__(self, cfg: ForestrixSlam, problem: SlamProblem) -> None:
        from stemmap.slam.motion import preintegrate

        self.cfg = cfg
        self.problem = problem
        fr = problem.frames
        self.frames = fr
        self.off = problem.sensor_offset
        self.pre = preintegrate(
            problem.motion,
            problem.controls,
            fr.times,
            np.asarray(problem.initial_pose),
            with_covariance=False,
        )
        self.pose = np.asarray(problem.initial_pose, dtype=np.float64).copy()
        self.poses = np.empty((len(fr), 3))
        self.graph = TreeGraph()
        self.det_tree = np.full(fr.n_detections, -1, dtype=np.int64)
        self.det_frame = fr.frame_index
        self.keyframes: list[int] = [0]
        self.loops: list[LoopClosure] = []
        self.pending = False
        self.n_corrected = 0
        self.n_loops = 0
        self.n_relax = 0
        self.n_loop_merged = 0
        self.n_close_merged = 0
        self.last_relax = -math.inf
        self.last_loop_try = -math.inf
        self.windowed = cfg.relaxation == "pose_graph"

    # ---- per frame -----------------------------------------------------------------------

    def step(self, f: int) -> None:
        from stemmap.slam.base import observation_to_world
        from stemmap.slam.motion import compose

        cfg, graph = self.cfg, self.graph
        if f > 0:
            self.pose = compose(self.pose, self.pre.deltas[f - 1])
        r, b, d = self.frames.frame(f)
        tf = float(self.frames.times[f])
        use = r <= cfg.max_range
        if not use.all():
            r, b, d = r[use], b[use], d[use]
        if r.size == 0:
            self._end_frame(f, tf)
            return
        off = self.off
        echo = observation_to_world(self.pose, r, b, off)
        order = np.argsort(r)
        match = np.full(r.size, -1, dtype=np.int64)
        txy = graph.positions()
        active = self._active(tf)
        if active.size:
            sp = observation_to_world(self.pose, [0.0], [0.0], off)[0]
            reach = float(r.max()) + cfg.search_radius + 5.0
            loc = active[np.hypot(txy[active, 0] - sp[0], txy[active, 1] - sp[1]) <= reach]
            if loc.size:
                m_loc = match_tree_groups(
                    echo,
                    txy[loc],
                    group_size=cfg.group_size,
                    dist_tol=cfg.dist_tol,
                    search_radius=cfg.search_radius,
                    min_support=cfg.min_support,
                    echo_order=order,
                )
                match = np.where(m_loc >= 0, loc[np.clip(m_loc, 0, None)], -1)
            mm = np.flatnonzero(match >= 0)
            if mm.size >= cfg.min_matches:
                fit = pose_from_matches(echo[mm], txy[match[mm]], method=cfg.pose_method)
                if fit:
                    self.pose = fit.apply_pose(self.pose)
                    echo = observation_to_world(self.pose, r, b, off)
                    self.n_corrected += 1
        # classify echoes as old or new trees; accumulate
        ids = np.empty(r.size, dtype=np.int64)
        w_d = 1.0 / np.maximum(r, 0.5) ** 2
        loop = False
        taken = {int(j) for j in match if j >= 0}
        ax = txy[active] if active.size else np.zeros((0, 2))
        for k in order:
            j = int(match[k])
            if j < 0 and ax.shape[0]:
                dd = np.hypot(ax[:, 0] - echo[k, 0], ax[:, 1] - echo[k, 1])
                jj = int(np.argmin(dd))
                gate_k = max(cfg.new_tree_gate, cfg.new_tree_gate_per_m * float(r[k]))
                if dd[jj] <= gate_k and int(active[jj]) not in taken:
                    j = int(active[jj])
                    taken.add(j)
            if j >= 0:
                if tf - graph.last_time[j] > cfg.loop_gap_s:
                    loop = True
                graph.update_tree(j, echo[k], float(d[k]), float(w_d[k]), tf)
            else:
                j = graph.add_tree(echo[k], float(d[k]), float(w_d[k]), tf)
            ids[k] = j
        p0 = int(self.frames.ptr[f])
        self.det_tree[p0 : p0 + use.size][use] = ids
        if cfg.relaxation == "tree_graph":
            self._tree_graph_step(echo, ids, loop, tf)
        self._end_frame(f, tf)

    def _active(self, tf: float) -> IntArray:
        g = self.graph
        if not len(g):
            return np.zeros(0, dtype=np.int64)
        if not self.windowed:
            return np.flatnonzero(g.alive)
        return np.flatnonzero(g.alive & (tf - g.last_time <= self.cfg.loop_gap_s))

    def _tree_graph_step(self, echo: FloatArray, ids: IntArray, loop: bool, tf: float) -> None:
        """The older behaviour: record in-scan edges; relax the tree graph on a re-match."""
        cfg, graph = self.cfg, self.graph
        g = int(cfg.group_size) - 1
        if ids.size >= 2:
            nidx, ndist = _neighbours(echo, min(g, ids.size - 1))
            for a in range(ids.size):
                for c in range(nidx.shape[1]):
                    if nidx[a, c] >= 0:
                        graph.add_edge(int(ids[a]), int(ids[nidx[a, c]]), float(ndist[a, c]))
        if loop and tf - self.last_relax >= cfg.relax_cooldown_s:
            self.last_relax = tf
            self.n_loops += 1
            ed, ln, wt = graph.edge_arrays()
            relaxed = relax_tree_graph(
                graph.positions(), ed, ln, wt, iterations=cfg.relax_iterations
            )
            graph.set_positions(relaxed)

    def _end_frame(self, f: int, tf: float) -> None:
        self.poses[f] = self.pose
        if f > 0:
            last = self.poses[self.keyframes[-1]]
            if (
                math.hypot(self.pose[0] - last[0], self.pose[1] - last[1]) >= self.cfg.keyframe_dist
                or abs(math.remainder(self.pose[2] - last[2], 2 * math.pi)) >= 0.1
            ):
                self.keyframes.append(f)
        if self.windowed and tf - self.last_loop_try >= self.cfg.loop_every_s:
            self.last_loop_try = tf
            self._try_loop(f, tf)

    # ---- loop closure ----------------------------------------------------------------------

    def _try_loop(self, f: int, tf: float) -> None:
        from stemmap.slam.base import observation_to_world

        cfg, g = self.cfg, self.graph
        n = len(g)
        if n < 2 * cfg.loop_min_matches:
            return
        alive, last, first = g.alive, g.last_time, g.first_time
        xy = g.positions()
        sp = observation_to_world(self.pose, [0.0], [0.0], self.off)[0]
        recent = np.flatnonzero(
            alive
            & (first >= tf - cfg.loop_window_s)
            & (g.count >= 2)
            & (tf - last <= cfg.loop_gap_s)
        )
        if recent.size < cfg.loop_min_matches:
            return
        reach = float(np.max(np.hypot(*(xy[recent] - sp).T))) + cfg.loop_search_radius
        old = np.flatnonzero(alive & (tf - last > cfg.loop_gap_s))
        old = old[np.hypot(*(xy[old] - sp).T) <= reach]
        if old.size < cfg.loop_min_matches:
            return
        lm = find_loop_closure(
            xy[recent],
            xy[old],
            group_size=cfg.group_size,
            dist_tol=cfg.dist_tol,
            search_radius=cfg.loop_search_radius,
            min_support=cfg.loop_min_support,
            min_matches=cfg.loop_min_matches,
            order_from=sp,
        )
        if not lm:
            return
        src, dst = recent[lm.recent], old[lm.old]
        # the older frame: where the revisited trees were last seen (median time)
        t_old = float(np.median(last[dst]))
        j = int(np.clip(np.searchsorted(self.frames.times, t_old), 0, f))
        self.loops.append(
            LoopClosure(j, f, loop_constraint(self.poses[j], self.poses[f], lm.fit), cfg.loop_sigmas)
        )
        if self.keyframes[-1] != f:
            self.keyframes.append(f)
        remap = np.arange(n)
        for s_, d_ in zip(src.tolist(), dst.tolist(), strict=True):
            g.merge(s_, d_)
            remap[s_] = d_
        self.n_loop_merged += src.size
        k_end = int(self.frames.ptr[f + 1])
        seen = self.det_tree[:k_end]
        self.det_tree[:k_end] = np.where(seen >= 0, remap[np.clip(seen, 0, None)], -1)
        self._relax(f)

    def _relax(self, f: int) -> None:
        if not self.loops:
            return
        self.n_relax += 1
        kf = np.asarray(self.keyframes, dtype=np.int64)
        kf = kf[kf <= f]
        self.poses[: f + 1] = relax_trajectory(
            self.poses[: f + 1], kf, self.loops, max_iterations=self.cfg.relax_iterations
        )
        self.pose = self.poses[f].copy()
        k_end = int(self.frames.ptr[f + 1])
        fr = self.frames
        xy, cnt = remap_trees(
            self.poses[: f + 1],
            self.det_frame[:k_end],
            fr.ranges[:k_end],
            fr.bearings[:k_end],
            self.det_tree[:k_end],
            len(self.graph),
            self.off,
        )
        ok = self.graph.alive & (cnt > 0)
        pos = self.graph.positions()
        pos[ok] = xy[ok]
        self.graph.set_positions(pos)
        if self.cfg.merge_dist > 0:
            self._merge_close(f)

    def _merge_close(self, f: int) -> None:
        """After a relaxation the map is consistent again: trees closer than ``merge_dist`` with
        compatible diameters (or overlapping trunks) are one tree (iSAM2's rule) -- the copies a
        drifted revisit created before its loop was recognised."""
        from stemmap.slam.graph import _merge_duplicates

        g = self.graph
        idx = np.flatnonzero(g.alive)
        if idx.size < 2:
            return
        xy = g.positions()[idx]
        dia = np.nan_to_num(g.diameters()[idx], nan=0.0)
        cnt = g.count[idx].astype(np.float64)
        rep = idx[_merge_duplicates(xy, dia, cnt, self.cfg.merge_dist, self.cfg.merge_ddiam)]
        moved = np.flatnonzero(rep != idx)
        if moved.size == 0:
            return
        n = len(g)
        remap = np.arange(n)
        pos = g.positions()
        for k in moved.tolist():
            s_, d_ = int(idx[k]), int(rep[k])
            cs, cd = float(g.count[s_]), float(g.count[d_])
            pos[d_] = (cs * pos[s_] + cd * pos[d_]) / max(cs + cd, 1.0)
            g.merge(s_, d_)
            remap[s_] = d_
        g.set_positions(pos)
        self.n_close_merged += moved.size
        k_end = int(self.frames.ptr[f + 1])
        seen = self.det_tree[:k_end]
        self.det_tree[:k_end] = np.where(seen >= 0, remap[np.clip(seen, 0, None)], -1)

    def finish(self) -> None:
        """Nothing pending: every loop closure relaxes at once (the last state is final)."""
        self.pending = False
