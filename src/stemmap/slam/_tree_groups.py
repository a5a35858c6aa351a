"""Forestrix primitives (Öhman et al. 2007 §2.1-2.2): tree-group matching, pose from matched
pairs, the hybrid tree graph and its spring relaxation. The back-end is
:class:`stemmap.slam.forestrix.ForestrixSlam`; these names are re-exported there.

References
----------
.. [Ohman2007] M. Öhman, M. Miettinen, K. Kannas, J. Jutila, A. Visala, P. Forsman, "Tree
   Measurement and Simultaneous Localization and Mapping System for Forest Harvesters",
   FSR 2007, §2.1-2.2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, wrap_angle

__all__ = [
    "PoseFit",
    "TreeGraph",
    "match_tree_groups",
    "pose_fit_jacobians",
    "pose_from_matches",
    "relax_tree_graph",
]

IntArray = NDArray[np.int64]


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


def pose_fit_jacobians(
    echo_xy: ArrayLike,
    tree_xy: ArrayLike,
    pose: ArrayLike,
    *,
    method: Literal["ohman2007", "procrustes"] = "ohman2007",
    fit: PoseFit | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Jacobians of the corrected pose ``pose_from_matches(echo_xy, tree_xy).apply_pose(pose)``.

    The linear form of Forestrix's localisation for its error analysis (issue 14,
    :mod:`stemmap.slam._tree_map_errors`): how the corrected pose moves with the predicted
    ``pose``, each echo and each tree.

    Parameters
    ----------
    echo_xy, tree_xy : ndarray (M, 2), m -- matched pairs, row by row
    pose : ndarray (3,) -- the predicted vehicle pose the echoes were projected with
    method : {"ohman2007", "procrustes"} -- as in :func:`pose_from_matches`
    fit : PoseFit, optional -- that fit of these pairs, if already computed

    Returns
    -------
    J_pose : ndarray (3, 3)
    J_echo, J_tree : ndarray (3, 2M)
        Columns ``2i, 2i + 1``: echo / tree ``i``'s (x, y).

    Raises
    ------
    InputError
        When :func:`pose_from_matches` cannot fit the pairs.

    Notes
    -----
    With ``c_e``, ``c_t`` the centres and ``dθ`` the fitted rotation, the corrected pose is
    ``p'_xy = R(dθ) (p_xy - c_e) + c_t``, ``θ' = θ + dθ``: ``∂p'/∂p = diag(R(dθ), 1)``; an
    echo moves ``p'`` by ``-R(dθ)/M`` through ``c_e``, a tree by ``I/M`` through ``c_t``, and
    both through ``dθ`` about ``c_t`` (``J (p'_xy - c_t) ∂dθ``, ``J`` the 90° rotation).
    Procrustes: ``dθ = atan2(C, D)``, ``C = Σ q_e × q_t``, ``D = Σ q_e · q_t`` (centred
    points); mean angle: ``dθ = atan2(mean sin α_i, mean cos α_i)``, ``α_i = ∠q_t,i - ∠q_e,i``.
    Centring adds ``-mean_i ∂dθ/∂q_i`` to each point's derivative (zero for Procrustes).
    Since the fit is rigid-equivariant, ``J_pose + J_echo ∂echo/∂pose = 0``.
    """
    e = np.asarray(echo_xy, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(tree_xy, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(pose, dtype=np.float64).reshape(3)
    if fit is None:
        fit = pose_from_matches(e, t, method=method)
    if not fit:
        raise InputError(f"pose_fit_jacobians: {fit.reason}.")
    m = e.shape[0]
    qe, qt = e - e.mean(axis=0), t - t.mean(axis=0)
    perp_e = np.column_stack((-qe[:, 1], qe[:, 0]))  # J q
    perp_t = np.column_stack((-qt[:, 1], qt[:, 0]))
    if method == "procrustes":
        C = float(np.sum(qe[:, 0] * qt[:, 1] - qe[:, 1] * qt[:, 0]))
        D = float(np.sum(qe * qt))
        n2 = C * C + D * D
        g_t = (D * perp_e - C * qe) / n2  # ∂dθ/∂q_t,i
        g_e = (-D * perp_t - C * qt) / n2  # ∂dθ/∂q_e,i
    else:
        ne2, nt2 = np.sum(qe * qe, axis=1), np.sum(qt * qt, axis=1)
        good = (ne2 > 1e-18) & (nt2 > 1e-18)
        ang = np.arctan2(qt[:, 1], qt[:, 0]) - np.arctan2(qe[:, 1], qe[:, 0])
        n = int(good.sum())
        S, Co = np.mean(np.sin(ang[good])), np.mean(np.cos(ang[good]))
        w = np.where(good, (Co * np.cos(ang) + S * np.sin(ang)) / (n * (S * S + Co * Co)), 0.0)
        g_t = (w / np.where(good, nt2, 1.0))[:, None] * perp_t
        g_e = -(w / np.where(good, ne2, 1.0))[:, None] * perp_e
    g_t = g_t - g_t.mean(axis=0)
    g_e = g_e - g_e.mean(axis=0)
    c, s = math.cos(fit.dtheta), math.sin(fit.dtheta)
    rot = np.array([[c, -s], [s, c]])
    u = rot @ (p[:2] - np.asarray(fit.centre))
    v = np.array([-u[1], u[0]])  # ∂p'_xy/∂dθ
    J_pose = np.eye(3)
    J_pose[:2, :2] = rot
    J_echo = np.zeros((3, 2 * m))
    J_tree = np.zeros((3, 2 * m))
    J_echo[:2] = np.outer(v, g_e.reshape(-1)) - np.tile(rot, m) / m
    J_tree[:2] = np.outer(v, g_t.reshape(-1)) + np.tile(np.eye(2), m) / m
    J_echo[2], J_tree[2] = g_e.reshape(-1), g_t.reshape(-1)
    return J_pose, J_echo, J_tree


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
