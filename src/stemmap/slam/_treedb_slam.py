"""The TreeDbSlam back-end: the tree DB of the visual-lidar T-SLAM paper (§2.5) run over a drive.

The tree DB itself (entries, the eq. (2) count-weighted update, promotion to landmarks) is
:mod:`stemmap.slam.treedb`, which also re-exports :class:`TreeDbSlam`; the pose-only EKF
localisation against the landmarks is :mod:`stemmap.slam._treedb_localize` and the error
covariance carried alongside the filter :mod:`stemmap.slam._tree_map_errors`.

The paper's pipeline maps trees at the poses of an EKF odometry (no feedback from the trees into
the poses except through its LiDAR SLAM). :class:`TreeDbSlam` reproduces that with
``localize=False``; with ``localize=True`` (default, ours) promoted landmarks also correct the pose
with a pose-only EKF update, which is how the paper feeds its landmarks back into localisation.

References
----------
.. [VL] "Visual LiDAR Odometry Using Tree Trunk Detection and LiDAR Localization",
   §2.5 "Tree trunks as T-SLAM landmarks", eq. (2); ../shared/papers/visual-lidar-odometry-...md
"""

from __future__ import annotations

import logging
import math
import time as _time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from stemmap.errors import ConfigError
from stemmap.slam._tree_map_errors import TreeMapErrors, ekf_localisation
from stemmap.slam._treedb_localize import compose_jacobian, landmark_covariances, localize_pose
from stemmap.slam.loop_closure import LoopConfig
from stemmap.slam.tree_covariance import check_tree_cov_pass, with_tree_covariances
from stemmap.slam.treedb import (
    PRESETS,
    IntArray,
    TreeDb,
    TreeDbConfig,
    treedb_from_detections,
    treedb_update,
)
from stemmap.slam.uncertainty import CENTRE_RHO
from stemmap.types import FloatArray

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem, SlamResult, TreeFrames
    from stemmap.slam.loop_closure import LoopCloser

__all__ = ["TreeDbSlam"]

# the logger the back-end has always logged under (it is re-exported from there)
log = logging.getLogger("stemmap.slam.treedb")


@dataclass
class TreeDbSlam:
    """Tree-DB mapping at odometry poses (visual-lidar paper §2.5), optionally localising.

    Per frame: dead-reckon the pose with the odometry increment (``preintegrate``), optionally
    correct it with the promoted landmarks (``localize=True``, ours: pose-only EKF update with
    nearest-neighbour Mahalanobis association, landmarks held fixed but their scatter added to
    the measurement noise), then map the frame's detections at that pose and feed them to
    :func:`treedb_update`. The stem map holds the entries promoted at ``promote_count``.
    The reported pose covariance (``SlamResult.pose_covs``; issue 14) is derived from the
    estimator itself, with no factor fitted to data: the first-order error covariance of the
    pose *and of the DB entries it localises on*, propagated with the gains the filter used
    (odometry prediction, localisation against landmarks mapped from earlier poses, eq. (2)
    averaging of the detections into the DB; :class:`~stemmap.slam._tree_map_errors.
    TreeMapErrors`), and, with loop closure, pulled in by the loop constraints of the
    relaxation (:meth:`~stemmap.slam._tree_map_errors.TreeMapErrors.pose_covariances`). The
    filter's own ``P`` treats the map as known and is only its gain. Every tree's reported
    covariance is that of the average of its detections with the reported pose covariances
    propagated into each detection and correlated between the frames that saw it
    (:func:`~stemmap.slam.tree_covariance.mapped_tree_covariances`).

    Parameters
    ----------
    preset : str, optional
        Name in :data:`PRESETS` (``"visual_lidar"``) setting ``gate`` and ``promote_count``.
    gate : float, m
    promote_count : int
        Recognition count at which an entry becomes a landmark (localises, is mapped). Default
        5 (ours; the paper's 20 is the ``"visual_lidar"`` preset): on Victoria Park 20 kept
        only 233 trees against iSAM2's 392 and the EKF's 414 (trees first localise after 4 s
        of sightings), 5 keeps 418 (docs/algorithms/slam-frontends.md, issue 18).
    localize : bool
        False = the paper's open-loop pipeline (poses are pure odometry).
    sigma_range : float, m; sigma_bearing : float, rad
        Detection noise for the localisation update, and of every detection in the derived
        pose and tree covariances.
    chi2_gate : float
        Squared Mahalanobis gate for landmark association (2 dof; 9.21 = 99 %).
    landmark_association : bool
        Ours (with ``localize``): detections the localisation matched to a landmark (Mahalanobis
        gate, which widens with range) update that landmark's DB entry even when farther than
        ``gate`` -- the paper's fixed gate was meant for its 5 m sensing range (§2.2); at
        Victoria Park's 30-80 m ranges a 1° bearing error alone moves a trunk 0.5-1.4 m and the
        fixed gate splits one tree into many entries.
    refine : bool
        Re-estimate the landmarks with the Kalman refinement of Munjer §3.6
        (:func:`~stemmap.slam.refine.refine_stem_map`) weighting each detection by the filter's
        pose covariance of its frame. False = the paper's eq. (2) averages. Either way the
        reported covariance is the class doc's (the refinement's own covariance treated the
        frames' pose errors as independent, so it shrank like 1/n: simulator z² median 267).
    loop_closure : bool
        Ours, after the paper's use of the tree DB's landmarks for loop closure (§2.5; its
        T-SLAM closes loops, the DB supplies the landmarks). With ``localize``: localise and
        gate only against entries seen in the last ``loop_gap_s``; every second match the
        landmarks first stored in the last 20 s by tree groups (Öhman 2007 §2.1) to the older
        landmarks (:class:`~stemmap.slam.loop_closure.LoopCloser`: search radius
        ``loop_search_radius``, ``loop_min_matches`` pairs agreeing on one rigid motion); on a
        revisit merge the entries, relax the trajectory (GTSAM pose graph,
        :func:`~stemmap.slam.relaxation.relax_trajectory`) and rebuild the DB from the relaxed
        poses (:func:`treedb_from_detections`: eq. (2) is the mean of the detections, so this
        is the DB the updates would have built there). False = the filter alone (its pose
        estimates are final; Victoria Park 3.79 m, docs/algorithms/slam.md).
    localize_recent_only : bool
        With ``loop_closure``: localise only against landmarks seen in the last ``loop_gap_s``
        (default). False lets the filter pull the pose to old landmarks, which puts the
        loop-closing jumps into the chain the relaxation treats as odometry (Victoria Park:
        5.8 m ATE against 2.0 m, measured before the landmark-only loop matching).
    max_range : float, m
        Detections farther than this are not used (iSAM2's 50 m).
    merge_dist, merge_ddiam : float, m
        After each relaxation and at the end, entries closer than ``merge_dist`` with diameters
        within ``merge_ddiam`` (or overlapping trunks) are one tree (iSAM2's rule).
    tree_cov_detections : bool
        Ours (Dec 6): the reported tree covariance takes each detection's own (range,
        bearing) covariance (``TreeFrames.noise_cov``, the scan detector's centre covariance)
        where it has one, instead of ``sigma_range`` / ``sigma_bearing``; detections without
        one (e.g. Victoria Park's) keep the constant. Covariance only: no estimate reads it.
    tree_cov_pass_rho : float in [0, 1]
        Ours (Dec 6): the errors of those detections of one tree within one pass (no gap of
        more than ``tree_cov_pass_gap_s``) correlated with this ``rho`` in the reported tree
        covariance (:mod:`stemmap.slam.tree_covariance`; 0: independent). Default
        :data:`~stemmap.slam.uncertainty.CENTRE_RHO`, measured on real drive-by passes: with
        both, held out on real trunk geometry the tree DB's trees state median Mahalanobis d
        0.66-2.02 (1.18 calibrated) where the constant noise stated 0.21-0.51 and the own
        covariances alone 1.5-5.4 (docs/algorithms/slam.md "Correlated detections in the
        tree DB's and Forestrix's tree covariance").
    tree_cov_pass_gap_s : float, s
        A tree's detections more than this apart in time belong to different passes.
    """

    preset: str | None = None
    gate: float = 0.5
    promote_count: int = 5
    localize: bool = True
    sigma_range: float = 0.3
    sigma_bearing: float = math.radians(1.0)
    chi2_gate: float = 9.21
    refine: bool = True
    landmark_association: bool = True
    loop_closure: bool = True
    loop_gap_s: float = LoopConfig.gap_s
    loop_search_radius: float = LoopConfig.search_radius
    loop_min_matches: int = LoopConfig.min_matches
    localize_recent_only: bool = True
    max_range: float = 50.0
    merge_dist: float = 1.0
    merge_ddiam: float = 0.42
    tree_cov_detections: bool = True
    tree_cov_pass_rho: float = CENTRE_RHO
    tree_cov_pass_gap_s: float = 5.0
    name: str = "treedb"

    def __post_init__(self) -> None:
        if self.preset is not None:
            if self.preset not in PRESETS:
                raise ConfigError(
                    f"unknown TreeDbSlam preset {self.preset!r}; choose from {sorted(PRESETS)}."
                )
            cfg = PRESETS[self.preset]
            self.gate, self.promote_count = cfg.gate, cfg.promote_count
        TreeDbConfig(self.gate, self.promote_count)  # validates
        if not (self.sigma_range > 0 and self.sigma_bearing > 0 and self.chi2_gate > 0):
            raise ConfigError("TreeDbSlam: sigma_range, sigma_bearing and chi2_gate must be > 0.")
        check_tree_cov_pass(self.tree_cov_pass_rho, self.tree_cov_pass_gap_s, "TreeDbSlam")

    def run(
        self, problem: SlamProblem, *, progress: Callable[[int, int], None] | None = None
    ) -> SlamResult:
        """Run the tree DB over ``problem``; see the class docstring."""
        from stemmap.slam.base import SlamResult, frame_trajectory, observation_to_world
        from stemmap.slam.motion import compose, preintegrate_spans

        t0 = _time.perf_counter()
        frames = problem.frames
        nf = len(frames)
        pre = preintegrate_spans(
            problem.motion, problem.controls, frames.times, np.asarray(problem.initial_pose)
        )
        off = problem.sensor_offset
        R = np.diag([self.sigma_range**2, self.sigma_bearing**2])
        pose = np.asarray(problem.initial_pose, dtype=np.float64).copy()
        P = np.zeros((3, 3))
        poses = np.empty((nf, 3))
        pose_covs = np.empty((nf, 3, 3))
        db = TreeDb()
        det_entry = np.full(frames.n_detections, -1, dtype=np.int64)
        dr_cov = np.zeros((nf, 3, 3))  # increments no landmark corrected (dead reckoning)
        closer = None
        if self.loop_closure and self.localize:  # open loop = the paper's odometry pipeline
            from stemmap.slam.loop_closure import LoopCloser, LoopConfig

            closer = LoopCloser(
                LoopConfig(
                    gap_s=self.loop_gap_s,
                    search_radius=self.loop_search_radius,
                    min_matches=self.loop_min_matches,
                ),
                frames.times,
            )
        # issue 14: the error covariance of this estimator as it runs (module doc)
        errs = TreeMapErrors(nf, R)
        n_updates = 0
        n_loop_merged = 0
        for f in range(nf):
            tf = float(frames.times[f])
            if f > 0:
                delta = pre.deltas[f - 1]
                Fx = compose_jacobian(pose, delta)
                c, s = math.cos(pose[2]), math.sin(pose[2])
                Rw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                P = Fx @ P @ Fx.T + Rw @ pre.covs[f - 1] @ Rw.T
                errs.predict(Fx, Rw @ pre.covs[f - 1] @ Rw.T)
                pose = compose(pose, delta)
            r, b, d = frames.frame(f)
            use = r <= self.max_range
            if not use.all():
                r, b, d = r[use], b[use], d[use]
            known = None
            active = None
            corrected = False
            loc = None
            if closer is not None and len(db):
                active = (db.count > 0) & (tf - db.last_time <= self.loop_gap_s)
                if self.localize_recent_only:
                    errs.drop(np.flatnonzero(~active))
            if self.localize and r.size and len(db):
                lm = db.landmarks(self.promote_count)
                if active is not None and self.localize_recent_only:
                    lm = lm[active[lm]]
                if lm.size:
                    pose, P, matched, gain = localize_pose(
                        pose,
                        P,
                        r,
                        b,
                        db.xy[lm],
                        landmark_covariances(db, lm),
                        R,
                        off,
                        self.chi2_gate,
                    )
                    n_updates += int(np.any(matched >= 0))
                    corrected = bool(np.any(matched >= 0))
                    if self.landmark_association:
                        known = np.where(matched >= 0, lm[np.clip(matched, 0, None)], -1)
                    if gain is not None:
                        loc = ekf_localisation(*gain[:4], lm[gain[4]])
            poses[f] = pose
            pose_covs[f] = P
            if f > 0 and not corrected:
                dr_cov[f] = pre.covs[f - 1]
            if r.size:
                xy = observation_to_world(pose, r, b, off)
                n_old, cnt_old = len(db), db.count
                db, idx = treedb_update(
                    db, xy, d, tf, gate=self.gate, known=known, candidates=active
                )
                det_entry[frames.ptr[f] : frames.ptr[f + 1]][use] = idx
                c_before = np.zeros(idx.size, dtype=np.int64)
                c_before[idx < n_old] = cnt_old[idx[idx < n_old]]
                errs.frame(pose, r, b, off, loc, idx, c_before)
            if closer is not None:
                n_kf = len(closer.keyframes)
                closer.on_frame(f, poses)
                errs.record(f, len(closer.keyframes) > n_kf)
                n_kf = len(closer.keyframes)
                if closer.due(tf) and len(db) >= 2 * closer.cfg.min_matches:
                    sp = observation_to_world(pose, [0.0], [0.0], off)[0]
                    alive = db.count > 0
                    found = closer.detect(
                        f,
                        poses,
                        sp,
                        db.xy,
                        db.first_time,
                        db.last_time,
                        db.count,
                        alive,
                        min_count=self.promote_count,
                        old_min_count=self.promote_count,
                    )
                    if len(closer.keyframes) > n_kf:  # a loop's endpoint became a keyframe
                        errs.promote(f)
                    if found is not None:
                        n_loop_merged += found[0].size
                        errs.merge(found[0], found[1], db.count)
                        db = self._relax(
                            closer, found, poses, det_entry, f, frames, off, dr_cov, errs.merge
                        )
                        pose = poses[f].copy()
            else:
                errs.record(f, False)
            if progress is not None and (f % 200 == 0 or f == nf - 1):
                progress(f + 1, nf)
        if closer is not None and self.merge_dist > 0 and len(db):
            db = self._merge_close(db, det_entry, poses, nf - 1, frames, off)
        stem_map = db.to_stem_map(self.promote_count)
        if self.refine:
            from stemmap.slam.refine import refine_stem_map

            stem_map = refine_stem_map(
                stem_map,
                poses,
                frames.ptr,
                frames.ranges,
                frames.bearings,
                sigma_range=self.sigma_range,
                sigma_bearing=self.sigma_bearing,
                sensor_offset=off,
                pose_covs=pose_covs,
                gate=self.gate,
            )
        out_covs = (
            errs.abs_cov
            if closer is None
            else errs.pose_covariances(
                poses, closer.keyframes, closer.loops, closer.cfg.noise.loop_robust_k
            )
        )
        # issue 14: the reported pose covariances propagated, correlated between frames
        stem_map = with_tree_covariances(
            stem_map,
            poses,
            out_covs,
            frames,
            sigma_range=self.sigma_range,
            sigma_bearing=self.sigma_bearing,
            sensor_offset=off,
            gate=self.gate,
            information_pose_covs=pose_covs if self.refine else None,
            detection_covs=self.tree_cov_detections,
            pass_rho=self.tree_cov_pass_rho,
            pass_gap=self.tree_cov_pass_gap_s,
        )
        stats: dict[str, float | int | str] = {
            "backend": self.name,
            "db_entries": len(db),
            "landmarks": len(stem_map),
            "frames_localized": n_updates,
            "entries_merged_at_loops": n_loop_merged,
            **(closer.stats() if closer is not None else {"loop_closures": 0}),
            "runtime_s": _time_since(t0),
        }
        log.info("treedb: %d DB entries, %d landmarks", len(db), len(stem_map))
        return SlamResult(
            frame_trajectory(frames.times, poses),
            stem_map,
            stats,
            pose_covs=out_covs,
        )

    def _relax(
        self,
        closer: LoopCloser,
        found: tuple[IntArray, IntArray],
        poses: FloatArray,
        det_entry: IntArray,
        f: int,
        frames: TreeFrames,
        off: tuple[float, float],
        dr_cov: FloatArray,
        on_merge: Callable[[IntArray, IntArray, IntArray], None] | None = None,
    ) -> TreeDb:
        """Merge the revisited entries, relax the trajectory, rebuild the DB from the relaxed
        poses and merge the entries that now lie on top of each other (``on_merge(src, dst,
        counts)`` told of the latter)."""
        from stemmap.slam.base import observation_to_world
        from stemmap.slam.loop_closure import relabel

        k_end = int(frames.ptr[f + 1])
        ent = det_entry[:k_end]
        n = int(ent.max(initial=-1)) + 1
        relabel(ent, found[0], found[1], n)
        poses[: f + 1] = closer.relax(poses, f, dr_cov)
        fi = frames.frame_index[:k_end]
        xy = observation_to_world(poses[fi], frames.ranges[:k_end], frames.bearings[:k_end], off)
        args = (frames.diameters[:k_end], frames.times[fi])
        db = treedb_from_detections(xy, *args, ent, n)
        if self.merge_dist > 0:
            db = self._merge_close(db, det_entry, poses, f, frames, off, on_merge)
        return db

    def _merge_close(
        self,
        db: TreeDb,
        det_entry: IntArray,
        poses: FloatArray,
        f: int,
        frames: TreeFrames,
        off: tuple[float, float],
        on_merge: Callable[[IntArray, IntArray, IntArray], None] | None = None,
    ) -> TreeDb:
        """Merge entries closer than ``merge_dist`` with compatible diameters (iSAM2's rule)
        and rebuild the DB from the detections of frames ``0..f`` at ``poses``."""
        from stemmap.slam.base import observation_to_world
        from stemmap.slam.loop_closure import close_duplicates, relabel

        src, dst = close_duplicates(
            np.nan_to_num(db.xy, nan=1e9),
            db.diameter,
            db.count,
            db.count > 0,
            self.merge_dist,
            self.merge_ddiam,
        )
        if src.size == 0:
            return db
        if on_merge is not None:
            on_merge(src, dst, db.count)
        k_end = int(frames.ptr[f + 1])
        ent = det_entry[:k_end]
        relabel(ent, src, dst, len(db))
        fi = frames.frame_index[:k_end]
        xy = observation_to_world(poses[fi], frames.ranges[:k_end], frames.bearings[:k_end], off)
        return treedb_from_detections(xy, frames.diameters[:k_end], frames.times[fi], ent, len(db))


def _time_since(t0: float) -> float:
    """Seconds elapsed since ``t0`` (``time.perf_counter`` value)."""
    return float(_time.perf_counter() - t0)
