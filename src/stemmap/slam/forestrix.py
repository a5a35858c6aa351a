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
from stemmap.types import FloatArray, StemMap, Tree, wrap_angle

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem, SlamResult

__all__ = [
    "PRESETS",
    "ForestrixSlam",
    "PoseFit",
    "TreeGraph",
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
        for name in ("_xy", "_count", "_dia_wsum", "_dia_w", "_first", "_last"):
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
        self._n += 1
        return j

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


@dataclass
class ForestrixSlam:
    """Forestrix SLAM back-end (Öhman et al. 2007 §2).

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
        Default ``"procrustes"`` (ours; see :func:`pose_from_matches`): on the full Victoria Park
        run 8.1 m ATE against 24.6 m for the paper's mean angle, on the simulated loop 0.36 m
        against 0.66 m (docs/algorithms/slam-frontends.md). The presets select the paper's.
    new_tree_gate : float, m
        After the pose correction, an unmatched echo this close to a map tree is that tree;
        otherwise it is a new tree.
    new_tree_gate_per_m : float, m per m of range
        Ours: widen that gate with range, ``max(new_tree_gate, new_tree_gate_per_m * r)``
        (a bearing error moves far echoes more; 0.02 m/m ~ 1.1°). 0 = the fixed gate. First
        600 s of Victoria Park: duplicate pairs 38 -> 26, simulated loop unchanged.
    loop_gap_s : float, s
        Re-matching a tree last seen longer ago than this closes a loop and triggers relaxation.
    relax_iterations : int
    relax_cooldown_s : float, s
        Minimum time between two relaxations (a returning vehicle re-sees many old trees).
    min_observations : int
        Trees seen fewer times are left out of the output map.
    merge_dist : float, m
        Ours (issue 18): after the run, output trees closer than this whose diameters differ by
        less than ``merge_ddiam`` (or whose trunk circles overlap) are one tree -- iSAM2's rule
        (:func:`stemmap.slam.graph._merge_duplicates`); members are averaged by their
        observation counts. Victoria Park: 98 duplicate pairs < 1 m among 1,084 trees
        (9 %). 0 disables.
    merge_ddiam : float, m
        3 sqrt(2) x 0.1 m, iSAM2's diameter tolerance.
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
    relax_iterations: int = 200
    relax_cooldown_s: float = 10.0
    min_observations: int = 3
    merge_dist: float = 1.0
    merge_ddiam: float = 0.42
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
        if not (self.dist_tol > 0 and self.search_radius > 0 and self.new_tree_gate > 0):
            raise ConfigError("ForestrixSlam: dist_tol, search_radius, new_tree_gate must be > 0.")
        if not (self.merge_dist >= 0 and self.merge_ddiam >= 0):
            raise ConfigError(
                f"ForestrixSlam: merge_dist and merge_ddiam must be >= 0 m, got "
                f"{self.merge_dist}, {self.merge_ddiam}."
            )

    def run(
        self, problem: SlamProblem, *, progress: Callable[[int, int], None] | None = None
    ) -> SlamResult:
        """Run Forestrix over ``problem``; see the module docstring."""
        from stemmap.slam.base import SlamResult, frame_trajectory, observation_to_world
        from stemmap.slam.motion import compose, preintegrate

        t_start = _time.perf_counter()
        frames = problem.frames
        nf = len(frames)
        off = problem.sensor_offset
        pre = preintegrate(
            problem.motion,
            problem.controls,
            frames.times,
            np.asarray(problem.initial_pose),
            with_covariance=False,
        )
        pose = np.asarray(problem.initial_pose, dtype=np.float64).copy()
        poses = np.empty((nf, 3))
        graph = TreeGraph()
        n_corrected = 0
        n_loops = 0
        last_relax = -math.inf
        g = int(self.group_size) - 1
        for f in range(nf):
            if f > 0:
                pose = compose(pose, pre.deltas[f - 1])
            r, b, d = frames.frame(f)
            tf = float(frames.times[f])
            if r.size == 0:
                poses[f] = pose
                continue
            echo = observation_to_world(pose, r, b, off)
            order = np.argsort(r)
            match = np.full(r.size, -1, dtype=np.int64)
            local = np.zeros(0, dtype=np.int64)
            if len(graph):
                txy = graph.positions()
                sp = observation_to_world(pose, [0.0], [0.0], off)[0]
                reach = float(r.max()) + self.search_radius + 5.0
                local = np.flatnonzero(np.hypot(txy[:, 0] - sp[0], txy[:, 1] - sp[1]) <= reach)
                if local.size:
                    m_loc = match_tree_groups(
                        echo,
                        txy[local],
                        group_size=self.group_size,
                        dist_tol=self.dist_tol,
                        search_radius=self.search_radius,
                        min_support=self.min_support,
                        echo_order=order,
                    )
                    match = np.where(m_loc >= 0, local[np.clip(m_loc, 0, None)], -1)
                mm = np.flatnonzero(match >= 0)
                if mm.size >= self.min_matches:
                    fit = pose_from_matches(echo[mm], txy[match[mm]], method=self.pose_method)
                    if fit:
                        pose = fit.apply_pose(pose)
                        echo = observation_to_world(pose, r, b, off)
                        n_corrected += 1
            # classify echoes as old or new trees; accumulate
            ids = np.empty(r.size, dtype=np.int64)
            txy = graph.positions()
            w_d = 1.0 / np.maximum(r, 0.5) ** 2
            loop = False
            taken = {int(j) for j in match if j >= 0}
            for k in order:
                j = int(match[k])
                if j < 0 and txy.shape[0]:
                    dd = np.hypot(txy[:, 0] - echo[k, 0], txy[:, 1] - echo[k, 1])
                    jj = int(np.argmin(dd))
                    gate_k = max(self.new_tree_gate, self.new_tree_gate_per_m * float(r[k]))
                    if dd[jj] <= gate_k and jj not in taken:
                        j = jj
                        taken.add(jj)
                if j >= 0:
                    if tf - graph.last_time[j] > self.loop_gap_s:
                        loop = True
                    graph.update_tree(j, echo[k], float(d[k]), float(w_d[k]), tf)
                else:
                    j = graph.add_tree(echo[k], float(d[k]), float(w_d[k]), tf)
                ids[k] = j
            # edges to in-scan neighbours (measured distances: pose-error free)
            if r.size >= 2:
                nidx, ndist = _neighbours(echo, min(g, r.size - 1))
                for a in range(r.size):
                    for c in range(nidx.shape[1]):
                        if nidx[a, c] >= 0:
                            graph.add_edge(int(ids[a]), int(ids[nidx[a, c]]), float(ndist[a, c]))
            if loop and tf - last_relax >= self.relax_cooldown_s:
                last_relax = tf
                n_loops += 1
                ed, ln, wt = graph.edge_arrays()
                relaxed = relax_tree_graph(
                    graph.positions(), ed, ln, wt, iterations=self.relax_iterations
                )
                graph.set_positions(relaxed)
            poses[f] = pose
            if progress is not None and (f % 200 == 0 or f == nf - 1):
                progress(f + 1, nf)

        keep = np.flatnonzero(graph.count >= self.min_observations)
        xy = graph.positions()[keep]
        dia = graph.diameters()[keep]
        cnt = graph.count[keep].astype(np.float64)
        t_first = np.asarray(graph.first_time, dtype=np.float64)[keep]
        t_last = np.asarray(graph.last_time, dtype=np.float64)[keep]
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
        trees = []
        for new_id in range(xy.shape[0]):
            trees.append(
                Tree(
                    id=new_id,
                    x=float(xy[new_id, 0]),
                    y=float(xy[new_id, 1]),
                    diameter=float(dia[new_id]),
                    n_obs=int(cnt[new_id]),
                    first_time=float(t_first[new_id]),
                    last_time=float(t_last[new_id]),
                )
            )
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "graph_nodes": len(graph),
            "graph_edges": len(graph.edges),
            "trees_mapped": len(trees),
            "trees_merged": n_merged,
            "frames_corrected": n_corrected,
            "loop_closures": n_loops,
            "runtime_s": float(_time.perf_counter() - t_start),
        }
        return SlamResult(frame_trajectory(frames.times, poses), StemMap(tuple(trees)), stats)
