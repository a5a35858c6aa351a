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
``range(draws)`` (the draw loop of ``benchmarks/munjer2025.py``, :func:`_munjer_draws.map_draws`,
which scores the first ``--draws`` of the same seeds, default 10, with ``formula``).

Usage: python benchmarks/munjer2025_motion_noise.py [--seeds 0 1 2] [--draws 10]
Prints one JSON object: per method and model, the sigmas and per drive the map position RMSE
and pairwise inter-tree distance error (mean and population sd over the draws).
Same drives as benchmarks/munjer2025.py (same seeds and defaults).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from _munjer_draws import MAX_RANGE, map_draws, spread  # shared with munjer2025
from stemmap.cli._map_problems import sim_motion_sigmas
from stemmap.sim.munjer import simulate_munjer_drive
from stemmap.slam.motion import UnicycleModel
from stemmap.slam.munjer import daim_observations, eb_lidar_observations, ours_lidar_observations
from stemmap.vision.detector import SegmentationDetector


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--draws", type=int, default=10)
    a = ap.parse_args()
    detector = SegmentationDetector()
    out: dict[str, Any] = {}
    for seed in a.seeds:
        d = simulate_munjer_drive(rng=seed)
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
                for _, result, _ in map_draws(d, o, a.draws, (d.controls(), model)):
                    _, mm = d.score(result.stem_map, 1.0)
                    rmse.append(mm.position_rmse)
                    pair.append(mm.pairwise.mean_percent_error)
                r, pp = spread(rmse, "rmse"), spread(pair, "pair")
                row = out.setdefault(name, {}).setdefault(label, {"per_seed": []})
                row["sigma_speed"] = round(model.sigma_speed, 4)
                row["sigma_steer"] = round(model.sigma_steer, 5)
                row["per_seed"].append(
                    {
                        "seed": seed,
                        "position_rmse_mean": round(r["rmse"], 4),
                        "position_rmse_sd": round(r["rmse_sd"], 4),
                        "pairwise_percent_mean": round(pp["pair"], 3),
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
