"""Benchmark: Öhman's ray-cast false-tree removal (Fig. 5) wired into the Forestrix back-end.

Simulated only (Victoria Park has no raw ranges, only ACFR's detections): a loop through a
random stand, raw scans from the simulator's 2D lidar, trunks found by the default scan
detector, plus ``--false`` persistent false echoes per run (branch or bush returns the laser
never sees as a solid trunk: points in free space >= 1 m from any trunk and 2-12 m from the
path, reported as a 12-30 cm "trunk" in every frame that has them within 15 m in front, with
probability 0.6). Forestrix runs twice per seed, ``false_trees="none"`` and ``"rays"`` (the raw
scans passed to ``run``); a map tree within 0.5 m of a true trunk is real, one within 0.5 m of
an injected echo is false.

Usage::

    python benchmarks/forestrix_false_trees.py --json [--seeds 0,1,2] [--false 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from typing import Any

import numpy as np


def _inject(problem: Any, run: Any, n_false: int, rng: np.random.Generator) -> tuple[Any, Any]:
    """``problem`` with persistent false echoes added to its frames; returns (problem, xy)."""
    from stemmap.slam.base import TreeFrames, sensor_poses

    stand = run.stand
    sp = sensor_poses(run.vehicle_poses.poses, problem.sensor_offset)
    fake: list[np.ndarray] = []
    lo, hi = stand.trees_xy.min(axis=0), stand.trees_xy.max(axis=0)
    while len(fake) < n_false:
        p = rng.uniform(lo, hi)
        gap = np.min(np.hypot(*(stand.trees_xy - p).T) - stand.radii)
        dp = np.min(np.hypot(*(sp[:, :2] - p).T))
        if gap >= 1.0 and 2.0 <= dp <= 12.0:
            fake.append(p)
    fxy = np.array(fake)
    fdia = rng.uniform(0.12, 0.30, n_false)
    fr = problem.frames
    ptr, rr, bb, dd = [0], [], [], []
    for f in range(len(fr)):
        r, b, d = fr.frame(f)
        rel = fxy - sp[f, :2]
        rho = np.hypot(rel[:, 0], rel[:, 1])
        phi = np.arctan2(rel[:, 1], rel[:, 0]) - sp[f, 2]
        phi = (phi + np.pi) % (2 * np.pi) - np.pi
        k = (rho <= 15.0) & (np.abs(phi) <= math.radians(80)) & (rng.uniform(size=n_false) < 0.6)
        rr.append(np.concatenate((r, rho[k])))
        bb.append(np.concatenate((b, phi[k])))
        dd.append(np.concatenate((d, fdia[k])))
        ptr.append(ptr[-1] + rr[-1].size)
    frames = TreeFrames(
        fr.times, np.array(ptr), np.concatenate(rr), np.concatenate(bb), np.concatenate(dd)
    )
    return dataclasses.replace(problem, frames=frames), fxy


TOL = 0.05


def _one(seed: int, n_false: int) -> dict[str, Any]:
    from stemmap.cli._map import sim_problem
    from stemmap.eval.matching import match_points
    from stemmap.sim.forest import random_stand
    from stemmap.sim.trajectory import loop_path, simulate_run
    from stemmap.slam.forestrix import ForestrixSlam

    rng = np.random.default_rng(seed)
    stand = random_stand(90, (70.0, 56.0), min_spacing=2.0, rng=rng)
    path = loop_path((35.0, 28.0), (20.0, 13.0), laps=1.2)
    run = simulate_run(stand, path, rate_hz=5.0, corridor_half_width=2.5, rng=seed)
    problem, _ = sim_problem(run)
    problem, fxy = _inject(problem, run, n_false, rng)
    out: dict[str, Any] = {}
    for mode in ("none", "rays"):
        t0 = time.perf_counter()
        res = ForestrixSlam(false_trees=mode, ray_position_tol=TOL).run(problem, scans=run.scans)
        wall = time.perf_counter() - t0
        xy = res.stem_map.xy
        real = match_points(xy, stand.trees_xy, 0.5)
        false = match_points(xy, fxy, 0.5)
        truth = run.vehicle_poses.poses
        err = np.hypot(*(res.trajectory.poses[:, :2] - truth[:, :2]).T)
        out[mode] = {
            "trees": len(res.stem_map),
            "real_trees_mapped": int(real.n_matched),
            "false_trees_mapped": int(false.n_matched),
            "other_unmatched": int(len(res.stem_map) - real.n_matched - false.n_matched),
            "rmse_m": round(float(np.sqrt(np.mean(err**2))), 3),
            "removed": int(res.stats.get("false_trees_removed", 0)),
            "runtime_s": round(wall, 2),
        }
    n, r = out["none"], out["rays"]
    out["false_removed"] = n["false_trees_mapped"] - r["false_trees_mapped"]
    out["real_lost"] = n["real_trees_mapped"] - r["real_trees_mapped"]
    out["other_removed"] = n["other_unmatched"] - r["other_unmatched"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--false", type=int, default=10, help="false echoes injected per run")
    ap.add_argument("--position-tol", type=float, default=0.05, help="ray_position_tol (m)")
    args = ap.parse_args()
    global TOL
    TOL = args.position_tol
    seeds = [int(s) for s in args.seeds.split(",")]
    per = {str(s): _one(s, args.false) for s in seeds}
    tot = {
        k: int(sum(p[k] for p in per.values()))
        for k in ("false_removed", "real_lost", "other_removed")
    }
    tot["false_mapped_before"] = int(sum(p["none"]["false_trees_mapped"] for p in per.values()))
    tot["real_mapped_before"] = int(sum(p["none"]["real_trees_mapped"] for p in per.values()))
    out = {"benchmark": "forestrix_false_trees", "false_per_run": args.false,
           "ray_position_tol": TOL, "seeds": per, "total": tot}  # fmt: skip
    print(json.dumps(out, indent=1) if args.json else out)


if __name__ == "__main__":
    main()
