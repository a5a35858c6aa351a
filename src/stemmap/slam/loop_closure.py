"""Loop closure for the tree-map front-ends (Forestrix, tree DB): detection and bookkeeping.

A front-end that localises scan-to-map against the trees it saw *recently* is locally right and
drifts globally. Öhman et al. (2007, §2.1) recognise places by *tree groups* -- a tree and its
nearest neighbours, compared on inter-tree distances, which the drift does not change. Here the
trees first mapped in the last ``window_s`` seconds are matched by tree groups to the trees not
seen for ``gap_s`` seconds (the older map) with a search radius as large as the drift may be
(:func:`find_loop_closure`); a match that agrees on one rigid motion is a loop closure
(:class:`~stemmap.slam.relaxation.LoopClosure`), after which the back-end merges the revisited
trees and relaxes its trajectory (:func:`~stemmap.slam.relaxation.relax_trajectory`).
:class:`LoopCloser` keeps the keyframes and loops of one run; :func:`close_duplicates` lists the
trees a consistent (relaxed) map holds twice.

References
----------
.. [Ohman2007] M. Öhman et al., "Tree Measurement and Simultaneous Localization and Mapping
   System for Forest Harvesters", FSR 2007, §2.1-2.2.
.. [VL] "Visual LiDAR Odometry Using Tree Trunk Detection and LiDAR Localization", §2.5 (the tree
   database as landmarks for loop closure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError
from stemmap.slam._tree_groups import match_tree_groups
from stemmap.slam.relaxation import (
    LoopClosure,
    RelaxNoise,
    RigidFit,
    fit_rigid_robust,
    loop_constraint,
    relax_trajectory,
)
from stemmap.types import FloatArray

__all__ = [
    "LoopCloser",
    "LoopConfig",
    "LoopMatch",
    "close_duplicates",
    "find_loop_closure",
]

IntArray = NDArray[np.int64]


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
    search_radius: float = 20.0,
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


@dataclass(frozen=True)
class LoopConfig:
    """Loop detection and relaxation settings (see :class:`LoopCloser`).

    Parameters
    ----------
    gap_s : float, s
        Trees not seen for this long are the older map.
    every_s : float, s
        Loop detection runs at most this often.
    window_s : float, s
        Trees first mapped this recently are matched against the older map.
    search_radius : float, m
        Drift a revisit may have and still be recognised.
    min_support, min_matches, group_size, dist_tol
        As in :func:`find_loop_closure`.
    sigmas : (m, m, rad)
        Standard deviations of a loop constraint.
    keyframe_dist : float, m; keyframe_turn : float, rad
        A pose-graph node every this much motion.
    iterations : int
        Levenberg-Marquardt iterations per relaxation.
    noise : RelaxNoise
        The front-end chain's noise.
    """

    gap_s: float = 60.0
    every_s: float = 1.0
    window_s: float = 20.0
    search_radius: float = 20.0
    min_support: int = 3
    min_matches: int = 5
    group_size: int = 8
    dist_tol: float = 0.3
    sigmas: tuple[float, float, float] = (0.3, 0.3, math.radians(1.0))
    keyframe_dist: float = 2.0
    keyframe_turn: float = 0.1
    iterations: int = 50
    noise: RelaxNoise = field(default_factory=RelaxNoise)

    def __post_init__(self) -> None:
        if not (self.gap_s > 0 and self.every_s > 0 and self.window_s > 0):
            raise ConfigError("LoopConfig: gap_s, every_s and window_s must be > 0 s.")
        if not (self.search_radius > 0 and self.keyframe_dist > 0 and self.dist_tol > 0):
            raise ConfigError("LoopConfig: search_radius, keyframe_dist, dist_tol must be > 0 m.")
        if int(self.min_matches) < 3 or int(self.min_support) < 1:
            raise ConfigError("LoopConfig: min_matches must be >= 3 and min_support >= 1.")


class LoopCloser:
    """Keyframes and loop closures of one run, and the relaxation they drive.

    The back-end calls :meth:`on_frame` after fixing each frame's pose, :meth:`detect` when
    :meth:`due`, and :meth:`relax` after a detection (and after its own map merges).
    """

    def __init__(self, cfg: LoopConfig, frame_times: ArrayLike) -> None:
        self.cfg = cfg
        self.times = np.asarray(frame_times, dtype=np.float64)
        self.keyframes: list[int] = [0]
        self.loops: list[LoopClosure] = []
        self.n_relax = 0
        self.corrections: list[float] = []  # m: how far each closure moved the sensor
        self._last_try = -math.inf

    def on_frame(self, f: int, poses: FloatArray) -> None:
        """Make frame ``f`` a keyframe if it moved or turned enough since the last one."""
        if f == 0:
            return
        last, p = poses[self.keyframes[-1]], poses[f]
        if (
            math.hypot(p[0] - last[0], p[1] - last[1]) >= self.cfg.keyframe_dist
            or abs(math.remainder(p[2] - last[2], 2 * math.pi)) >= self.cfg.keyframe_turn
        ):
            self.keyframes.append(f)

    def due(self, tf: float) -> bool:
        if tf - self._last_try >= self.cfg.every_s:
            self._last_try = tf
            return True
        return False

    def detect(
        self,
        f: int,
        poses: FloatArray,
        sensor_xy: ArrayLike,
        xy: FloatArray,
        first: FloatArray,
        last: FloatArray,
        count: ArrayLike,
        alive: NDArray[np.bool_],
        *,
        min_count: int = 2,
        old_min_count: int = 1,
    ) -> tuple[IntArray, IntArray] | None:
        """Look for a revisit at frame ``f``; on success record the loop constraint and return
        the (recent, old) map indices of the revisited trees (the caller merges them).

        ``xy``, ``first``, ``last``, ``count``, ``alive``: the map's trees (positions, first and
        last sighting times, sightings, not retired); ``sensor_xy``: where the sensor is now;
        ``min_count`` / ``old_min_count``: sightings a recent / old tree needs to take part (the
        tree DB matches only its landmarks, as the visual-lidar paper uses them).
        """
        cfg = self.cfg
        tf = float(self.times[f])
        cnt = np.asarray(count)
        sp = np.asarray(sensor_xy, dtype=np.float64).reshape(2)
        recent = np.flatnonzero(
            alive & (first >= tf - cfg.window_s) & (cnt >= min_count) & (tf - last <= cfg.gap_s)
        )
        if recent.size < cfg.min_matches:
            return None
        reach = float(np.max(np.hypot(*(xy[recent] - sp).T))) + cfg.search_radius
        old = np.flatnonzero(alive & (tf - last > cfg.gap_s) & (cnt >= old_min_count))
        old = old[np.hypot(*(xy[old] - sp).T) <= reach]
        if old.size < cfg.min_matches:
            return None
        lm = find_loop_closure(
            xy[recent],
            xy[old],
            group_size=cfg.group_size,
            dist_tol=cfg.dist_tol,
            search_radius=cfg.search_radius,
            min_support=cfg.min_support,
            min_matches=cfg.min_matches,
            order_from=sp,
        )
        if not lm:
            return None
        src, dst = recent[lm.recent], old[lm.old]
        # the older frame: where the revisited trees were last seen (median time)
        j = int(np.clip(np.searchsorted(self.times, float(np.median(last[dst]))), 0, f))
        delta = loop_constraint(poses[j], poses[f], lm.fit)
        moved = lm.fit.apply_points(sp)[0] - sp
        self.corrections.append(float(math.hypot(moved[0], moved[1])))
        self.loops.append(LoopClosure(j, f, delta, cfg.sigmas))
        if self.keyframes[-1] != f:
            self.keyframes.append(f)
        return src, dst

    def stats(self) -> dict[str, float | int]:
        """Loop closures, relaxations and the sizes of the corrections (GPS-free diagnostics)."""
        c = np.asarray(self.corrections)
        return {
            "loop_closures": len(self.loops),
            "relaxations": self.n_relax,
            "loop_correction_median_m": float(np.median(c)) if c.size else 0.0,
            "loop_correction_max_m": float(c.max()) if c.size else 0.0,
        }

    def relax(
        self, poses: FloatArray, f: int, odometry_cov: FloatArray | None = None
    ) -> FloatArray:
        """Relaxed poses of frames ``0..f`` (all loops so far); ``odometry_cov``: see
        :func:`~stemmap.slam.relaxation.relax_trajectory`."""
        self.n_relax += 1
        kf = np.asarray(self.keyframes, dtype=np.int64)
        return relax_trajectory(
            poses[: f + 1],
            kf[kf <= f],
            self.loops,
            noise=self.cfg.noise,
            max_iterations=self.cfg.iterations,
            odometry_cov=None if odometry_cov is None else odometry_cov[: f + 1],
        )


def close_duplicates(
    xy: FloatArray,
    diameters: FloatArray,
    count: ArrayLike,
    alive: NDArray[np.bool_],
    dist: float,
    max_ddiam: float,
) -> tuple[IntArray, IntArray]:
    """(source, target) indices of live trees that are one tree: closer than ``dist`` with
    diameters within ``max_ddiam``, or overlapping trunks (iSAM2's rule,
    ``stemmap.slam.graph._merge_duplicates``); the target is the most-seen member."""
    from stemmap.slam.graph import _merge_duplicates

    idx = np.flatnonzero(alive)
    if idx.size < 2:
        e = np.zeros(0, dtype=np.int64)
        return e, e
    cnt = np.asarray(count, dtype=np.float64)[idx]
    dia = np.nan_to_num(np.asarray(diameters, dtype=np.float64)[idx], nan=0.0)
    rep = idx[_merge_duplicates(xy[idx], dia, cnt, dist, max_ddiam)]
    moved = rep != idx
    return idx[moved], rep[moved]


def relabel(labels: IntArray, src: ArrayLike, dst: ArrayLike, n: int) -> None:
    """In place: every label in ``src`` becomes the matching ``dst`` (-1 stays -1)."""
    remap = np.arange(n)
    remap[np.asarray(src, dtype=np.int64)] = np.asarray(dst, dtype=np.int64)
    ok = labels >= 0
    labels[ok] = remap[labels[ok]]
