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
5. **Relaxation** (§2.2): "the accumulated error" is distributed "evenly e.g. when a large loop
   is being closed". Default (``relaxation="pose_graph"``): loops are found by tree-group
   matching of the recently mapped trees against the older map
   (:func:`~stemmap.slam.loop_closure.find_loop_closure`), the *trajectory* is relaxed with the
   loop constraints (:func:`~stemmap.slam.relaxation.relax_trajectory`, GTSAM) and every tree is
   re-mapped from the relaxed poses. ``relaxation="tree_graph"``: the paper's simple iterative
   algorithm on the tree graph (:func:`relax_tree_graph`), which moves map nodes only.
6. **False trees** (§2.2, Fig. 5): the raw scan rays are cast through the mapped trees and a tree
   more rays pass through than hit it is removed (:mod:`stemmap.slam.negative`; ``false_trees``).

The primitives live in :mod:`stemmap.slam._tree_groups` and are re-exported here.

Decisions where the paper is silent (docs/algorithms/slam-frontends.md, slam.md): the matching
tolerance and search radius, the support needed to accept a group match, updating old trees'
positions by a running mean, the loop detection (search radius, agreeing pairs, the rigid-fit
check) and the relaxation's noise model.

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
from numpy.typing import NDArray

from stemmap.errors import ConfigError, InputError
from stemmap.slam._tree_groups import (
    PoseFit,
    TreeGraph,
    _neighbours,
    match_tree_groups,
    pose_fit_jacobians,
    pose_from_matches,
    relax_tree_graph,
)
from stemmap.slam._tree_map_errors import Localisation, TreeMapErrors
from stemmap.slam._treedb_localize import compose_jacobian
from stemmap.slam.loop_closure import LoopCloser, LoopConfig, close_duplicates, relabel
from stemmap.slam.relaxation import remap_trees
from stemmap.slam.tree_covariance import check_tree_cov_pass, with_tree_covariances
from stemmap.slam.uncertainty import CENTRE_RHO
from stemmap.types import FloatArray, ScanBatch, StemMap, Tree

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
    Every tree's reported covariance is that of the mean of its detections with the reported
    pose covariances (``SlamResult.pose_covs``) propagated into each detection and correlated
    between the frames that saw it (:func:`~stemmap.slam.tree_covariance.with_tree_covariances`;
    issue 14; the paper gives none).

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
    ray_position_tol : float, m
        Map position error the ray casting tolerates
        (:func:`~stemmap.slam.negative.ray_pass_through` ``position_tol``); false trees thinner
        than twice this are never judged.
    sigma_range : float, m; sigma_bearing : float, rad
        Detection noise of the reported pose and tree covariances only (the estimate does not
        use them). Default 0.10 m and 0.5°: the detection noise measured on Victoria Park from
        the detections alone (lag-1 re-observations, no GPS; iSAM2's defaults,
        docs/algorithms/slam.md "Noise parameters"). The tree DB's and EKF's 0.3 m / 1° made
        the derived pose covariance 4x too wide in std (demo drives, seeds 0-6: z² median
        0.075; Victoria Park second half 0.12): the fit takes its pose from the detections
        alone, so their noise model is all of its covariance between odometry steps.
    tree_cov_detections, tree_cov_pass_rho, tree_cov_pass_gap_s
        As :class:`~stemmap.slam._treedb_slam.TreeDbSlam`'s (Dec 6, default on): the reported
        tree covariance with each detection's own covariance where it has one, correlated
        within a pass with :data:`~stemmap.slam.uncertainty.CENTRE_RHO`.
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
    loop_gap_s: float = LoopConfig.gap_s
    relaxation: Literal["pose_graph", "tree_graph", "none"] = "pose_graph"
    loop_every_s: float = LoopConfig.every_s
    loop_window_s: float = LoopConfig.window_s
    loop_search_radius: float = LoopConfig.search_radius
    loop_min_support: int = LoopConfig.min_support
    loop_min_matches: int = LoopConfig.min_matches
    loop_sigmas: tuple[float, float, float] = LoopConfig.sigmas
    relax_iterations: int = 200
    relax_cooldown_s: float = 10.0
    keyframe_dist: float = 2.0
    min_observations: int = 5
    max_range: float = 50.0
    merge_dist: float = 1.0
    merge_ddiam: float = 0.42
    false_trees: Literal["none", "rays", "detections"] = "rays"
    ray_position_tol: float = 0.05
    sigma_range: float = 0.10
    sigma_bearing: float = math.radians(0.5)
    tree_cov_detections: bool = True
    tree_cov_pass_rho: float = CENTRE_RHO
    tree_cov_pass_gap_s: float = 5.0
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
        if not (self.sigma_range > 0 and self.sigma_bearing > 0):
            raise ConfigError("ForestrixSlam: sigma_range and sigma_bearing must be > 0.")
        check_tree_cov_pass(self.tree_cov_pass_rho, self.tree_cov_pass_gap_s, "ForestrixSlam")
        if not (self.merge_dist >= 0 and self.merge_ddiam >= 0):
            raise ConfigError(
                f"ForestrixSlam: merge_dist and merge_ddiam must be >= 0 m, got "
                f"{self.merge_dist}, {self.merge_ddiam}."
            )

    def loop_config(self) -> LoopConfig:
        """The loop-closure settings of this configuration."""
        return LoopConfig(
            gap_s=self.loop_gap_s,
            every_s=self.loop_every_s,
            window_s=self.loop_window_s,
            search_radius=self.loop_search_radius,
            min_support=self.loop_min_support,
            min_matches=self.loop_min_matches,
            group_size=self.group_size,
            dist_tol=self.dist_tol,
            sigmas=self.loop_sigmas,
            keyframe_dist=self.keyframe_dist,
            iterations=min(int(self.relax_iterations), 50),
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
        stem_map, n_merged = self._output_map(st)
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "graph_nodes": len(st.graph),
            "graph_edges": len(st.graph.edges),
            "trees_merged": n_merged,
            "frames_corrected": st.n_corrected,
            **(st.closer.stats() if st.closer else {"loop_closures": st.n_loops}),
            "trees_merged_at_loops": st.n_loop_merged,
            "trees_merged_after_relaxation": st.n_close_merged,
        }
        stem_map = self._remove_false_trees(stem_map, st, problem, scans, stats)
        stats["trees_mapped"] = len(stem_map)
        stats["runtime_s"] = float(_time.perf_counter() - t_start)
        # issue 14: the error covariance of this estimator as it ran (TreeMapErrors), with the
        # relaxation's loop constraints when it closed loops
        lc = st.closer
        pose_covs = (
            st.errs.abs_cov
            if lc is None
            else st.errs.pose_covariances(
                st.poses, lc.keyframes, lc.loops, lc.cfg.noise.loop_robust_k
            )
        )
        # issue 14: the reported pose covariances propagated, correlated between frames
        stem_map = with_tree_covariances(
            stem_map,
            st.poses,
            pose_covs,
            frames,
            sigma_range=self.sigma_range,
            sigma_bearing=self.sigma_bearing,
            sensor_offset=st.off,
            gate=self.new_tree_gate,
            detection_covs=self.tree_cov_detections,
            pass_rho=self.tree_cov_pass_rho,
            pass_gap=self.tree_cov_pass_gap_s,
        )
        return SlamResult(
            frame_trajectory(frames.times, st.poses), stem_map, stats, pose_covs=pose_covs
        )

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
            cleaned, res = remove_false_trees_by_rays(
                stem_map,
                sp,
                scans,  # type: ignore[arg-type]
                position_tol=self.ray_position_tol,
            )
        else:
            from stemmap.slam.negative import remove_false_trees_after

            tmp = SlamResult(frame_trajectory(problem.frames.times, st.poses), stem_map, {})
            cleaned, res = remove_false_trees_after(tmp, problem)
        stats["false_trees_removed"] = res.n_removed
        return cleaned


class _RunState:
    """Mutable state of one :meth:`ForestrixSlam.run` (front-end, loop closures, relaxation)."""

    def __init__(self, cfg: ForestrixSlam, problem: SlamProblem) -> None:
        from stemmap.slam.motion import preintegrate_spans

        self.cfg = cfg
        self.problem = problem
        fr = problem.frames
        self.frames = fr
        self.off = problem.sensor_offset
        self.pre = preintegrate_spans(
            problem.motion,
            problem.controls,
            fr.times,
            np.asarray(problem.initial_pose),
        )
        # covariance of the increments the map did not correct (dead-reckoned frames): the
        # relaxation's edge noise and, with every relaxation setting, the pose covariance
        self.dr_cov: FloatArray = np.zeros((len(fr), 3, 3))
        self.pose = np.asarray(problem.initial_pose, dtype=np.float64).copy()
        self.poses = np.empty((len(fr), 3))
        self.graph = TreeGraph()
        self.det_tree = np.full(fr.n_detections, -1, dtype=np.int64)
        self.det_frame = fr.frame_index
        self.n_corrected = 0
        self.n_loops = 0
        self.n_loop_merged = 0
        self.n_close_merged = 0
        self.last_relax = -math.inf
        self.corrected = False
        self.windowed = cfg.relaxation == "pose_graph"
        self.closer = LoopCloser(cfg.loop_config(), fr.times) if self.windowed else None
        R = np.diag([cfg.sigma_range**2, cfg.sigma_bearing**2])
        self.errs = TreeMapErrors(len(fr), R)

    # ---- per frame -----------------------------------------------------------------------

    def step(self, f: int) -> None:
        from stemmap.slam.base import observation_to_world
        from stemmap.slam.motion import compose

        cfg, graph, errs = self.cfg, self.graph, self.errs
        self.corrected = False
        if f > 0:
            delta = self.pre.deltas[f - 1]
            c, s = math.cos(self.pose[2]), math.sin(self.pose[2])
            Rw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            errs.predict(compose_jacobian(self.pose, delta), Rw @ self.pre.covs[f - 1] @ Rw.T)
            self.pose = compose(self.pose, delta)
        r, b, d = self.frames.frame(f)
        tf = float(self.frames.times[f])
        active = self._active(tf)
        if self.windowed:  # trees the matcher can no longer see leave the error state
            gone = np.ones(len(graph), dtype=bool)
            gone[active] = False
            errs.drop(np.flatnonzero(gone))
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
        lin: Localisation | None = None  # the correction as a linear map (issue 14)
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
                    Lp, Lm, Lv, _, _ = _fit_localisation(
                        self.pose, r[mm], b[mm], echo[mm], txy[match[mm]], fit, cfg.pose_method
                    )
                    lin = (Lp, Lm, Lv, mm, match[mm])
                    self.pose = fit.apply_pose(self.pose)
                    echo = observation_to_world(self.pose, r, b, off)
                    self.n_corrected += 1
                    self.corrected = True
        # classify echoes as old or new trees; accumulate
        ids = np.empty(r.size, dtype=np.int64)
        c_before = np.zeros(r.size, dtype=np.int64)  # each tree's count before this frame
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
                c_before[k] = graph.count[j]
                graph.update_tree(j, echo[k], float(d[k]), float(w_d[k]), tf)
            else:
                j = graph.add_tree(echo[k], float(d[k]), float(w_d[k]), tf)
            ids[k] = j
        p0 = int(self.frames.ptr[f])
        self.det_tree[p0 : p0 + use.size][use] = ids
        errs.frame(self.pose, r, b, off, lin, ids, c_before)
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
        if f > 0 and not self.corrected:
            self.dr_cov[f] = self.pre.covs[f - 1]
        lc = self.closer
        if lc is None:
            self.errs.record(f, False)
            return
        n_kf = len(lc.keyframes)
        lc.on_frame(f, self.poses)
        self.errs.record(f, len(lc.keyframes) > n_kf)
        if not lc.due(tf) or len(self.graph) < 2 * lc.cfg.min_matches:
            return
        n_kf = len(lc.keyframes)
        from stemmap.slam.base import observation_to_world

        g = self.graph
        sp = observation_to_world(self.pose, [0.0], [0.0], self.off)[0]
        found = lc.detect(
            f, self.poses, sp, g.positions(), g.first_time, g.last_time, g.count, g.alive
        )
        if len(lc.keyframes) > n_kf:  # a loop's endpoint became a keyframe
            self.errs.promote(f)
        if found is None:
            return
        self._merge(f, *found)
        self.n_loop_merged += found[0].size
        self._relax(f)

    # ---- loop closure ----------------------------------------------------------------------

    def _merge(self, f: int, src: IntArray, dst: IntArray) -> None:
        g = self.graph
        self.errs.merge(src, dst, g.count)
        pos = g.positions()
        for s_, d_ in zip(src.tolist(), dst.tolist(), strict=True):
            cs, cd = float(g.count[s_]), float(g.count[d_])
            pos[d_] = (cs * pos[s_] + cd * pos[d_]) / max(cs + cd, 1.0)
            g.merge(s_, d_)
        g.set_positions(pos)
        relabel(self.det_tree[: int(self.frames.ptr[f + 1])], src, dst, len(g))

    def _relax(self, f: int) -> None:
        assert self.closer is not None
        self.poses[: f + 1] = self.closer.relax(self.poses, f, self.dr_cov)
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
        g = self.graph
        ok = g.alive & (cnt > 0)
        pos = g.positions()
        pos[ok] = xy[ok]
        g.set_positions(pos)
        if self.cfg.merge_dist > 0:
            # the relaxed map is consistent again: the copies a drifted revisit created before
            # its loop was recognised now lie on top of the originals
            src, dst = close_duplicates(
                pos, g.diameters(), g.count, g.alive, self.cfg.merge_dist, self.cfg.merge_ddiam
            )
            if src.size:
                self._merge(f, src, dst)
                self.n_close_merged += src.size


def _fit_localisation(
    pose: FloatArray,
    r: FloatArray,
    b: FloatArray,
    echo: FloatArray,
    trees: FloatArray,
    fit: PoseFit,
    method: Literal["ohman2007", "procrustes"],
) -> Localisation:
    """Forestrix's pose correction as a linear map of the errors (issue 14;
    :data:`~stemmap.slam._tree_map_errors.Localisation`, matched detections numbered 0..m-1):
    the rigid ``fit`` of the echoes ``echo`` (projected with the predicted ``pose``) onto
    their ``trees`` differentiated (:func:`~stemmap.slam._tree_groups.pose_fit_jacobians`), chained
    with each echo's dependence on the predicted pose (``[I, J (e - p_xy)]``) and on its
    (range ``r``, bearing ``b``) noise."""
    Jp, Je, Jt = pose_fit_jacobians(echo, trees, pose, method=method, fit=fit)
    m = r.size
    ca, sa = np.cos(pose[2] + b), np.sin(pose[2] + b)
    Hw = np.zeros((m, 2, 3))
    Hw[:, 0, 0] = Hw[:, 1, 1] = 1.0
    Hw[:, 0, 2] = pose[1] - echo[:, 1]
    Hw[:, 1, 2] = echo[:, 0] - pose[0]
    Jz = np.stack((np.column_stack((ca, -r * sa)), np.column_stack((sa, r * ca))), axis=1)
    Je3 = Je.reshape(3, m, 2)
    Lp = Jp + np.einsum("iak,akj->ij", Je3, Hw)
    Lv = np.einsum("iak,akj->iaj", Je3, Jz).reshape(3, 2 * m)
    idx = np.arange(m, dtype=np.int64)
    return Lp, Jt, Lv, idx, idx
