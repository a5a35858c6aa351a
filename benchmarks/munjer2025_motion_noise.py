"""FastSLAM's motion noise on the Munjer-like simulated drives: the drive's one-second formula
against the derived white equivalent of its odometry generator, over many particle draws.

``formula``: :meth:`MunjerDrive.motion_model` (white noise averaged over one second plus the
scale error at the drive speed plus the gyro bias). ``derived``:
:func:`stemmap.sim.odometry_model.white_equivalent_sigmas` at the dead-reckoning horizon
(:func:`~stemmap.sim.odometry_model.dead_reckoning_horizon` of each method's detection ranges
within FastSLAM's 12 m), as ``stemmap map --sim`` derives it
(:func:`stemmap.cli._map_problems.sim_motion_sigmas`; FastSLAM does not calibrate the scale
and bias, so it gets the full generator). Each method's detections go through FastSLAM (100
particles) + the Kalman refinement with ``MunjerMapConfig(seed=d)`` for ``d`` in
``range(draws)``; ``benchmarks/munjer2025.py`` runs the single draw ``d = seed``.

Usage: python benchmarks/munjer2025_motion_noise.py [--seeds 0 1 2] [--draws 10]
Prints one JSON object: per method and model, the sigmas and per drive the map position RMSE
and pairwise inter-tree distance error (mean and sd over the draws, and the benchmark's draw).
Same drives as benchmarks/munjer2025.py (same seeds and defaults).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from stemmap.cli._map_problems import sim_motion_sigmas
from stemmap.sim.munjer import simulate_munjer_drive
from stemmap.slam.motion import UnicycleModel
from stemmap.slam.munjer import (
    MunjerMapConfig,
    daim_observations,
    eb_lidar_observations,
    map_munjer,
    munjer_problem,
    ours_lidar_observations,
)
from stemmap.vision.detector import SegmentationDetector

MAX_RANGE = 12.0  # FastSLAM's detection range in benchmarks/munjer2025.py


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--draws", type=int, default=10)
    a = ap.parse_args()
    detector = SegmentationDetector()
    out: dict[str, Any] = {}
    for seed in a.seeds:
        d = simulate_munjer_drive(rng=seed)
        p0 = (float(d.poses[0, 0]), float(d.poses[0, 1]), float(d.poses[0, 2]))
        obs = {
            "eb_lidar": eb_lidar_observations(d.frames, d.times),
            "daim": daim_observations(
                d.images, d.depths, d.camera_frames, d.times, d.rig, detector
            ),
            "ours": ours_lidar_observations(d.frames, d.times),
        }
        for name, o in obs.items():
            ranges = np.hypot(o.centers[:, 0], o.centers[:, 1])
            sv, sw = sim_motion_sigmas(d, ranges[ranges <= MAX_RANGE])
            models = {
                "formula": d.motion_model(),
                "derived": UnicycleModel(sigma_speed=sv, sigma_steer=sw),
            }
            for label, model in models.items():
                rmse, pair = [], []
                for draw in range(a.draws):
                    problem = munjer_problem(
                        o, d.times, d.controls(), model, initial_pose=p0, max_range=MAX_RANGE
                    )
                    sm = map_munjer(problem, MunjerMapConfig(seed=draw)).stem_map
                    _, mm = d.score(sm, 1.0)
                    rmse.append(mm.position_rmse)
                    pair.append(mm.pairwise.mean_percent_error)
                row = out.setdefault(name, {}).setdefault(label, {"per_seed": []})
                row["sigma_speed"] = round(model.sigma_speed, 4)
                row["sigma_steer"] = round(model.sigma_steer, 5)
                row["per_seed"].append(
                    {
                        "seed": seed,
                        "position_rmse_mean": round(float(np.nanmean(rmse)), 4),
                        "position_rmse_sd": round(float(np.nanstd(rmse)), 4),
                        "pairwise_percent_mean": round(float(np.nanmean(pair)), 3),
                        "benchmark_draw_rmse": (
                            round(float(rmse[seed]), 4) if seed < a.draws else None
                        ),
                    }
                )
    for rows in out.values():
        for row in rows.values():
            ps = row["per_seed"]
            row["position_rmse"] = round(float(np.mean([p["position_rmse_mean"] for p in ps])), 3)
            row["pairwise_percent"] = round(
                float(np.mean([p["pairwise_percent_mean"] for p in ps])), 2
            )
    out["draws"] = a.draws
    out["data"] = f"simulated Munjer-like drives, seeds {a.seeds}"
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
