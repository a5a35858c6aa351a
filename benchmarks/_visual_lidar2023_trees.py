"""The tree database rows of benchmarks/visual_lidar2023.py: trunk detections from the
benchmark's own simulated 2D scans, fed through the tree DB (visual-lidar §2.5, eq. (2)) on the
fused odometry, the promoted trees used as landmarks for loop closure.

Detection sources (:data:`SOURCES`), each a row ``fused_trees*`` of the benchmark:

* ``fused_trees``: the library's scan detector with its default preset, the path
  ``stemmap detect`` runs (:class:`stemmap.scan.detect.ScanTrunkDetector` ``("stemmap")``,
  ``detect_batch`` on the run's scans, no option changed);
* ``fused_trees_paper``: the paper's own filter (preset ``visual_lidar2023``: 100° window,
  5 m, width <= 0.55 m, radius median 0.5 m, Kasa fit, >= 40 points) with its point minimum
  converted to the simulated scanner's beam spacing (:func:`paper_min_points`): the paper's
  40 points are returns of an RPLIDAR S2 at 0.12° (its Table 1), i.e. a trunk at least 4.8°
  wide; at the benchmark's 0.25° that is 20 returns. As published (40 returns at 0.25°) it
  detects nothing on these scans (:func:`paper_filter_stages`, reported as
  ``detections.paper_stage.detections_as_published``);
* ``fused_trees_oracle``: the detection upper bound, ORACLE detections
  (:func:`stemmap.sim.observations.oracle_observations`: every trunk with >= 10 beams on it
  within :data:`TREE_RANGE`, 360°, 3 cm noise): every trunk a detector could see, none
  missed, none false. Not an upper bound on the loop error: the library's detector misses
  trunks but its centres are closer (median 1.8 cm against the oracle's 3.5 cm).

Every source goes through :class:`stemmap.slam.treedb.TreeDbSlam` with the ``visual_lidar``
preset's 0.5 m gate, detections within :data:`TREE_RANGE`, pose correction by the landmarks
and loop closure on them, at the recognition count of :data:`PROMOTE_COUNT`.

The paper's count 20 is a number of frames: 20 recognitions at its 20 fps lidar and 0.1-0.3
m/s (§3.1) is 1 s and 0.1-0.3 m of travel. Here the scans come at 5 Hz and 1 m/s: 20
recognitions are 4 s and 4 m. Every source's count is chosen on drives the
benchmark does not score (``visual_lidar2023.py --tune-trees 30 40``: the calibration drive
and the loops of seeds 30 and 40, :func:`tune_counts`); see :data:`PROMOTE_COUNT`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Trunks are detected within this range (m); the paper's distance filter is 5 m (§2.2). The
#: oracle observes trunks within it; the tree DB uses no detection beyond it.
TREE_RANGE = 6.0

#: The paper's circle-fit minimum (§2.3: 40 points) and the angular step of its scanner
#: (RPLIDAR S2, 0.12°, Table 1).
PAPER_MIN_POINTS = 40
PAPER_ANGLE_INCREMENT_DEG = 0.12

#: Detection sources: benchmark key -> source name of :func:`tree_observations`.
SOURCES = {
    "fused_trees": "stemmap",
    "fused_trees_paper": "visual_lidar2023",
    "fused_trees_oracle": "oracle",
}

#: Recognition count at which a DB entry becomes a landmark, per source, chosen with
#: ``--tune-trees 30 40`` from :data:`COUNT_GRID` by the smallest mean loop-closure error on
#: the calibration drive and the 8 loops of seeds 30 and 40 (none scored; ties to the larger
#: count; ``fused`` alone 0.078 m there). ``stemmap``: 3 (0.032 m; 1: 0.049, 2: 0.036, 5:
#: 0.043, 10: 0.054, 20: 0.053): its trunks are detected in 26-79 frames (median per drive),
#: so 20 promotes them too, but 4 s later, after the error the landmarks should hold has
#: grown. ``visual_lidar2023``: 20 (0.086 m, = 10; 1: 0.111, 2: 0.120, 3: 0.280, 5: 0.102):
#: its trunks are seen in 2-7 frames, so at 10-20 almost none is promoted (the row is
#: ``fused`` but for one tree on one drive), and landmarks from its few, 7-9 cm-off
#: detections make the loop worse than ``fused``. ``oracle``: 1 (0.032 m; 2: 0.040, 3: 0.042,
#: 5: 0.046, 10: 0.055, 20: 0.051; seen in 56-120 frames). The paper's 20 is 1 s of its 20
#: fps scans at 0.1-0.3 m/s, 0.1-0.3 m of travel: 1-2 frames here by distance, 5 by time
#: (docs/algorithms/slam-frontends.md, "Tree DB with real detections"). Those numbers are from
#: 3 Dec (VO before Dec 4); re-run Dec 5 with the keyframe fraction 0.7 (``fused`` 0.075 m):
#: ``stemmap`` 3 (0.026 m) and ``oracle`` 1 (0.040 m) again, ``visual_lidar2023`` 10 (0.082
#: against 0.085 m at 20): kept at 20, not re-tuned (same docs).
PROMOTE_COUNT = {"stemmap": 3, "visual_lidar2023": 20, "oracle": 1}

#: The counts ``--tune-trees`` tries.
COUNT_GRID = (1, 2, 3, 5, 10, 20)


def paper_min_points(angle_increment: float) -> int:
    """The paper's 40-point minimum (at 0.12°) as a return count at ``angle_increment``
    (radians): the same smallest angular width of a trunk, ``ceil(40 x 0.12° / step)``."""
    step = math.degrees(abs(angle_increment))
    return max(3, math.ceil(PAPER_MIN_POINTS * PAPER_ANGLE_INCREMENT_DEG / step - 1e-9))


def tree_observations(run: Any, source: str, seed: int) -> Any:
    """Trunk observations (sensor frame, ``index`` = scan) of a simulated run from ``source``
    (``"stemmap"``, ``"visual_lidar2023"``, ``"oracle"``; see the module doc)."""
    from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
    from stemmap.sim.observations import oracle_observations

    if source == "oracle":
        obs, _ = oracle_observations(
            run, min_returns=10, max_range=TREE_RANGE, sigma_xy=0.03, rng=seed
        )
        return obs
    if source == "visual_lidar2023":
        mp = paper_min_points(run.scans.angle_increment)
        return ScanTrunkDetector(DetectorConfig.preset(source, min_points=mp)).detect_batch(
            run.scans
        )
    if source == "stemmap":
        return ScanTrunkDetector(source).detect_batch(run.scans)
    raise ValueError(f"unknown detection source {source!r}")


def detection_stats(run: Any, obs: Any) -> dict[str, float]:
    """Per frame: detections, those within :data:`TREE_RANGE`, their precision (a true trunk
    centre within 0.3 m, the sensor frame) and median centre error; per true trunk detected
    at all within
    :data:`TREE_RANGE`: the median number of frames it is detected in (what a recognition
    count is compared with)."""
    from stemmap.sim.observations import trees_in_sensor_frame

    n = len(run)
    near = np.hypot(obs.centers[:, 0], obs.centers[:, 1]) <= TREE_RANGE
    loc = trees_in_sensor_frame(run)
    if len(obs):
        d = np.hypot(*(loc[obs.index] - obs.centers[:, None, :]).transpose(2, 0, 1))
        dmin = d.min(axis=1)
        hit = dmin <= 0.3
        tree = np.argmin(d, axis=1)
        frames = np.bincount(tree[near & hit], minlength=run.stand.n_trees)
        seen = frames[frames > 0]
    else:
        dmin, hit, seen = np.zeros(0), np.zeros(0, dtype=bool), np.zeros(0)
    return {
        "per_frame": len(obs) / n,
        "within_range_per_frame": float(np.sum(near)) / n,
        "precision_within_range": float(np.mean(hit[near])) if np.any(near) else math.nan,
        "median_centre_error_m": float(np.median(dmin[near & hit]))
        if np.any(near & hit)
        else math.nan,
        "trees_detected": int(seen.size),
        "median_frames_per_tree": float(np.median(seen)) if seen.size else 0.0,
    }


def tree_db_trajectory(
    fused: Any, obs: Any, scan_times: Any, pose0: Any, promote_count: int
) -> tuple[Any, int]:
    """The tree DB (visual_lidar gate 0.5 m, eq. (2), ``promote_count``, landmarks correcting
    the pose and closing loops) on the fused odometry's path
    (:meth:`stemmap.slam.base.Controls.from_trajectory`: controls through every pose, the
    lateral part of the EKF's pose updates included, so with no landmark it returns that
    path). Returns the trajectory and the trees mapped."""
    from stemmap.slam.base import Controls, SlamProblem, TreeFrames
    from stemmap.slam.motion import UnicycleModel
    from stemmap.slam.treedb import PRESETS, TreeDbSlam

    problem = SlamProblem(
        Controls.from_trajectory(fused.trajectory),
        TreeFrames.from_observations(obs, scan_times),
        UnicycleModel(sigma_speed=0.05, sigma_steer=math.radians(1.0)),
        initial_pose=tuple(pose0),
    )
    slam = TreeDbSlam(
        gate=PRESETS["visual_lidar"].gate, promote_count=promote_count, max_range=TREE_RANGE
    )
    res = slam.run(problem)
    return res.trajectory, len(res.stem_map)


def tree_rows(
    run: Any, fused: Any, pose0: Any, seed: int, counts: dict[str, int] | None = None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Every source of :data:`SOURCES` on one loop: ``({key: trajectory}, diagnostics)``."""
    counts = counts or PROMOTE_COUNT
    est: dict[str, Any] = {}
    diag: dict[str, Any] = {}
    for key, src in SOURCES.items():
        obs = tree_observations(run, src, seed)
        est[key], n_trees = tree_db_trajectory(fused, obs, run.scans.times, pose0, counts[src])
        st = detection_stats(run, obs)
        diag[f"trees_mapped.{key}"] = n_trees
        diag.update({f"detections.{key}.{k}": v for k, v in st.items()})
    diag.update({f"detections.paper_stage.{k}": v for k, v in paper_filter_stages(run).items()})
    return est, diag


def paper_filter_stages(run: Any) -> dict[str, float]:
    """Where the paper's filter (preset ``visual_lidar2023``) loses the trunks of a run, per
    frame: true trunks inside its window (5 m, ±50°) hit by any beam, those with at least
    :func:`paper_min_points` returns and with the published 40, the largest return count of
    any trunk in the window, and the detections of the preset as published and converted.
    (The detector's segments are the trunks' returns here: nothing else in the window.)"""
    from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
    from stemmap.sim.observations import returns_per_tree, trees_in_sensor_frame

    cfg = DetectorConfig.preset("visual_lidar2023")
    loc = trees_in_sensor_frame(run)
    bearing = np.degrees(np.arctan2(loc[..., 1], loc[..., 0]))
    lo, hi = cfg.fov_deg or (-180.0, 180.0)
    inside = (np.hypot(loc[..., 0], loc[..., 1]) <= (cfg.range_max or math.inf)) & (
        (bearing >= lo) & (bearing <= hi)
    )
    n_ret = np.where(inside, returns_per_tree(run), 0)
    mp = paper_min_points(run.scans.angle_increment)
    n = len(run)
    published = ScanTrunkDetector(cfg).detect_batch(run.scans)
    converted = tree_observations(run, "visual_lidar2023", 0)
    return {
        "window_trunks_hit": float(np.sum(n_ret > 0)) / n,
        "window_trunks_min_points_converted": float(np.sum(n_ret >= mp)) / n,
        "window_trunks_40_returns": float(np.sum(n_ret >= PAPER_MIN_POINTS)) / n,
        "window_max_returns": float(n_ret.max()),
        "detections_as_published": len(published) / n,
        "detections_converted": len(converted) / n,
    }


def tune_counts(drives: list[tuple[str, Any, Any, Any, int]]) -> dict[str, Any]:
    """Choose the recognition count of each detection source (:data:`COUNT_GRID`) by the mean
    loop-closure error over held-out ``drives`` (``(name, run, fused, truth, seed)``)."""
    from _visual_lidar2023_diagnostics import true_displacement as disp
    from stemmap.eval.trajectory import loop_closure_error

    errs: dict[str, list[float]] = {"fused": []}
    frames: dict[str, list[float]] = {}
    for _name, run, fused, truth, seed in drives:
        errs["fused"].append(loop_closure_error(fused.trajectory, disp(truth, fused.trajectory)))
        for src in SOURCES.values():
            obs = tree_observations(run, src, seed)
            frames.setdefault(src, []).append(detection_stats(run, obs)["median_frames_per_tree"])
            for c in COUNT_GRID:
                tr, _ = tree_db_trajectory(fused, obs, run.scans.times, truth.poses[0], c)
                errs.setdefault(f"{src}/{c}", []).append(loop_closure_error(tr, disp(truth, tr)))
    mean = {k: float(np.mean(v)) for k, v in errs.items()}
    best = {
        src: min(COUNT_GRID, key=lambda c, s=src: (mean[f"{s}/{c}"], -c))
        for src in SOURCES.values()
    }
    return {
        "drives": [d[0] for d in drives],
        "loop_closure_error_m": mean,
        "per_drive": errs,
        "median_frames_per_tree": frames,
        "best_count": best,
    }
