"""Every SLAM back-end on the ``stemmap demo`` scenario: accuracy and covariance calibration.

Issue 14 ("a confidence that means something"): the motion noise handed to the back-ends by
:func:`stemmap.cli._map_problems.sim_problem` comes from the simulator's odometry generator
(:mod:`stemmap.sim.odometry_model`); this measures, per back-end over the demo seeds, what the
back-ends make of it:

* accuracy: path RMSE against the true vehicle path and the loop-closure error
  (:func:`stemmap.cli._map_report.slam_metrics`, as ``stemmap demo`` reports them);
* pose covariance (every reported row after the fixed first one, as
  ``benchmarks/pose_covariance.py --sim`` scores it): the median position ``z² = eᵀ C⁻¹ e``
  (2 dof, calibrated median 1.386), the median heading ``z²`` (1 dof, calibrated 0.455) and
  the pose NEES mean divided by its 3 dof (calibrated 1);
* tree covariance (the map ``stemmap demo`` writes, after
  :func:`stemmap.slam.uncertainty.annotate_uncertainty`; trees matched to the stand within
  1 m): median position ``z²`` (2 dof, calibrated 1.386), mean ``z²`` / 2 (calibrated 1) and
  the share inside the 2-sigma ellipse ``z² < 4`` (calibrated 86.5 %).

``--motion-sigma SPEED,YAW_RATE`` replaces the problem's UnicycleModel sigmas (m/s, rad/s,
one-second white-equivalent) to compare against another noise model on the same runs;
``--legacy-sigmas`` uses the pre-issue-14 formula (per-sample noise / sqrt(rate) + |scale - 1|
+ |bias|). ``--variant NAME`` runs a non-default variant of one back-end instead of
``--backends`` (docs/outputs.md "Pose covariance" table): ``fastslam-unsmoothed``
(``FastSlamConfig(smooth=False)``: the filter's path and the particles' pose spread x
``POSE_COV_INFLATION``) or ``ekf-marginal-map-term`` (the EKF smoother's map term from the
landmarks' marginals, :func:`stemmap.slam._ekf_smooth.map_error_covariance`, as before the
joint term: ``smooth_path`` called without ``map_cov``). ``--sim-hit-fraction Q`` simulates the
drives with a SICK that returns when ``Q`` of its footprint hits (the ``sick_lms`` preset's own
threshold, 0.3 since Dec 6, by default; 0.5 gives the scanner before); ``--detector-set JSON``
overrides fields of the detector's ``stemmap`` preset. The simulator tests
code here; nothing is chosen on it.

Usage: python benchmarks/sim_demo_backends.py [--seeds 0 1 2 3 4 5 6] [--backends isam2 ekf]
       [--variant fastslam-unsmoothed] [--sim-hit-fraction 0.5] [--detector-set JSON]
Prints JSON. The machine is shared; times are not reported.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from typing import Any

import numpy as np

from _pose_cov import BACKENDS, pose_errors  # shared with pose_covariance.py

N_TREES = 120


def _marginal_map_term() -> None:
    """EKF variant ``ekf-marginal-map-term``: the smoother without the filter's joint landmark
    covariance, so it adds the marginal-based map term (``map_error_covariance``)."""
    import stemmap.slam._ekf_compressed as ekf_c
    import stemmap.slam.ekf as ekf

    orig = ekf.smooth_path

    def smooth_path(*args: Any, **kw: Any) -> Any:
        kw.pop("map_cov", None)
        return orig(*args, **kw)

    ekf.smooth_path = smooth_path  # type: ignore[assignment]
    ekf_c.smooth_path = smooth_path  # type: ignore[assignment]


#: ``--variant``: name -> (back-end, its config, setup run before the first run)
VARIANTS: dict[str, tuple[str, dict[str, Any], Any]] = {
    "fastslam-unsmoothed": ("fastslam", {"smooth": False}, None),
    "ekf-marginal-map-term": ("ekf", {}, _marginal_map_term),
    "ekf-noise-from-residuals": ("ekf", {"noise_from_residuals": True}, None),
}


def true_detection_noise(run: Any, problem: Any) -> dict[str, float]:
    """The demo detections' actual noise: each detection against the true stem (nearest within
    1 m of where the true pose puts it) seen from the true pose, measured with the same
    estimator the EKF applies to its residuals (:func:`stemmap.slam.residual_noise.residual_noise`)
    -- what ``noise_from_residuals`` should recover."""
    from scipy.spatial import cKDTree

    from stemmap.slam.residual_noise import detection_residuals, residual_noise

    fr = problem.frames
    frame = np.repeat(np.arange(len(fr.times)), np.diff(fr.ptr))
    poses = run.vehicle_poses.interpolate(fr.times)
    a, b = problem.sensor_offset
    x, y, th = poses[frame].T
    ang = th + fr.bearings
    px = x + a * np.cos(th) - b * np.sin(th) + fr.ranges * np.cos(ang)
    py = y + a * np.sin(th) + b * np.cos(th) + fr.ranges * np.sin(ang)
    trees = np.asarray(run.stand.trees_xy)
    d, j = cKDTree(trees).query(np.column_stack((px, py)))
    ok = d < 1.0
    e = detection_residuals(poses, frame[ok], j[ok], fr.ranges[ok], fr.bearings[ok], trees, (a, b))
    r = residual_noise(frame[ok], j[ok], e)
    return {
        "sigma_range": r.sigma[0],
        "sigma_bearing_deg": math.degrees(r.sigma[1]),
        "sigma_range_long_run": r.sigma_long_run[0],
        "sigma_bearing_long_run_deg": math.degrees(r.sigma_long_run[1]),
    }


def legacy_sigmas(params: dict[str, Any]) -> tuple[float, float]:
    """The motion sigmas ``sim_problem`` used before issue 14 (for the before/after table)."""
    on = params.get("odometry_noise") or {}
    rate = float(params.get("odom_rate_hz", 50.0))
    sv = float(on.get("speed_noise", 0.05)) / math.sqrt(rate) + abs(
        float(on.get("speed_scale", 1.0)) - 1.0
    )
    sw = float(on.get("yaw_rate_noise", 0.0175)) / math.sqrt(rate) + abs(
        float(on.get("yaw_rate_bias", 0.0))
    )
    return max(sv, 1e-3), max(sw, 1e-4)


def one(
    seed: int,
    backend: str,
    sigmas: str | tuple[float, float] | None,
    config: dict[str, Any] | None = None,
    hit_fraction: float | None = None,
    detector_set: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One seed and back-end: accuracy, pose and tree z² arrays. ``hit_fraction``: the
    simulated SICK's return threshold instead of the ``sick_lms`` preset's own;
    ``detector_set``: overrides of the detector's ``stemmap`` preset."""
    from stemmap.cli._demo import DEMO_SCENARIO, _stand_and_run
    from stemmap.cli._map import sim_problem, slam_metrics
    from stemmap.eval.matching import match_points
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.sim.scanner import scanner_preset
    from stemmap.slam.base import make_backend
    from stemmap.slam.uncertainty import annotate_uncertainty

    scanner = None
    if hit_fraction is not None:
        scanner = scanner_preset(DEMO_SCENARIO["scanner"], min_hit_fraction=hit_fraction)
    run = _stand_and_run(seed, N_TREES, scanner=scanner)
    problem, ctx = sim_problem(
        run,
        ScanTrunkDetector(DetectorConfig.preset("stemmap", **(detector_set or {}))).detect_batch(
            run.scans
        ),
        backend=backend,
    )
    if sigmas == "legacy":
        sigmas = legacy_sigmas(run.params)
    if isinstance(sigmas, tuple):
        motion = dataclasses.replace(problem.motion, sigma_speed=sigmas[0], sigma_steer=sigmas[1])
        problem = dataclasses.replace(problem, motion=motion)
    res = make_backend(backend, **(config or {})).run(problem)
    sm, _ = annotate_uncertainty(res, problem)
    m, _, _ = slam_metrics(problem, res, ctx)
    out: dict[str, Any] = {
        "path_rmse_m": m["trajectory_rmse_m"],
        "loop_error_m": m["loop_closure_error_m"],
        "sigmas": (problem.motion.sigma_speed, problem.motion.sigma_steer),
    }
    out |= pose_errors(run, res)
    if backend == "ekf":  # the EKF's residual noise against the detections' actual noise
        st = res.stats
        out["detection_noise"] = {
            "true": true_detection_noise(run, problem),
            "from_residuals": {
                "sigma_range": st.get("residual_sigma_range", math.nan),
                "sigma_bearing_deg": math.degrees(st.get("residual_sigma_bearing", math.nan)),
                "sigma_range_long_run": st.get("residual_sigma_range_long_run", math.nan),
                "sigma_bearing_long_run_deg": math.degrees(
                    st.get("residual_sigma_bearing_long_run", math.nan)
                ),
            },
            "used": [
                st.get("noise_from_residuals_sigma_range", math.nan),
                math.degrees(st.get("noise_from_residuals_sigma_bearing", math.nan)),
            ],
        }
    match = match_points(sm.xy, run.stand.trees_xy, gate=1.0)
    z2 = []
    for i, t in match.pairs:
        c = sm.trees[int(i)].cov
        if np.all(np.isfinite(c)) and np.linalg.det(c) > 0:
            e = sm.xy[int(i)] - run.stand.trees_xy[int(t)]
            z2.append(float(e @ np.linalg.solve(c, e)))
    out["z2_tree"] = np.asarray(z2)
    return out


def _r(x: float) -> float:
    return round(float(x), 3)


def summarise(runs: list[dict[str, Any]], seeds: list[int]) -> dict[str, Any]:
    row: dict[str, Any] = {
        "path_rmse_m_per_seed": dict(zip(seeds, (_r(r["path_rmse_m"]) for r in runs), strict=True)),
        "loop_error_m_per_seed": dict(
            zip(seeds, (_r(r["loop_error_m"]) for r in runs), strict=True)
        ),
    }
    if all("e" in r for r in runs):
        pos = np.concatenate([r["z2_pos"] for r in runs])
        th = np.concatenate([r["z2_th"] for r in runs])
        nees = np.concatenate([r["nees"] for r in runs])
        err = np.concatenate([np.hypot(*r["e"][:, :2].T) for r in runs])
        std = np.concatenate([r["std"] for r in runs])
        row |= {
            "pose_rows": int(pos.size),
            "pose_position_error_median_m": _r(np.median(err)),
            "pose_position_std_median_m": _r(np.median(std)),
            "pose_position_z2_median (calibrated 1.386)": _r(np.median(pos)),
            "pose_share_in_2sigma (calibrated 0.865)": _r(np.mean(pos < 4.0)),
            "pose_heading_z2_median (calibrated 0.455)": _r(np.median(th)),
            "pose_nees_mean (calibrated 3)": _r(np.mean(nees)),
            "pose_nees_mean_per_dof (calibrated 1)": _r(np.mean(nees) / 3.0),
        }
    if all("detection_noise" in r for r in runs):
        row["detection_noise_per_seed"] = {
            s: {
                k: {kk: _r(vv) for kk, vv in v.items()}
                if isinstance(v, dict)
                else [_r(x) for x in v]
                for k, v in r["detection_noise"].items()
            }
            for s, r in zip(seeds, runs, strict=True)
        }
    tz = np.concatenate([r["z2_tree"] for r in runs])
    if tz.size:
        row |= {
            "n_matched_trees": int(tz.size),
            "tree_z2_median (calibrated 1.386)": _r(np.median(tz)),
            "tree_z2_mean_per_dof (calibrated 1)": _r(np.mean(tz) / 2.0),
            "tree_share_in_2sigma (calibrated 0.865)": _r(np.mean(tz < 4.0)),
        }
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(7)))
    ap.add_argument("--backends", nargs="+", default=[b for b in BACKENDS if b != "online"])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--motion-sigma", default=None, help="SPEED,YAW_RATE (m/s, rad/s)")
    g.add_argument("--legacy-sigmas", action="store_true", help="the pre-issue-14 formula")
    ap.add_argument(
        "--variant", choices=sorted(VARIANTS), default=None, help="a non-default back-end variant"
    )
    ap.add_argument(
        "--sim-hit-fraction",
        type=float,
        default=None,
        help="the simulated SICK's return threshold, the share of its footprint that must hit"
        " for a beam to return (default: the sick_lms preset's own; 0.5 before Dec 6)",
    )
    ap.add_argument(
        "--detector-set",
        type=json.loads,
        default=None,
        help="overrides of the detector's stemmap preset, e.g. "
        '\'{"edge_hit_min": 0.25, "edge_hit_max": 0.38, "edge_hit_window": true}\'',
    )
    a = ap.parse_args()
    sig: str | tuple[float, float] | None = None
    if a.legacy_sigmas:
        sig = "legacy"
    elif a.motion_sigma:
        sv, sw = (float(x) for x in a.motion_sigma.split(","))
        sig = (sv, sw)
    out: dict[str, Any] = {"scenario": f"stemmap demo, {N_TREES} trees", "seeds": a.seeds}
    if a.sim_hit_fraction is not None:
        out["sim_hit_fraction"] = a.sim_hit_fraction
    if a.detector_set:
        out["detector_set"] = a.detector_set
    todo: list[tuple[str, str, dict[str, Any]]] = [(b, b, {}) for b in a.backends]
    if a.variant is not None:
        backend, config, setup = VARIANTS[a.variant]
        if setup is not None:
            setup()
        todo = [(a.variant, backend, config)]
    for b, backend, config in todo:
        runs = [one(s, backend, sig, config, a.sim_hit_fraction, a.detector_set) for s in a.seeds]
        sv, sw = runs[0]["sigmas"]  # seed 0's (the horizon follows each run's detections)
        out[b] = {"motion_sigmas_seed0 (m/s, deg/s)": [round(sv, 4), round(math.degrees(sw), 3)]}
        out[b] |= summarise(runs, a.seeds)
        print(json.dumps({b: out[b]}), flush=True, file=sys.stderr)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
