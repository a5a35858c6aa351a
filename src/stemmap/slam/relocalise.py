"""Global relocalisation in a prior stem map by tree-group matching (after Öhman et al. 2007).

A new session starts somewhere in an area mapped before, its start pose unknown (or known only
roughly). :func:`relocalise` drives on with dead reckoning for growing windows of the run
(``window_s`` steps up to ``max_window_s``), builds a *local* tree map from the window's
detections, and matches it to the prior map:

1. **Local trees**: every detection placed with the dead-reckoned sensor pose (drift over
   ~30 s on Victoria Park is a few decimetres); detections within ``cluster_radius`` of each
   other are one tree (connected components), kept when seen in >= ``min_cluster`` scans.
2. **Hypotheses from pairs of trees** (Öhman 2007 §2.1: inter-tree distances are invariant to
   the unknown pose, so they are what is matched): every local pair ``(a, b)`` at a well
   conditioned distance (``pair_range``) is paired with every map pair ``(j, k)`` whose distance
   agrees within ``pair_tol``; each such correspondence fixes one SE(2) transform. With a
   start guess, transforms farther than ``search_radius`` / ``search_angle`` from it are
   dropped (``None``: global search).
3. **Scoring**: a hypothesis scores the number of local trees that land within ``inlier_dist``
   of a map tree (one k-d tree query for all hypotheses at once); the best is refined by the
   closed-form SE(2) fit (:func:`stemmap.eval.trajectory.align_se2`) over its inliers.
4. **Acceptance**: at least ``min_inliers`` inliers; at most ``max_conflict_frac`` of the
   local trees that land inside the mapped stand (a map tree within ``cover_dist``, by
   default the map's own median tree spacing, :func:`map_spacing`) may land
   off every map tree (negative evidence: the earlier session would have mapped a tree there;
   local trees beyond ``cover_dist`` are outside the map and say nothing -- a session that
   drives out of the mapped area sees few mapped trees but no contradiction); and no
   *different* hypothesis (more than 2 m or 5 deg away, itself not contradicted) with more
   than ``ambiguity_ratio`` times the best score -- a repetitive stand (an orchard row) must
   not relocalise on the wrong row. Hypotheses failing the conflict test are dropped before
   the best is chosen.
5. **Start pose**: the accepted transform is refitted to the detections of the first
   ``anchor_s`` seconds only (dead-reckoning error grows with the time since the start).

Mapping on the prior map (:func:`continue_session`, :class:`stemmap.slam.graph.Isam2Slam`):
its trees become landmarks held by priors on their earlier covariances, inflated
(:func:`inflate_prior`); :func:`prior_consistency` checks those covariances against what the
new session sees.

Öhman et al. match groups of a tree and its nearest neighbours with the pose predicted by
odometry (their matcher, :func:`stemmap.slam.forestrix.match_tree_groups`, assumes the
prediction is within ``search_radius`` of the truth, 2 m by default); a start that is off by
tens of metres needs the pose-free pair hypotheses above, which test the same invariant (the
inter-tree distances) over all candidate pairs. Decision documented in
docs/algorithms/slam.md "Maps reused across sessions".
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from stemmap.errors import ConfigError, InputError
from stemmap.slam.base import SlamProblem, sensor_poses
from stemmap.slam.motion import preintegrate
from stemmap.types import FloatArray, StemMap

__all__ = [
    "PriorConsistency",
    "RelocConfig",
    "Relocalisation",
    "continue_session",
    "inflate_prior",
    "local_trees",
    "map_spacing",
    "match_to_map",
    "prior_consistency",
    "prior_tree_factors",
    "relocalise",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RelocConfig:
    """Settings of :func:`relocalise` (see the module docs; defaults in docs/algorithms/slam.md).

    window_s, max_window_s : s, the local map grows by ``window_s`` until ``max_window_s``
    cluster_radius : m; min_cluster : scans per local tree
    pair_range : (m, m) local pair distances used for hypotheses; max_pairs : at most this many
    pair_tol : m, agreement of a local and a map inter-tree distance
    inlier_dist : m; min_inliers : local trees that must land on map trees
    ambiguity_ratio : a distinct second hypothesis must score below this fraction of the best
    cover_dist : m, a local tree landing off every map tree (> ``inlier_dist``) but within this
        of one is a conflict (inside the mapped stand); ``None`` (default): the map's own
        spacing, the median nearest-neighbour distance of the map trees the search can reach
        (:func:`map_spacing`), at least ``2 inlier_dist``; max_conflict_frac : at most this
        fraction of the local trees inside the mapped stand may conflict
    anchor_s : s, the start pose is refitted to the detections of this first part of the run
    search_radius, search_angle : m, rad around the start guess (None: global)
    """

    window_s: float = 5.0
    max_window_s: float = 30.0
    cluster_radius: float = 0.6
    min_cluster: int = 3
    pair_range: tuple[float, float] = (6.0, 40.0)
    max_pairs: int = 60
    pair_tol: float = 0.4
    inlier_dist: float = 0.8
    min_inliers: int = 5
    ambiguity_ratio: float = 0.7
    cover_dist: float | None = None
    anchor_s: float = 0.5
    max_conflict_frac: float = 0.25
    search_radius: float | None = 30.0
    search_angle: float | None = math.radians(45.0)

    def __post_init__(self) -> None:
        for name in (
            "window_s", "max_window_s", "cluster_radius", "pair_tol", "inlier_dist",
            "cover_dist", "anchor_s",
        ):  # fmt: skip
            v = getattr(self, name)
            if name == "cover_dist" and v is None:  # from the map's spacing
                continue
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"RelocConfig.{name} must be a positive number, got {v}.")
        if self.min_inliers < 3 or self.min_cluster < 1 or self.max_pairs < 1:
            raise ConfigError("RelocConfig: min_inliers >= 3, min_cluster >= 1, max_pairs >= 1.")
        if not 0 < self.ambiguity_ratio < 1:
            raise ConfigError(
                f"RelocConfig.ambiguity_ratio must be in (0, 1), got {self.ambiguity_ratio}."
            )
        cover_ok = self.cover_dist is None or self.cover_dist > self.inlier_dist
        if not 0 <= self.max_conflict_frac < 1 or not cover_ok:
            raise ConfigError(
                "RelocConfig: max_conflict_frac in [0, 1) and cover_dist > inlier_dist."
            )


@dataclass(frozen=True)
class Relocalisation:
    """Result of :func:`relocalise`.

    ok : whether a pose was accepted; pose : (x, y, theta) of the vehicle at the run's first
    frame in the map frame (the start guess when not ok); time_s : seconds of the run used
    (the window that succeeded); n_inliers, n_local : inlier and local tree counts;
    second_ratio : score of the best distinct other hypothesis / best; reason : why not ok
    """

    ok: bool
    pose: tuple[float, float, float]
    time_s: float
    n_inliers: int
    n_local: int
    second_ratio: float
    reason: str = ""


def local_trees(problem: SlamProblem, t_end: float, cfg: RelocConfig) -> tuple[FloatArray, int]:
    """(m, 2) local trees (dead-reckoned frame of ``problem.initial_pose``) seen up to ``t_end``,
    and the number of scans used. Step 1 of the module docs."""
    lm = _local_map(problem, t_end, cfg)
    return lm.trees, lm.n_scans


@dataclass(frozen=True)
class _LocalMap:
    """Local trees and the detections they were made of (dead-reckoned frame): ``trees`` (m, 2)
    most-seen first; ``det_xy`` (k, 2), ``det_t`` (k,) s since the first scan, ``det_tree``
    (k,) index into ``trees`` (-1: a cluster seen in too few scans)."""

    trees: FloatArray
    n_scans: int
    det_xy: FloatArray
    det_t: FloatArray
    det_tree: np.ndarray


def _local_map(problem: SlamProblem, t_end: float, cfg: RelocConfig) -> _LocalMap:
    fr = problem.frames
    nf = int(np.searchsorted(fr.times, t_end, side="right"))
    empty = _LocalMap(np.zeros((0, 2)), nf, np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
    if nf < 2:
        return empty
    pre = preintegrate(
        problem.motion, problem.controls, fr.times[:nf], problem.initial_pose,
        with_covariance=False,
    )  # fmt: skip
    sp = sensor_poses(pre.poses, problem.sensor_offset)
    k = int(fr.ptr[nf])
    fi = fr.frame_index[:k]
    r, b = fr.ranges[:k], fr.bearings[:k]
    keep = r <= min(problem.max_range, 40.0)
    fi, r, b = fi[keep], r[keep], b[keep]
    ang = sp[fi, 2] + b
    xy = np.column_stack((sp[fi, 0] + r * np.cos(ang), sp[fi, 1] + r * np.sin(ang)))
    if xy.shape[0] == 0:
        return empty
    pairs = cKDTree(xy).query_pairs(cfg.cluster_radius, output_type="ndarray")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = xy.shape[0]
    g = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_c, lab = connected_components(g, directed=False)
    # scans per cluster (a tree seen in many scans, not many detections of one scan)
    scans = np.zeros(n_c, dtype=np.int64)
    u = np.unique(np.column_stack((lab, fi)), axis=0)
    np.add.at(scans, u[:, 0], 1)
    cnt = np.bincount(lab, minlength=n_c)
    cx = np.bincount(lab, weights=xy[:, 0], minlength=n_c) / np.maximum(cnt, 1)
    cy = np.bincount(lab, weights=xy[:, 1], minlength=n_c) / np.maximum(cnt, 1)
    ok = np.flatnonzero(scans >= cfg.min_cluster)
    order = ok[np.argsort(-scans[ok], kind="stable")]  # most-seen first
    slot = np.full(n_c, -1, dtype=np.int64)
    slot[order] = np.arange(order.size)
    return _LocalMap(
        np.column_stack((cx[order], cy[order])), nf, xy, fr.times[fi] - fr.times[0], slot[lab]
    )


def _transforms(la: FloatArray, lb: FloatArray, ma: FloatArray, mb: FloatArray) -> FloatArray:
    """(H, 3) SE(2) ``(tx, ty, theta)`` taking local points la -> ma and (approx.) lb -> mb."""
    th = np.arctan2(mb[:, 1] - ma[:, 1], mb[:, 0] - ma[:, 0]) - np.arctan2(
        lb[:, 1] - la[:, 1], lb[:, 0] - la[:, 0]
    )
    # anchor at the pair's midpoint (the distance mismatch splits evenly)
    lm, mm = 0.5 * (la + lb), 0.5 * (ma + mb)
    c, s = np.cos(th), np.sin(th)
    tx = mm[:, 0] - (c * lm[:, 0] - s * lm[:, 1])
    ty = mm[:, 1] - (s * lm[:, 0] + c * lm[:, 1])
    return np.column_stack((tx, ty, np.angle(np.exp(1j * th))))


def _apply(T: FloatArray, xy: FloatArray) -> FloatArray:
    """(H, m, 2): local points ``xy`` (m, 2) under each transform of ``T`` (H, 3)."""
    c, s = np.cos(T[:, 2])[:, None], np.sin(T[:, 2])[:, None]
    return np.stack(
        (T[:, 0:1] + c * xy[None, :, 0] - s * xy[None, :, 1],
         T[:, 1:2] + s * xy[None, :, 0] + c * xy[None, :, 1]), axis=-1,
    )  # fmt: skip


def map_spacing(map_xy: FloatArray, inlier_dist: float = 0.0) -> float:
    """Median nearest-neighbour distance (m) of the trees ``map_xy`` (n, 2), at least
    ``2 inlier_dist``: the default ``RelocConfig.cover_dist``.

    A point farther than this from every mapped tree lies in a gap wider than half the
    stand's; nearer, the earlier session would most likely have mapped a tree there. The floor
    keeps a band between an inlier (<= ``inlier_dist``) and the stand's spacing in a very dense
    map (or one of fewer than 2 trees, which has no spacing).
    """
    floor = 2.0 * inlier_dist
    if map_xy.shape[0] < 2:
        return floor if floor > 0 else math.inf
    d, _ = cKDTree(map_xy).query(map_xy, k=2)
    return max(float(np.median(d[:, 1])), floor)


def match_to_map(
    local_xy: FloatArray,
    map_xy: FloatArray,
    cfg: RelocConfig,
    guess: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[FloatArray | None, int, float, str]:
    """Best SE(2) ``(tx, ty, theta)`` taking local trees onto map trees (steps 2-4 of the module
    docs), its inlier count, the distinct-second-best ratio, and a reason when rejected.

    ``guess`` is the transform expected a priori, i.e. the start pose in the map (the local
    frame's origin is the start); hypotheses whose start position / heading differ from it by
    more than ``search_radius`` / ``search_angle`` are dropped.
    """
    m = local_xy.shape[0]
    if m < cfg.min_inliers:
        return None, 0, 0.0, f"only {m} local trees (need {cfg.min_inliers})"
    if map_xy.shape[0] < cfg.min_inliers:
        return None, 0, 0.0, f"the prior map has only {map_xy.shape[0]} trees"
    lo, hi = cfg.pair_range
    cen = local_xy.mean(axis=0)
    gth = guess[2]
    g_xy = np.array([guess[0], guess[1]])
    map_use = map_xy
    if cfg.search_radius is not None:  # map trees any admissible start could see
        ext = float(np.hypot(*local_xy.T).max())
        d_c = np.hypot(*(map_xy - g_xy).T)
        map_use = map_xy[d_c <= cfg.search_radius + ext + cfg.inlier_dist]
        if map_use.shape[0] < cfg.min_inliers:
            return None, 0, 0.0, "no mapped trees near the start guess"
    # local pairs among the most-seen trees, spread over distances
    top = local_xy[: min(m, 25)]
    ia, ib = np.triu_indices(top.shape[0], 1)
    dl = np.hypot(*(top[ia] - top[ib]).T)
    sel = np.flatnonzero((dl >= lo) & (dl <= hi))
    if sel.size == 0:
        return None, 0, 0.0, "no local tree pair in the usable distance range"
    sel = sel[np.linspace(0, sel.size - 1, min(sel.size, cfg.max_pairs)).astype(np.int64)]
    # map pairs (both orders) sorted by distance
    mt = cKDTree(map_use)
    mp = mt.query_pairs(hi + cfg.pair_tol, output_type="ndarray")
    if mp.shape[0] == 0:
        return None, 0, 0.0, "no map tree pairs"
    mp = np.concatenate((mp, mp[:, ::-1]))
    dm = np.hypot(*(map_use[mp[:, 0]] - map_use[mp[:, 1]]).T)
    o = np.argsort(dm)
    mp, dm = mp[o], dm[o]
    hyps = []
    for q in sel.tolist():
        a, b = int(ia[q]), int(ib[q])
        j0 = np.searchsorted(dm, dl[q] - cfg.pair_tol)
        j1 = np.searchsorted(dm, dl[q] + cfg.pair_tol, side="right")
        if j1 <= j0:
            continue
        cand = mp[j0:j1]
        k = cand.shape[0]
        la, lb = np.repeat(top[a : a + 1], k, 0), np.repeat(top[b : b + 1], k, 0)
        hyps.append(_transforms(la, lb, map_use[cand[:, 0]], map_use[cand[:, 1]]))
    if not hyps:
        return None, 0, 0.0, "no map pair matches a local inter-tree distance"
    T = np.concatenate(hyps)
    if cfg.search_angle is not None:
        T = T[np.abs(np.angle(np.exp(1j * (T[:, 2] - gth)))) <= cfg.search_angle]
    if cfg.search_radius is not None and T.shape[0]:
        T = T[np.hypot(T[:, 0] - g_xy[0], T[:, 1] - g_xy[1]) <= cfg.search_radius]
    if T.shape[0] == 0:
        return None, 0, 0.0, "no hypothesis within the search bounds of the start guess"
    # inliers (within inlier_dist of a map tree) and conflicts (no map tree within inlier_dist,
    # but one within cover_dist: inside the mapped stand where the earlier session would have
    # mapped the tree) of every hypothesis, one bounded k-d tree query
    cover = cfg.cover_dist if cfg.cover_dist is not None else map_spacing(map_use, cfg.inlier_dist)
    full_t = cKDTree(map_xy)
    score = np.zeros(T.shape[0], dtype=np.int64)
    conf = np.zeros(T.shape[0], dtype=np.int64)
    for h0 in range(0, T.shape[0], 4096):  # bounded memory
        pts = _apply(T[h0 : h0 + 4096], local_xy)
        d, _ = full_t.query(pts.reshape(-1, 2), distance_upper_bound=cover)
        d = d.reshape(pts.shape[:2])
        score[h0 : h0 + 4096] = (d <= cfg.inlier_dist).sum(axis=1)
        conf[h0 : h0 + 4096] = ((d > cfg.inlier_dist) & np.isfinite(d)).sum(axis=1)
    valid = conf <= cfg.max_conflict_frac * (score + conf)
    if not valid.any():
        return None, int(score.max()), 0.0, "every hypothesis is contradicted by the map"
    best = int(np.argmax(np.where(valid, score, -1)))
    # refine: closed-form fit over the inliers, twice (inliers may change)
    from stemmap.eval.trajectory import align_se2

    Tb = T[best]
    n_in = int(score[best])
    for _ in range(2):
        p = _apply(Tb[None], local_xy)[0]
        d, j = full_t.query(p, distance_upper_bound=cfg.inlier_dist)
        inl = np.isfinite(d)
        if inl.sum() < 3:
            break
        al = align_se2(local_xy[inl], map_xy[j[inl]])
        Tb = np.array([al.t[0], al.t[1], al.theta])
        n_in = int(inl.sum())
    d, _ = full_t.query(_apply(Tb[None], local_xy)[0], distance_upper_bound=cover)
    n_conf = int(((d > cfg.inlier_dist) & np.isfinite(d)).sum())
    # ambiguity: best score among hypotheses distinct from the best (and not contradicted)
    c_b = _apply(Tb[None], cen[None])[0, 0]
    c_all = _apply(T, cen[None])[:, 0]
    distinct = (np.hypot(*(c_all - c_b).T) > 2.0) | (
        np.abs(np.angle(np.exp(1j * (T[:, 2] - Tb[2])))) > math.radians(5.0)
    )
    second = int(score[distinct & valid].max(initial=0))
    ratio = second / max(n_in, 1)
    if n_in < cfg.min_inliers:
        return None, n_in, ratio, f"{n_in} inliers (need {cfg.min_inliers})"
    if n_conf > cfg.max_conflict_frac * (n_in + n_conf):
        return None, n_in, ratio, f"{n_conf} local trees land in the mapped stand off every tree"
    if ratio >= cfg.ambiguity_ratio:
        return None, n_in, ratio, f"ambiguous: a distinct hypothesis scores {second} vs {n_in}"
    return Tb, n_in, ratio, ""


def _refine_start(T: FloatArray, lm: _LocalMap, map_xy: FloatArray, cfg: RelocConfig) -> FloatArray:
    """The accepted transform refitted to the detections of the first ``cfg.anchor_s`` seconds.

    The local trees are placed by dead reckoning, whose error grows with the time since the
    start (in the sharp turn at the start of the 400-s session of Victoria Park the
    uncalibrated odometry under-turns by ~3 deg/s, and the fit over a 5-s window put the start
    heading 6.6 deg off with 19 inliers). The start pose is what is wanted, so it is refitted
    (:func:`stemmap.eval.trajectory.align_se2`) to the early detections of the inlier trees,
    each against its matched map tree; kept unchanged when they cover fewer than 3 trees.
    """
    from stemmap.eval.trajectory import align_se2

    d, j = cKDTree(map_xy).query(_apply(T[None], lm.trees)[0], distance_upper_bound=cfg.inlier_dist)
    tree_ok = np.isfinite(d)
    sel = (lm.det_t <= cfg.anchor_s) & (lm.det_tree >= 0)
    sel[sel] = tree_ok[lm.det_tree[sel]]
    if np.unique(lm.det_tree[sel]).size < 3:
        return T
    al = align_se2(lm.det_xy[sel], map_xy[j[lm.det_tree[sel]]])
    return np.array([al.t[0], al.t[1], al.theta])


def relocalise(
    problem: SlamProblem,
    prior_map: StemMap,
    cfg: RelocConfig | None = None,
    guess: tuple[float, float, float] | None = None,
) -> Relocalisation:
    """Find the run's start pose in ``prior_map`` (module docs); ``guess`` is the start pose
    expected in the map frame (default ``problem.initial_pose``), searched around within
    ``cfg.search_radius`` / ``cfg.search_angle``."""
    cfg = cfg or RelocConfig()
    if len(prior_map) == 0:
        raise InputError("relocalise: the prior map has no trees.")
    g = problem.initial_pose if guess is None else guess
    # local frame = the run dead-reckoned from the origin; the guess maps it into the map
    base = dataclasses.replace(problem, initial_pose=(0.0, 0.0, 0.0))
    t0 = float(problem.frames.times[0])
    t_last = float(problem.frames.times[-1])
    map_xy = prior_map.xy
    res = Relocalisation(False, tuple(g), 0.0, 0, 0, 0.0, "no window tried")  # type: ignore[arg-type]
    w = cfg.window_s
    while True:
        t_end = min(t0 + w, t_last)
        lm = _local_map(base, t_end, cfg)
        loc = lm.trees
        T, n_in, ratio, why = match_to_map(loc, map_xy, cfg, (g[0], g[1], g[2]))
        if T is not None:
            T = _refine_start(T, lm, map_xy, cfg)
            pose = (float(T[0]), float(T[1]), float(np.angle(np.exp(1j * T[2]))))
            log.info(
                "relocalised after %.1f s: pose (%.2f, %.2f, %.1f deg), %d of %d local trees",
                t_end - t0, pose[0], pose[1], math.degrees(pose[2]), n_in, loc.shape[0],
            )  # fmt: skip
            return Relocalisation(True, pose, t_end - t0, n_in, loc.shape[0], ratio)
        res = Relocalisation(False, tuple(g), t_end - t0, n_in, loc.shape[0], ratio, why)  # type: ignore[arg-type]
        if w >= cfg.max_window_s or t_end >= t_last:
            break
        w = min(w + cfg.window_s, cfg.max_window_s)
    log.warning("relocalisation failed after %.1f s: %s", res.time_s, res.reason)
    return res


def prior_tree_factors(
    prior_map: StemMap, key: Any, min_obs: int, default_sigma: float = 0.1, kernel: Any = None
) -> list[tuple[FloatArray, float, int, Any]]:
    """``(xy, diameter, n_obs, PriorFactorPoint2)`` per tree of a prior map, landmark keys
    ``key(0..n-1)`` in map order.

    The prior's covariance is the tree's marginal covariance from the earlier session (the
    trees CSV's ``std_x, std_y, cov_xy``); trees without one get ``default_sigma`` (m). A
    tree's observation count is at least ``min_obs`` so it stays in the merged map. When the
    map carries its joint information (:attr:`StemMap.information`) the factor is ``None``:
    :func:`joint_prior_factor` holds all trees at once instead -- unless ``kernel`` (a GTSAM
    m-estimator, ``Isam2Config.prior_map_robust``) is given: then every tree gets its own
    prior with that robust loss on its marginal (the correlations are dropped), so a tree
    whose earlier estimate this session's data contradict moves without dragging the poses
    (docs/algorithms/slam.md, "Maps reused across sessions").
    """
    import gtsam

    out: list[tuple[FloatArray, float, int, Any]] = []
    joint = kernel is None and _joint_sqrt_information(prior_map) is not None
    for j, t in enumerate(prior_map):
        if joint:
            xy = np.array([t.x, t.y], dtype=np.float64)
            out.append((xy, float(t.diameter), max(int(t.n_obs), min_obs), None))
            continue
        cov = np.asarray(t.cov, dtype=np.float64)
        if not (np.isfinite(cov).all() and np.linalg.eigvalsh(cov).min() > 0):
            cov = np.eye(2) * default_sigma**2
        cov = cov + np.eye(2) * 1e-6  # a floor: a 0-variance prior is a constraint
        xy = np.array([t.x, t.y], dtype=np.float64)
        noise: Any = gtsam.noiseModel.Gaussian.Covariance(cov)
        if kernel is not None:
            noise = gtsam.noiseModel.Robust.Create(kernel, noise)
        fac = gtsam.PriorFactorPoint2(key(j), xy, noise)
        out.append((xy, float(t.diameter), max(int(t.n_obs), min_obs), fac))
    return out


def inflate_prior(prior_map: StemMap, factor: float) -> StemMap:
    """``prior_map`` with every tree's covariance multiplied by ``factor`` (and its joint
    information, when it has one, divided by it): how a later session holds the map
    (``Isam2Config.prior_map_inflation``). Positions and everything else unchanged; ``factor``
    1 returns the map itself.

    Why (docs/algorithms/slam.md "Prior inflation"): an earlier session's tree marginals
    are conditioned on its own linearisation, data association and approximate noise model;
    on Victoria Park the bulk of them is within 0.8-2x of consistent with a later session's
    own estimates, but the mean normalised innovation is 3.4-12x (:func:`prior_consistency`),
    and session 2 scored best with the prior x4 on the splits the factor was chosen on.
    """
    if not (math.isfinite(factor) and factor > 0):
        raise InputError(f"inflate_prior: factor must be a positive number, got {factor}.")
    if factor == 1.0:
        return prior_map
    trees = tuple(dataclasses.replace(t, cov=np.asarray(t.cov) * factor) for t in prior_map)
    info = None if prior_map.information is None else prior_map.information / factor
    return dataclasses.replace(prior_map, trees=trees, information=info)


@dataclass(frozen=True)
class PriorConsistency:
    """Result of :func:`prior_consistency`.

    n_trees : prior trees the session re-observed (compared); nis : (n_trees,) normalised
    innovations ``dᵀ (P1 + P2)⁻¹ d``, chi-squared with 2 dof when both covariances are right;
    ratio_median : ``median(nis) / 1.386`` (the chi-squared(2) median), ratio_mean :
    ``mean(nis) / 2`` (1 when consistent; the mean is dominated by the few trees the data
    contradict, the median by the bulk); inflation : the factor ``f`` on ``P1`` for which the
    median of ``dᵀ (f P1 + P2)⁻¹ d`` is the chi-squared(2) median (``nan`` without trees)
    """

    n_trees: int
    nis: FloatArray
    ratio_median: float
    ratio_mean: float
    inflation: float


_CHI2_2_MEDIAN = 2.0 * math.log(2.0)


def prior_consistency(
    prior_map: StemMap, session_map: StemMap, min_new_obs: int = 3
) -> PriorConsistency:
    """Are a prior map's tree covariances consistent with what a later session sees?

    ``session_map`` is the later session's map made on ``prior_map`` with the prior held
    *weakly* (``Isam2Slam(prior_map_inflation=...)`` with a large factor, e.g. 100: the prior
    trees then only tie the session into the map's frame, and each one's estimate and
    marginal ``P2`` come from the session's own observations). A prior tree ``j`` (landmark
    ``j``, so ``Tree.id == j`` in the session's map) that the session observed at least
    ``min_new_obs`` more times gives the innovation ``d = x2 - x1`` between the two independent
    estimates and its normalised square ``dᵀ (P1 + P2)⁻¹ d`` -- the normalised innovation
    squared of Bar-Shalom, Li & Kirubarajan (2001), *Estimation with Applications to Tracking
    and Navigation*, §5.4.2, chi-squared with 2 dof for consistent covariances. The median is
    compared with the chi-squared median (robust to the few trees the data contradict, which
    a robust prior handles); ``inflation`` solves ``median_j dᵀ (f P1 + P2)⁻¹ d = 1.386`` for
    ``f`` (bisection in log f over [1e-3, 1e4]).
    """
    n1 = len(prior_map)
    p1 = list(prior_map)
    d_l, p1_l, p2_l = [], [], []
    for t in session_map:
        j = int(t.id)
        if not 0 <= j < n1:
            continue
        t1 = p1[j]
        if int(t.n_obs) - int(t1.n_obs) < min_new_obs:
            continue
        c1, c2 = np.asarray(t1.cov, np.float64), np.asarray(t.cov, np.float64)
        if not (np.isfinite(c1).all() and np.isfinite(c2).all()):
            continue
        d_l.append([t.x - t1.x, t.y - t1.y])
        p1_l.append(c1)
        p2_l.append(c2)
    if not d_l:
        return PriorConsistency(0, np.zeros(0), math.nan, math.nan, math.nan)
    d, c1a, c2a = np.asarray(d_l), np.asarray(p1_l), np.asarray(p2_l)

    def nis(f: float) -> FloatArray:
        s = f * c1a + c2a + np.eye(2) * 1e-9
        return np.asarray(np.einsum("ni,ni->n", d, np.linalg.solve(s, d[:, :, None])[:, :, 0]))

    lo, hi = math.log(1e-3), math.log(1e4)
    if np.median(nis(math.exp(hi))) > _CHI2_2_MEDIAN:
        f_hat = math.exp(hi)
    elif np.median(nis(math.exp(lo))) < _CHI2_2_MEDIAN:
        f_hat = math.exp(lo)
    else:
        for _ in range(60):  # the median NIS decreases with f
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if np.median(nis(math.exp(mid))) > _CHI2_2_MEDIAN else (lo, mid)
        f_hat = math.exp(0.5 * (lo + hi))
    q = nis(1.0)
    return PriorConsistency(
        int(q.size), q, float(np.median(q) / _CHI2_2_MEDIAN), float(q.mean() / 2.0), f_hat
    )


def _joint_sqrt_information(prior_map: StemMap) -> FloatArray | None:
    """Upper Cholesky factor ``U`` (``UᵀU = Λ``) of the map's joint information with the same
    1e-6 m² covariance floor as the per-tree priors; ``None`` without one (or not positive
    definite: logged, the per-tree priors are used)."""
    import scipy.linalg as sla

    info = prior_map.information
    if info is None or len(prior_map) == 0:
        return None
    try:
        cov = sla.cho_solve(sla.cho_factor(info), np.eye(info.shape[0]))
        cov = 0.5 * (cov + cov.T) + np.eye(info.shape[0]) * 1e-6
        lam = sla.cho_solve(sla.cho_factor(cov), np.eye(info.shape[0]))
        return np.asarray(sla.cholesky(0.5 * (lam + lam.T), lower=False), dtype=np.float64)
    except (np.linalg.LinAlgError, ValueError) as exc:
        log.warning("prior map: joint information unusable (%s); per-tree priors", exc)
        return None


def joint_prior_factor(prior_map: StemMap, key: Any, alias: np.ndarray | None = None) -> Any | None:
    """One factor holding all trees of ``prior_map`` by their joint information (``None`` when
    the map has none): the Gaussian ``‖U (x - x̂)‖²`` with ``UᵀU`` the earlier session's
    :attr:`StemMap.information` and ``x̂`` its tree positions, on landmark keys ``key(j)``.

    This is the earlier session's graph marginalised onto its trees (poses eliminated): exact
    to first order, so this session's observations move the old trees *together*, the way the
    earlier session's own poses tie them (per-tree priors drop those correlations and hold
    every tree on its own). ``alias`` (slot -> representative slot, after duplicate merging)
    puts a merged tree's part on its representative. A :class:`gtsam.CustomFactor` (one
    dense 2N x 2N Jacobian per linearisation, ~1 ms for 200 trees).
    """
    u = _joint_sqrt_information(prior_map)
    if u is None:
        return None
    n = len(prior_map)
    rep = np.arange(n) if alias is None else np.asarray(alias[:n], dtype=np.int64)
    return joint_factor(u, prior_map.xy, rep, key)


def joint_factor(u: FloatArray, xy: FloatArray, slots: np.ndarray, key: Any) -> Any:
    """The Gaussian ``‖U (x - x̂)‖²`` (``U`` (2n, 2n), ``x̂ = xy`` (n, 2)) on the landmarks
    ``key(slots[j])``; trees sharing a slot (merged) add their columns up. The factor of
    :func:`joint_prior_factor`, also of a continued graph's joint prior
    (:mod:`stemmap.slam._graph_continue`)."""
    import gtsam

    n = int(np.asarray(slots).size)
    reps, inv = np.unique(np.asarray(slots, dtype=np.int64), return_inverse=True)
    a = np.zeros((2 * n, 2 * reps.size))
    for j in range(n):  # x_j = y_rep(j): columns of merged trees add up
        a[:, 2 * inv[j] : 2 * inv[j] + 2] += u[:, 2 * j : 2 * j + 2]
    ux0 = u @ np.asarray(xy, dtype=np.float64).reshape(-1)
    keys = [key(int(r)) for r in reps]
    blocks = [np.ascontiguousarray(a[:, 2 * c : 2 * c + 2]) for c in range(reps.size)]

    def error(this: Any, values: Any, jac: Any) -> FloatArray:
        y = np.concatenate([values.atPoint2(k) for k in keys])
        if jac is not None:
            for c, blk in enumerate(blocks):
                jac[c] = blk
        return np.asarray(a @ y - ux0, dtype=np.float64)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n), keys, error)


def with_calibration(problem: SlamProblem, offset: float, scale: float) -> SlamProblem:
    """``problem`` with its odometry corrected by an earlier session's calibration of the same
    vehicle: every steering sample (yaw-rate sample for unicycle controls) ``+ offset`` and
    every speed sample ``x (1 + scale)`` -- the parameters :class:`Isam2Slam` estimates
    (stats ``calib_offset_mean``, ``calib_scale_mean``). Its own calibration then starts from
    the earlier estimate instead of from zero (its prior mean is the problem's controls)."""
    from stemmap.slam.base import Controls

    for name, v in (("offset", offset), ("scale", scale)):
        if not math.isfinite(v):
            raise InputError(f"with_calibration: {name} must be finite, got {v}.")
    c = problem.controls
    speed = np.asarray(c.speed, dtype=np.float64) * (1.0 + scale)
    steer = np.asarray(c.steer, dtype=np.float64) + offset
    return dataclasses.replace(problem, controls=Controls(c.times, speed, steer, c.kind))


def continue_session(
    problem: SlamProblem,
    prior_map: StemMap,
    guess: tuple[float, float, float] | None = None,
    cfg: RelocConfig | None = None,
    calibration: tuple[float, float] | None = None,
) -> tuple[SlamProblem, Relocalisation]:
    """``problem`` relocalised in ``prior_map`` and set to map on from it (merged output).

    ``guess`` (vehicle pose at the first scan, map frame) bounds the search; without one the
    search is global. ``calibration`` (offset, scale): the earlier session's odometry
    calibration, applied first (:func:`with_calibration`). Raises :class:`InputError` when
    relocalisation fails, with the reason.
    """
    if calibration is not None:
        problem = with_calibration(problem, *calibration)
    cfg = cfg or RelocConfig()
    if guess is None:
        cfg = dataclasses.replace(cfg, search_radius=None, search_angle=None)
        guess = (0.0, 0.0, 0.0)
    rel = relocalise(problem, prior_map, cfg, guess)
    if not rel.ok:
        raise InputError(
            f"could not relocalise in the prior map within {rel.time_s:.0f} s of driving: "
            f"{rel.reason}. Check that the run starts inside the mapped area, or give a start "
            "guess closer than the search radius."
        )
    return dataclasses.replace(problem, initial_pose=rel.pose, prior_map=prior_map), rel
