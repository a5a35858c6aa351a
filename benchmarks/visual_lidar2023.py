"""Benchmark: the visual-lidar tree-trunk paper's experiment shape on simulated orchard rows.

The paper (visual-lidar §3.2) drives loops that start and end at the same spot and reports the
loop-closure error (distance between the estimated start and end points): 0.56 m with tree
landmarks vs 0.656 m without on its first run, 0.3-0.5 m on four runs. Here, per loop:

* **visual**: :func:`stemmap.odometry.visual.run_visual_odometry` (stereo KLT + PnP RANSAC) on
  stereo frames rendered by :func:`stemmap.sim.render.render_stereo` from the stand the 2D
  scanner sees (orchard rows, :func:`~stemmap.sim.forest.row_stand`);
* **lidar**: :func:`stemmap.odometry.lidar.lidar_odometry` (KISS-ICP scan-to-map registration,
  2D scans lifted to ``z = 0``) on the simulated 2D scans of the same drive (RPLIDAR model at
  0.25 deg, the scans the tree detections come from), lidar only (no IMU prior); each step's
  registration covariance (divided by the frame interval) is its EKF noise;
* **fused**: the paper's loosely coupled EKF of the two outputs
  (:func:`stemmap.odometry.fusion.fuse_sources`, plain filter, no calibration states, no gate): the
  visual odometry as body-frame velocities (each applied to the interval it was measured over), the
  lidar odometry's scan-to-map poses as absolute pose measurements; both noises from the sources'
  residuals on a calibration drive that is not scored
  (:data:`_visual_lidar2023_noise.CALIBRATION_LOOP`,
  :func:`_visual_lidar2023_noise.calibrate_noise`;
  :data:`_visual_lidar2023_fusion.EKF_LIDAR_SIGMA_FACTOR`);
* **fused_increments**: the loose coupling by relative motion
  (:func:`stemmap.odometry.increments.fuse_increments`): each source's increments with its own error
  model, information-weighted -- the lidar's jitter (at both ends of an increment) and random-walk
  drift per frame fitted on the calibration drive (:func:`_visual_lidar2023_noise.fit_lidar_drift`),
  the VO's per-step noise from its PnP inlier count
  (:func:`_visual_lidar2023_noise.fit_inlier_model`); the VO's variance factor, the lidar model and
  the span chosen on held-out seeds (``--tune 30 40``,
  :data:`_visual_lidar2023_fusion.FUSED_VO_SCALE`,
  :func:`_visual_lidar2023_fusion.increment_sources`). On those it is no better than the lidar alone
  and worse than ``fused`` (docs/algorithms/slam-frontends.md), so ``fused`` stays the EKF;
* **fused_inlier_noise**: ``fused`` with the VO's noise per interval from its PnP inlier count
  (``sigma = c (n / 100) ** -p``, ``c`` and ``p`` fitted on the calibration drive,
  :func:`_visual_lidar2023_noise.fit_inlier_model`; ``visual_odometry_source(inlier_exponent=p)``);
* **fused_drift**: that, and the lidar's poses as jitter about a drifting frame
  (``PoseSource(drift=...)``: the lidar's frame offset is a random walk the VO can correct; jitter
  and drift per frame fitted on the calibration drive,
  :func:`_visual_lidar2023_noise.fit_lidar_drift`). The model the z^2 checks call consistent;
  reported to show what it does;
* **fused_default**: the same with the library's noise (``visual_velocity_sigma``, the lidar's
  registration covariances), what ``stemmap map --motion fused`` uses;
* **fused_velocities**: the same filter with the lidar odometry also differenced into
  velocities (:func:`~stemmap.odometry.fusion.fuse_odometry`). KISS-ICP's pose error is jitter
  about a slowly drifting path, not a sum of independent steps; as white velocity noise its
  steps are over-weighted against the VO. Reported to show it;
* **fused_trees**: the fused odometry as the motion input of the tree database
  (:class:`stemmap.slam.treedb.TreeDbSlam`: the ``visual_lidar`` preset's 0.5 m gate, eq. (2)
  averaging, landmarks at a recognition count, pose corrected by the landmarks, loops closed on
  them), trunk detections by the library's scan detector (preset ``stemmap``, what
  ``stemmap detect`` runs) on the benchmark's own simulated 2D scans;
  **fused_trees_paper**: the same with the paper's filter (preset ``visual_lidar2023``, its
  40-point minimum converted to the 0.25° beams); **fused_trees_oracle**: the detection upper
  bound, with ORACLE detections (every trunk with >= 10 beams on it within 6 m, 3 cm noise).
  Each at its recognition count chosen on held-out drives (``--tune-trees``). Sources, counts
  and why: benchmarks/_visual_lidar2023_trees.py.

Keys: ``loop_closure_error_m.{visual,lidar,fused,fused_increments,fused_inlier_noise,fused_drift,
fused_default,fused_velocities,fused_trees,fused_trees_paper,fused_trees_oracle}`` (mean over
loops),
``ate_m.{...}`` (RMSE of the vehicle position, no alignment: every estimate starts at the true
start pose), ``vo_drift_percent`` (mean translational relative pose error of the visual odometry
over 10 m stretches, % of distance, :func:`stemmap.eval.trajectory.rpe`), ``noise_calibration``,
``fused_better_than_both_loops`` (count of loops where fused beats visual and lidar; the same
for every fused variant under ``better_than_both_loops``), ``fused_better_than_both_seed``
(per seed: fused's mean below both sources' means), ``trees_below_fused_loops`` (per tree
row: loops where it is below ``fused``), ``tree_detections`` (per source, mean over loops),
``loops`` (per-loop table, with diagnostics against the truth: scale errors, yaw-rate
biases, step error stds, and ``nees.*``: mean z^2 per degree of freedom of each source's errors
under the noise the EKF is given, :func:`_visual_lidar2023_diagnostics.consistency`).
Everything is simulated: these numbers test the code; they do not reproduce the paper's field
result.

Usage::

    python benchmarks/visual_lidar2023.py --json [--loops 4] [--seed 0] [--cache DIR]
    python benchmarks/visual_lidar2023.py --json --cache DIR --tune 30 40   # held-out choice
    python benchmarks/visual_lidar2023.py --json --cache DIR --tune-trees 30 40  # tree DB counts

``--seed S`` simulates loop ``k`` with seed ``S + k`` (stand, drive, noise, textures); the
calibration drive always uses its own seed (100).

``--cache`` keeps each loop's visual odometry result (rendering + VO are 95 % of the time);
delete it after changing the renderer or the visual odometry.

Rendering dominates the run time (~0.5 s per 320 x 200 stereo pair on the loaded 2-core
machine; ~10 min for the four loops).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

# this benchmark's parts (helper modules beside it, no command line of their own)
import _visual_lidar2023_trees as trees
from _visual_lidar2023_diagnostics import (
    consistency,
    increment_errors,
    scale_and_yaw_bias,
    true_displacement,
)
from _visual_lidar2023_drive import prepare_loop
from _visual_lidar2023_fusion import (
    FUSED_SPAN,
    TUNE_EKF_FACTORS,
    TUNE_GRID,
    ekf_fused,
    increment_sources,
)
from _visual_lidar2023_noise import CALIBRATION_LOOP, calibrate_noise

#: Loop waypoints around the orchard rows (rows at y = 0, 4, 8; trees at x = 0..18 m).
LOOPS: dict[str, list[tuple[float, float]]] = {
    "around_row_2": [(5, 2), (21, 2), (21, 6), (-3, 6), (-3, 2), (5, 2)],
    "around_rows_2_3": [(5, 2), (21, 2), (21, 10), (-3, 10), (-3, 2), (5, 2)],
    "around_row_3_cw": [(5, 6), (-3, 6), (-3, 10), (21, 10), (21, 6), (5, 6)],
    "around_row_2_twice": [(5.0, 2.0), (21, 2), (21, 6), (-3, 6), (-3, 2)] * 2 + [(5, 2)],
}

#: Fused rows counted against both sources per loop (``<variant>_better_than_both``).
FUSED_VARIANTS = ("fused", "fused_increments", "fused_inlier_noise", "fused_drift")


def tune(seeds: list[int], cache: Path | None) -> dict[str, Any]:
    """Choose the relative-motion fusion's settings (:data:`TUNE_GRID`) by the mean
    loop-closure error over the calibration drive and the loops of ``seeds`` (loop ``k`` of
    seed ``S`` simulated with seed ``S + k``, as the scored runs): the held-out set."""
    from stemmap.eval.trajectory import loop_closure_error
    from stemmap.odometry.increments import fuse_increments

    noise = calibrate_noise(cache)
    drives = [CALIBRATION_LOOP] + [
        (name, wp, s + k) for s in seeds for k, (name, wp) in enumerate(LOOPS.items())
    ]
    errs: dict[str, list[float]] = {"visual": [], "lidar": []}
    wins: dict[str, int] = {}
    names = []
    for name, wp, seed in drives:
        L = prepare_loop(name, wp, seed, cache)
        names.append(f"{name} ({seed})")
        row = {
            k: loop_closure_error(L[k], true_displacement(L["truth"], L[k]))
            for k in ("visual", "lidar")
        }
        for k, v in row.items():
            errs[k].append(v)
        for f in TUNE_EKF_FACTORS:
            ekf = ekf_fused(L, noise, f)[0].trajectory
            e = loop_closure_error(ekf, true_displacement(L["truth"], ekf))
            errs.setdefault(f"ekf/{f:g}", []).append(e)
            wins[f"ekf/{f:g}"] = wins.get(f"ekf/{f:g}", 0) + int(e < min(row.values()))
        for lm in TUNE_GRID["lidar_model"]:
            for a in TUNE_GRID["vo_scale"]:
                srcs = increment_sources(L, noise, lm, a)
                for sp in TUNE_GRID["span"]:
                    tr = fuse_increments(srcs, span=sp, initial_pose=L["truth"].poses[0])[0]
                    e = loop_closure_error(tr, true_displacement(L["truth"], tr))
                    key = f"{lm}/{a:g}/{sp}"
                    errs.setdefault(key, []).append(e)
                    wins[key] = wins.get(key, 0) + int(e < min(row.values()))
    mean = {k: float(np.mean(v)) for k, v in errs.items()}
    best = min(
        (k for k in mean if k in wins and "/" in k and not k.startswith("ekf")),
        key=lambda k: mean[k],
    )
    best_ekf = min((k for k in mean if k.startswith("ekf/")), key=lambda k: mean[k])
    return {
        "drives": names,
        "loop_closure_error_m": mean,
        "better_than_both": wins,
        "best": best,
        "best_ekf": best_ekf,
        "per_drive_best": dict(zip(names, errs[best], strict=True)),
    }


def tune_tree_counts(seeds: list[int], cache: Path | None) -> dict[str, Any]:
    """Choose the tree DB's recognition count per real detector
    (:func:`_visual_lidar2023_trees.tune_counts`) on the calibration drive and the loops of
    ``seeds`` (held out, as :func:`tune`), each with its ``fused`` odometry."""
    noise = calibrate_noise(cache)
    drives = [CALIBRATION_LOOP] + [
        (name, wp, s + k) for s in seeds for k, (name, wp) in enumerate(LOOPS.items())
    ]
    prepared = []
    for name, wp, seed in drives:
        L = prepare_loop(name, wp, seed, cache)
        prepared.append((f"{name} ({seed})", L["run"], ekf_fused(L, noise)[0], L["truth"], seed))
    return trees.tune_counts(prepared)


def run_loop(
    name: str,
    waypoints: list[tuple[float, float]],
    seed: int,
    cache: Path | None = None,
    noise: dict[str, Any] | None = None,
) -> dict[str, Any]:
    from stemmap.eval.trajectory import ate, loop_closure_error, rpe
    from stemmap.odometry.fusion import (
        PoseSource,
        fuse_odometry,
        fuse_sources,
        velocities_from_poses,
    )
    from stemmap.odometry.increments import fuse_increments
    from stemmap.odometry.visual import VoStatus, visual_odometry_source, visual_velocity_sigma
    from stemmap.types import Trajectory

    noise = noise or calibrate_noise(cache)
    L = prepare_loop(name, waypoints, seed, cache)
    run, truth, cam, vo = L["run"], L["truth"], L["cam"], L["vo"]
    visual, lidar, lres = L["visual"], L["lidar"], L["lres"]
    t_render_vo, t_lidar = L["t_render_vo"], L["t_lidar"]
    pose0 = truth.poses[0]
    dt = 1.0 / cam.rate_hz
    # lidar differenced into velocities (fused_velocities): its registration covariance
    # (Gauss-Newton, floored; the first frame's NaN is dropped with the interval that has no
    # increment) divided by the frame interval
    cov = lres.increment_cov[1:]
    held = ~np.isfinite(cov[:, 0, 0])
    ok_cov = np.where(held[:, None, None], np.nan, cov)
    src_lidar = velocities_from_poses(
        lidar,
        sigma_speed=np.sqrt(np.nan_to_num(ok_cov[:, 0, 0], nan=1.0)) / dt,
        sigma_yaw_rate=np.sqrt(np.nan_to_num(ok_cov[:, 2, 2], nan=1.0)) / dt,
        name="lidar odometry",
    ).take(~held)

    def visual_source(sigma_speed: float, sigma_yaw_rate: float) -> Any:
        return visual_odometry_source(
            vo, cam.vehicle_from_camera(), sigma_speed=sigma_speed, sigma_yaw_rate=sigma_yaw_rate
        )

    # the paper's loose coupling with the lidar's poses as absolute measurements (fused)
    fused, src_visual, ps_cal = ekf_fused(L, noise)
    fused_traj = fused.trajectory
    ps = lres.pose_source("lidar odometry")
    # the loose coupling by relative motion (fused_increments): each source's increments with
    # its own error model, information-weighted (stemmap.odometry.increments); settings
    # chosen on held-out seeds (--tune)
    srcs = increment_sources(L, noise)
    fused_inc = fuse_increments(srcs, span=FUSED_SPAN, initial_pose=pose0)[0]
    # fused_inlier_noise: the VO's noise per interval from its PnP inlier count;
    # fused_drift: that, and the lidar's poses as jitter about a drifting frame (its offset
    # a random walk the VO can correct); both fitted on the calibration drive
    src_visual_n = visual_odometry_source(
        vo,
        cam.vehicle_from_camera(),
        sigma_speed=noise["visual_step_sigma_at_100_inliers_m"] / dt,
        sigma_yaw_rate=math.radians(noise["visual_step_sigma_at_100_inliers_deg"]) / dt,
        inlier_exponent=noise["visual_inlier_exponent"],
    )
    jit = np.array(
        [noise["lidar_jitter_sigma_m"]] * 2 + [math.radians(noise["lidar_jitter_sigma_deg"])]
    )
    dq = np.array(
        [noise["lidar_drift_sigma_per_frame_m"]] * 2
        + [math.radians(noise["lidar_drift_sigma_per_frame_deg"])]
    )
    drift = np.repeat(np.diag(dq**2)[None], len(ps), axis=0)
    drift[0] = 0.0
    ps_drift = PoseSource(
        ps.times,
        ps.poses,
        np.where(np.isfinite(ps.covs[:, :1, :1]), np.diag(jit**2)[None], np.nan),
        name="lidar odometry",
        drift=drift,
    )
    fused_inl = fuse_sources([src_visual_n], poses=[ps_cal], initial_pose=pose0, gate_prob=None)
    fused_drift = fuse_sources([src_visual_n], poses=[ps_drift], initial_pose=pose0, gate_prob=None)
    fused_default = fuse_sources(
        [visual_source(*visual_velocity_sigma(dt))], poses=[ps], initial_pose=pose0, gate_prob=None
    )
    fused_vel = fuse_odometry(src_lidar, src_visual, initial_pose=pose0, gate_prob=None)
    # tree database on the fused odometry: real detections (stemmap, the paper's filter) and
    # the oracle upper bound
    tree_est, tree_diag = trees.tree_rows(run, fused, pose0, seed)
    estimates = {
        "visual": visual,
        "lidar": lidar,
        "fused": fused_traj,
        "fused_increments": fused_inc,
        "fused_inlier_noise": fused_inl.trajectory,
        "fused_drift": fused_drift.trajectory,
        "fused_default": fused_default.trajectory,
        "fused_velocities": fused_vel.trajectory,
        **tree_est,
    }
    tp = truth.poses
    lidar_step_err = increment_errors(lidar, truth, 1)

    def true_disp(est: Any) -> tuple[float, float]:
        return true_displacement(truth, est)

    vs, vb = scale_and_yaw_bias(visual, truth)
    ls, lb = scale_and_yaw_bias(lidar, truth)
    row: dict[str, Any] = {
        "loop": name,
        "seed": seed,
        "frames": len(truth),
        "path_length_m": float(np.sum(np.hypot(*np.diff(tp[:, :2], axis=0).T))),
        "true_end_minus_start_m": float(math.hypot(*true_disp(truth))),
        "vo_lost_frames": int(np.sum(~vo.ok)),
        "vo_keyframes": int(np.sum(vo.status == VoStatus.KEYFRAME)),
        "vo_median_inliers": float(np.median(vo.n_inliers[vo.ok])),
        **tree_diag,
        "render_and_vo_s": round(t_render_vo, 1),
        "lidar_odometry_s": round(t_lidar, 1),
        "lidar_held_frames": int(lres.held.sum()),
        "lidar_median_sigma_xy_m": float(np.sqrt(np.nanmedian(cov[:, 0, 0]))),
        # diagnostics against the truth (not used by any estimate)
        "lidar_step_error_std_m": float(np.std(lidar_step_err[:, 0])),
        "lidar_step_error_std_deg": float(np.degrees(np.std(lidar_step_err[:, 2]))),
        "vo_step_error_std_m": float(np.std(increment_errors(visual, truth, 1)[:, 0])),
        "vo_scale_error_percent": vs,
        "lidar_scale_error_percent": ls,
        "vo_yaw_rate_bias_deg_s": vb,
        "lidar_yaw_rate_bias_deg_s": lb,
    }
    for key, est in estimates.items():
        row[f"loop_closure_error_m.{key}"] = loop_closure_error(est, true_disp(est))
        row[f"ate_m.{key}"] = ate(est, truth.times, tp[:, :2], align=False).rmse
    for m in ("loop_closure_error_m", "ate_m"):
        for k in trees.SOURCES:
            # below by more than a micron: a tree DB with no landmark reproduces fused to 1e-13
            row[f"{k}_below_fused.{m}"] = bool(row[f"{m}.{k}"] < row[f"{m}.fused"] - 1e-6)
        for k in FUSED_VARIANTS:
            row[f"{k}_better_than_both.{m}"] = bool(
                row[f"{m}.{k}"] < min(row[f"{m}.visual"], row[f"{m}.lidar"])
            )
    row.update(
        consistency(
            L, noise, src_visual, src_visual_n, {"fused": fused, "fused_drift": fused_drift}
        )
    )
    rp = rpe(visual, Trajectory(truth.times, tp), delta=10.0)
    row["vo_drift_percent"] = 100.0 * rp.trans_mean / 10.0
    row["vo_rot_drift_deg_per_10m"] = rp.rot_rmse_deg
    return row


def _better_than_both_odds(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """What a re-weighting fusion of two independent errors can expect per loop
    (:mod:`stemmap.eval.fusion_odds`): the sources' error ratio ``r`` from the RMS loop-closure
    errors over these loops, ``P`` (2D Monte Carlo) that the fused error is below both on one
    loop, the expected count ``n P`` and the chance ``P ** n`` of every loop."""
    from stemmap.eval.fusion_odds import p_fused_beats_both

    def rms(key: str) -> float:
        return float(np.sqrt(np.mean([r[f"loop_closure_error_m.{key}"] ** 2 for r in rows])))

    v, li = rms("visual"), rms("lidar")
    ratio = max(v, li) / min(v, li)
    p = p_fused_beats_both(ratio, dim=2)
    n = len(rows)
    return {
        "sigma_ratio": ratio,
        "p_per_loop": p,
        "expected_loops": n * p,
        "p_every_loop": p**n,
        "observed_loops": int(sum(r["fused_better_than_both.loop_closure_error_m"] for r in rows)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--loops", type=int, default=len(LOOPS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="folder for the visual odometry results per loop (re-used when present)",
    )
    ap.add_argument(
        "--tune",
        type=int,
        nargs="+",
        default=None,
        metavar="SEED",
        help="only choose the relative-motion fusion's settings on these held-out seeds",
    )
    ap.add_argument(
        "--tune-trees",
        type=int,
        nargs="+",
        default=None,
        metavar="SEED",
        help="only choose the tree DB's recognition counts on these held-out seeds",
    )
    a = ap.parse_args(argv)
    if a.tune:
        print(json.dumps(tune(a.tune, a.cache), indent=None if a.json else 2))
        return 0
    if a.tune_trees:
        print(json.dumps(tune_tree_counts(a.tune_trees, a.cache), indent=None if a.json else 2))
        return 0
    rows = []
    t0 = time.perf_counter()
    noise = calibrate_noise(a.cache)
    for k, (name, wp) in enumerate(list(LOOPS.items())[: a.loops]):
        rows.append(run_loop(name, wp, a.seed + k, a.cache, noise))
        print(json.dumps(rows[-1]), file=sys.stderr)
    keys = (
        "visual",
        "lidar",
        "fused",
        "fused_increments",
        "fused_inlier_noise",
        "fused_drift",
        "fused_default",
        "fused_velocities",
        *trees.SOURCES,
    )
    out: dict[str, Any] = {
        "data": "simulated orchard rows (row_stand 3 x 7, 4 m x 3 m) inside a forest edge "
        "(with_forest_edge), 320x200 stereo at 5 Hz, 1 m/s; lidar = KISS-ICP on the simulated "
        "2D scans (RPLIDAR model, 0.25 deg); tree detections: fused_trees = ScanTrunkDetector "
        "('stemmap') on those scans, fused_trees_paper = preset 'visual_lidar2023' (40 points "
        "at 0.12 deg as 20 at 0.25 deg), fused_trees_oracle = oracle (every trunk with >= 10 beams "
        "within 6 m, 3 cm noise: the detection upper bound)",
        "promote_count": trees.PROMOTE_COUNT,
        "paper": {
            "loop_closure_error_m": {"fused_trees": 0.56, "fused": 0.656},
            "range_m": [0.3, 0.5],
        },
        "loop_closure_error_m": {
            k: float(np.mean([r[f"loop_closure_error_m.{k}"] for r in rows])) for k in keys
        },
        "ate_m": {k: float(np.mean([r[f"ate_m.{k}"] for r in rows])) for k in keys},
        "vo_drift_percent": float(np.mean([r["vo_drift_percent"] for r in rows])),
        "noise_calibration": noise,
        "fused_better_than_both_loops": {
            m: int(sum(r[f"fused_better_than_both.{m}"] for r in rows))
            for m in ("loop_closure_error_m", "ate_m")
        },
        "better_than_both_loops": {
            k: {
                m: int(sum(r[f"{k}_better_than_both.{m}"] for r in rows))
                for m in ("loop_closure_error_m", "ate_m")
            }
            for k in FUSED_VARIANTS
        },
        "fused_better_than_both_seed": {
            m: bool(
                np.mean([r[f"{m}.fused"] for r in rows])
                < min(np.mean([r[f"{m}.{k}"] for r in rows]) for k in ("visual", "lidar"))
            )
            for m in ("loop_closure_error_m", "ate_m")
        },
        "trees_below_fused_loops": {
            k: {
                m: int(sum(r[f"{k}_below_fused.{m}"] for r in rows))
                for m in ("loop_closure_error_m", "ate_m")
            }
            for k in trees.SOURCES
        },
        "tree_detections": {
            k.removeprefix("detections."): float(np.mean([r[k] for r in rows]))
            for k in rows[0]
            if k.startswith("detections.")
        },
        "better_than_both_odds": _better_than_both_odds(rows),
        "loops": rows,
        "wall_s": round(time.perf_counter() - t0, 1),
        "load_average": os.getloadavg()[0],
    }
    print(json.dumps(out, indent=2 if not a.json else None))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
