"""Settings of the iSAM2 back-end (:class:`stemmap.slam.graph.Isam2Slam`).

Split out of :mod:`stemmap.slam.graph` (which re-exports it): graph.py had reached the ~800-line
limit. The method each setting belongs to is described in :mod:`stemmap.slam.graph` and in
docs/algorithms/slam.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from stemmap.errors import ConfigError

__all__ = ["Isam2Config"]


@dataclass(frozen=True)
class Isam2Config:
    """Settings of :class:`Isam2Slam` (defaults justified in docs/algorithms/slam.md).

    sigma_range, sigma_bearing : measurement noise (m, rad)
    sigma_diameter : m, diameter scatter for the association cue (None disables it)
    robust : "huber", "cauchy" or "none"; robust_k : kernel width in sigmas
    gate_chi2 : association gate on the Mahalanobis d² (3 dof with the diameter cue)
    new_chi2 : a detection starts a new tree only if its d² to every tree exceeds this
    new_min_dist : m, and it is at least this far from every tree
    max_range : m, detections farther than this are not used (bearing error x range)
    drift_scale : multiplies the odometry-derived variance between a tree's last observation
        in iSAM2 and the last update (the tree's drift relative to the current estimate),
        capped at ``max_drift_sigma``² (m²)
    local_drift_sigma : m, trees whose drift is below this are "local" (step 1 of the
        front-end); the others are re-acquired as a consistent group (step 2)
    consensus_chi2 : gate on the difference of two re-acquisition offsets (2 dof, 99 %)
    track_floor_sigmas : (m, m, rad), covariance of the tracked pose right after an iSAM2
        update (the estimate relative to the local map)
    keyframe_every : frames per keyframe (one Pose2 variable and one iSAM2 update each); the
        detections of a tree within a keyframe window are merged into one factor
    update_every : keyframes per iSAM2 update (association in between uses the odometry
        prediction from the last estimate)
    relinearize_threshold : iSAM2 relinearisation threshold
    batch_iterations : LM iterations at the end (0 = skip the batch step)
    batch_rel_tol : LM stops when an iteration lowers the cost by less than this fraction
        (GTSAM's default is 1e-5; 1e-4 of the full run's cost is ~0.9, under 1 % of the cost's
        own standard deviation sqrt(dof / 2) ~ 100, so the optimum does not change measurably)
    min_obs : trees seen fewer times are left out of the map (they stay in the graph)
    min_window_obs : a tree seen in fewer scans of a keyframe window gets no factor from that
        window (its detections still serve the association)
    merge_dist : m, after the batch step two trees closer than this with compatible diameters
        are merged into one and the graph is optimised again (0 disables)
    revisit_factors : localisation mode on revisits (:mod:`stemmap.slam._graph_revisits`,
        :mod:`stemmap.slam._graph_localise`): a keyframe whose every measured tree already has
        this many measurement factors in the graph adds no pose to the graph (reduced pose
        graph); it is tracked and associated as usual, the tracker is localised on the map
        from its measurements, and its pose is localised on the final map. 0 = off (every
        keyframe enters the graph). Default 15 (docs/algorithms/slam.md "Revisits";
        docs/reliability.md "Soak": the 10-pass Victoria Park replay)
    revisit_radius, revisit_keyframes, revisit_after_m : the area bound of the mode: where
        ``revisit_keyframes`` graph keyframes of an earlier visit (added ``revisit_after_m`` m
        of driving or more before; 0 = every earlier one) lie within ``revisit_radius`` m, a
        keyframe that sees only trees already in the graph stays out even if some have fewer
        than ``revisit_factors`` factors (only a new tree or a lost tracker brings it in).
        Visits are told apart by path distance, not time: a vehicle that drives slowly or
        stops is still on its first visit (docs/algorithms/slam.md "Revisits")
    revisit_place_visits : the area bound by visits: a place (``revisit_radius``) the
        vehicle drove past this many times before (keyframes in or out of the graph count;
        visits told apart by ``revisit_after_m``) is full as above, so a keyframe there whose
        trees are all in the graph stays out (:class:`stemmap.slam._graph_revisits.PlaceVisits`;
        0 = off). Default 3: on the 10x Victoria Park soak through ``stemmap map`` the
        memory growth per pass 6.37 -> 2.0 MB, single drive 1.303 -> 1.315 m; 2-8 keep the
        single drive within 1 %, 1 loses its second traversals (1.70 m);
        docs/algorithms/slam.md "The place bound counts every visit"
    revisit_keep_loops : a keyframe that closes a loop enters even where the bounds above
        leave it out: linked by odometry to a graph chain not tied to the map for
        ``revisit_after_m`` m, it measures a tree whose last graph factor lies
        ``revisit_after_m`` m or more back (:class:`stemmap.slam._graph_revisits.RevisitGate`)
    revisit_settle_visits : the bound by tree: a tree that got measurement factors on this
        many earlier visits (a visit: measured again after ``revisit_after_m`` m of driving
        without it) pulls no keyframe into the graph, even with fewer than ``revisit_factors``
        factors (:class:`stemmap.slam._graph_revisits.TreeVisits`; 0 = off). Default 0: 2
        bounds the 10x Victoria Park soak's graph (1,265 keyframes instead of 2,014, every
        pass 1.24-1.27 m) but the full log started at 6.0 s loses its path (11.6 m; 1.30 m
        off), docs/reliability.md "iSAM2 memory per pass"; 1 lost the 1x drive's loop closures
    revisit_anchor_after : a keyframe that enters the graph after more than this many left-out
        keyframes gets a prior at its tracked pose (covariance of the composed odometry,
        :func:`stemmap.slam._graph_revisits.anchor_prior`) instead of an odometry factor to the
        last graph keyframe (0 = always the odometry factor). Default 15 (docs/reliability.md
        "iSAM2: long left-out runs anchored": bounds iSAM2's memory on the 10x soak)
    revisit_hold_new : a tree first measured where the vehicle drove past this many times
        before (:class:`stemmap.slam._graph_revisits.PlaceVisits`) stays out of the graph: its
        measurements wait in the left-out store with their keyframes, it pulls no keyframe
        in, and at the end it is mapped from the left-out keyframes' localised poses
        (:func:`stemmap.slam._graph_revisits.map_held`) when measured on
        ``revisit_hold_confirm`` visits (and ``min_obs`` scans); measured from a keyframe that
        enters the graph anyway (a lost tracker, new ground) it enters the graph there. 0 =
        off (default; docs/reliability.md "Soak", tenth session)
    revisit_hold_confirm : visits (by path distance, ``revisit_after_m``) on which a held
        tree must be measured to be mapped (>= 1)
    marginals : compute per-tree covariances (:func:`_point_marginals`) at the end
    pose_marginals : also the marginal covariance of every graph keyframe, carried to every
        frame (``SlamResult.pose_covs``, :func:`_tree_and_pose_marginals`; docs/outputs.md
        "trajectory.csv"); the frames of keyframes left out of the graph bridged from their
        graph neighbours (:func:`~stemmap.slam._graph_odometry.frame_covariances`)
    calibrate : estimate the odometry calibration from the graph's own poses: a steering
        offset (rad; yaw-rate offset in rad/s for unicycle controls) and a speed-scale
        correction (:func:`_calibration_lsq`); online over the last ``calib_window``
        keyframes (for the new odometry factors), at the end per segment of ``calib_every``
        keyframes linked by a random walk, alternated with the batch LM (``calib_rounds``)
    calib_prior_sigmas : (offset, scale) prior sigmas (mean 0: the motion model's own
        calibration is the prior mean)
    calib_walk_sigmas : (offset, scale) random-walk intensities per sqrt(second)
    gnss_robust, gnss_robust_k : robust kernel of the GNSS position priors ("cauchy", "huber"
        or "none") and its width in sigmas (used when the problem has ``gnss`` fixes,
        :mod:`stemmap.slam.gnss`)
    gnss_prior_sigmas : (m, m, rad) weak prior on the first pose when GNSS is fused (the GNSS
        fixes fix the frame; this only keeps the first updates well-posed)
    reloc_prior_sigmas : (m, m, rad) prior on the first pose when the problem has a
        ``prior_map`` (the relocalised start: the map's trees fix the frame)
    prior_map_robust : "huber" (default), "cauchy" (width ``robust_k``) or "none": with a
        ``prior_map``, hold each of its trees by its own prior on its marginal with this robust
        loss; "none" holds them by the joint prior when the map carries its information
        (:attr:`stemmap.types.StemMap.information`), else by Gaussian per-tree priors. Huber
        by default: on three Victoria Park session pairs (0-400 / 0-600 / 0-800 s mapped, the
        rest relocalised and mapped on) session 2 scored 1.304 / 1.355 / 1.451 m against the
        joint prior's 1.340 / 1.433 / 1.529 m at 1.5-3.2x less CPU, relocalisation unchanged
        (docs/algorithms/slam.md "Maps reused across sessions")
    prior_map_inflation : factor (> 0) on the prior map's tree covariances (its joint
        information divided by it) as this session holds them
        (:func:`stemmap.slam.relocalise.inflate_prior`). 4 by default: chosen on the 400-s and
        800-s Victoria Park session pairs (session 2 1.303 / 1.451 m -> 1.261 / 1.446 m; 2, 8,
        30: 2.730 / 2.720 / 2.715 m summed vs 2.707), reported on 600 / 1000 / 1200 s (1.355
        / 1.438 / 0.834 -> 1.306 / 1.440 / 0.845 m); the bulk of the prior is near consistent
        with session 2, its tail is not (:func:`stemmap.slam.relocalise.prior_consistency`;
        docs/algorithms/slam.md "Prior inflation")
    joint_information : also return the trees' joint information matrix
        (:attr:`stemmap.types.StemMap.information`, needs ``marginals``): a later session on
        this map then continues from the correlated prior of all its trees instead of
        independent per-tree priors (docs/algorithms/slam.md "Prior maps"). Off by default:
        (2N)² floats (~12 MB for the ~600 trees of the full Victoria Park run)
    export_graph : also return the session's factor graph (``SlamResult.graph``,
        :mod:`stemmap.slam._graph_continue`; ``graph.npz`` beside the map) so that a later
        session can continue it (``SlamProblem.prior_graph``). Not for a session held by a
        marginal prior map or fused with GNSS (their priors are not in the saved graph): None
    prior_graph_inflation : factor (> 0) on the covariances of a continued graph's odometry
        and measurement factors (``SlamProblem.prior_graph``; its gauge prior as saved): the
        earlier session's information / factor, as ``prior_map_inflation`` for the marginal
        prior. 4 by default: chosen on the 400-s and 800-s Victoria Park session pairs
        (session 2 1.335 / 1.482 m at 1, 1.288 / 1.464 at 2, **1.282 / 1.446** at 4, 1.265 /
        1.485 at 8, 1.272 / 1.509 at 16); docs/algorithms/slam.md "Continuing the saved graph"
    """

    sigma_range: float = 0.10
    sigma_bearing: float = math.radians(0.5)
    sigma_diameter: float | None = 0.10
    robust: str = "huber"
    robust_k: float = 1.345
    gate_chi2: float = 11.34
    new_chi2: float = 30.0
    new_min_dist: float = 1.0
    max_range: float = 50.0
    drift_scale: float = 1.0
    max_drift_sigma: float = 1.5
    local_drift_sigma: float = 0.3
    consensus_chi2: float = 9.21
    track_floor_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.005)
    keyframe_every: int = 5
    update_every: int = 3
    relinearize_threshold: float = 0.05
    relinearize_skip: int = 10
    batch_iterations: int = 20
    batch_rel_tol: float = 1e-4
    min_obs: int = 3
    min_window_obs: int = 2
    merge_dist: float = 1.0
    revisit_factors: int = 15
    revisit_radius: float = 2.0
    revisit_keyframes: int = 3
    revisit_after_m: float = 50.0
    revisit_place_visits: int = 3
    revisit_settle_visits: int = 0
    revisit_keep_loops: bool = True
    revisit_anchor_after: int = 15
    revisit_hold_new: int = 0
    revisit_hold_confirm: int = 2
    marginals: bool = True
    pose_marginals: bool = True
    prior_sigmas: tuple[float, float, float] = (1e-3, 1e-3, 1e-4)
    calibrate: bool = True
    calib_prior_sigmas: tuple[float, float] = (0.02, 0.05)
    calib_walk_sigmas: tuple[float, float] = (1e-4, 1e-3)
    calib_every: int = 20
    calib_window: int = 40
    calib_rounds: int = 4
    gnss_robust: str = "cauchy"
    gnss_robust_k: float = 2.3849
    gnss_prior_sigmas: tuple[float, float, float] = (10.0, 10.0, 0.5)
    reloc_prior_sigmas: tuple[float, float, float] = (1.0, 1.0, 0.05)
    joint_information: bool = False
    prior_map_robust: str = "huber"
    prior_map_inflation: float = 4.0
    export_graph: bool = False
    prior_graph_inflation: float = 4.0

    def __post_init__(self) -> None:
        for name in ("robust", "gnss_robust", "prior_map_robust"):
            if getattr(self, name) not in ("huber", "cauchy", "none"):
                raise ConfigError(
                    f"Isam2Config.{name} must be 'huber', 'cauchy' or 'none', "
                    f"got {getattr(self, name)!r}."
                )
        for name in (
            "sigma_range",
            "sigma_bearing",
            "robust_k",
            "gnss_robust_k",
            "gate_chi2",
            "new_chi2",
            "prior_map_inflation",
            "prior_graph_inflation",
            "max_range",
            "relinearize_threshold",
            "batch_rel_tol",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"Isam2Config.{name} must be a positive number, got {v}.")
        if self.update_every < 1:
            raise ConfigError(f"Isam2Config.update_every must be >= 1, got {self.update_every}.")
        if self.keyframe_every < 1:
            raise ConfigError(
                f"Isam2Config.keyframe_every must be >= 1, got {self.keyframe_every}."
            )
        if not 1 <= self.min_window_obs <= self.keyframe_every:
            # a window holds keyframe_every scans: a larger minimum would drop every factor
            raise ConfigError(
                f"Isam2Config.min_window_obs must be in [1, keyframe_every = "
                f"{self.keyframe_every}], got {self.min_window_obs}."
            )
        if not (math.isfinite(self.revisit_radius) and self.revisit_radius > 0):
            raise ConfigError(
                f"Isam2Config.revisit_radius must be a positive number (m), got "
                f"{self.revisit_radius}."
            )
        if not (math.isfinite(self.revisit_after_m) and self.revisit_after_m >= 0):
            raise ConfigError(
                f"Isam2Config.revisit_after_m must be a number >= 0 (m), got "
                f"{self.revisit_after_m}."
            )
        if self.revisit_keyframes < 1:
            raise ConfigError(
                f"Isam2Config.revisit_keyframes must be >= 1, got {self.revisit_keyframes}."
            )
        if self.revisit_place_visits < 0:
            raise ConfigError(
                f"Isam2Config.revisit_place_visits must be >= 0 (0 = off), got "
                f"{self.revisit_place_visits}."
            )
        if self.revisit_settle_visits < 0:
            raise ConfigError(
                f"Isam2Config.revisit_settle_visits must be >= 0 (0 = off), got "
                f"{self.revisit_settle_visits}."
            )
        if self.revisit_anchor_after < 0:
            raise ConfigError(
                f"Isam2Config.revisit_anchor_after must be >= 0 (0 = off), got "
                f"{self.revisit_anchor_after}."
            )
        if self.revisit_hold_new < 0:
            raise ConfigError(
                f"Isam2Config.revisit_hold_new must be >= 0 (0 = off), got {self.revisit_hold_new}."
            )
        if self.revisit_hold_confirm < 1:
            raise ConfigError(
                f"Isam2Config.revisit_hold_confirm must be >= 1, got {self.revisit_hold_confirm}."
            )
        if self.revisit_factors < 0:
            raise ConfigError(
                f"Isam2Config.revisit_factors must be >= 0 (0 = off), got {self.revisit_factors}."
            )
        for name in ("calib_every", "calib_window", "calib_rounds"):
            if getattr(self, name) < 1:
                raise ConfigError(f"Isam2Config.{name} must be >= 1, got {getattr(self, name)}.")
        for name in ("calib_prior_sigmas", "calib_walk_sigmas"):
            v2 = getattr(self, name)
            if len(v2) != 2 or not all(math.isfinite(x) and x > 0 for x in v2):
                raise ConfigError(f"Isam2Config.{name} must be two positive numbers, got {v2}.")
        if self.sigma_diameter is not None and not self.sigma_diameter > 0:
            raise ConfigError(
                f"Isam2Config.sigma_diameter must be > 0 or None, got {self.sigma_diameter}."
            )
