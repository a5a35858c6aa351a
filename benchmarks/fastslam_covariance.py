"""Why FastSLAM's tree covariance is too small: the measurements of docs/outputs.md
("Calibration", position covariance).

Simulated (the ``stemmap demo`` scenario, one run per seed): FastSLAM's trees matched to the
stand within 3 m -- median position error, median covariance std (sqrt of the mean of the
diagonal), z^2 = e^T cov^-1 e (median and the shares below 1 / 4 / 9: 0.39 / 0.86 / 0.99 for a
calibrated 2D covariance) -- and the dead-reckoning drift the motion model predicts (sigma of
the preintegrated position after 30 / 120 s) against the drift it actually has.

``--vp``: Victoria Park has no per-tree truth; the check there is consistency between
back-ends: trees of two back-ends paired within 2 m, z^2 of their difference with the two
covariances summed (chi-square with 2 dof if both are calibrated).

Usage: python benchmarks/fastslam_covariance.py --seeds 1 2 3 4 5 6 [--vp]
Prints JSON. The machine is shared; times are not reported.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from stemmap.eval.matching import match_points
from stemmap.types import StemMap


def _z2_stats(e: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    z = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e)
    return {
        "z2_median": float(np.median(z)),
        "share_z2_below_1_4_9": [round(float(np.mean(z < q)), 3) for q in (1, 4, 9)],
    }


def _covs(sm: StemMap, idx: np.ndarray) -> np.ndarray:
    return np.array([sm.trees[int(i)].cov for i in idx])


def simulated(seed: int) -> dict[str, Any]:
    from stemmap.cli._demo import _stand_and_run
    from stemmap.cli._map import sim_problem
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.slam.base import dead_reckoning, make_backend
    from stemmap.slam.motion import preintegrate

    run = _stand_and_run(seed, 120)
    problem, _ = sim_problem(run, ScanTrunkDetector().detect_batch(run.scans), name="sim")
    sm = make_backend("fastslam").run(problem).stem_map
    truth = run.stand.trees_xy
    m = match_points(sm.xy, truth, gate=3.0)
    mi, ti = m.pairs[:, 0], m.pairs[:, 1]
    e = sm.xy[mi] - truth[ti]
    cov = _covs(sm, mi)
    t = problem.frames.times
    true_xy = run.vehicle_poses.interpolate(t)[:, :2]
    dr = dead_reckoning(problem).interpolate(t)[:, :2]
    out: dict[str, Any] = {
        "seed": seed,
        "trees_matched": int(mi.size),
        "median_error_m": float(np.median(np.hypot(*e.T))),
        "median_cov_std_m": float(np.median(np.sqrt(0.5 * np.trace(cov, axis1=1, axis2=2)))),
        **_z2_stats(e, cov),
    }
    for span in (30.0, 120.0):
        k = int(np.searchsorted(t, t[0] + span))
        if k >= t.size:
            continue
        pre = preintegrate(problem.motion, problem.controls, [t[0], t[k]], problem.initial_pose)
        out[f"dr_sigma_model_{span:g}s_m"] = float(np.sqrt(np.trace(pre.covs[0][:2, :2])))
        out[f"dr_error_actual_{span:g}s_m"] = float(np.hypot(*(dr[k] - true_xy[k])))
    return out


def victoria_park() -> dict[str, Any]:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.slam.base import make_backend

    problem = load_victoria_park(None).problem()
    maps = {b: make_backend(b).run(problem).stem_map for b in ("fastslam", "isam2", "ekf")}
    out: dict[str, Any] = {b: {"trees": len(sm)} for b, sm in maps.items()}
    for a, b in (("ekf", "isam2"), ("fastslam", "isam2"), ("fastslam", "ekf")):
        m = match_points(maps[a].xy, maps[b].xy, gate=2.0)
        i, j = m.pairs[:, 0], m.pairs[:, 1]
        e = maps[a].xy[i] - maps[b].xy[j]
        out[f"{a}_vs_{b}"] = {
            "pairs": int(i.size),
            "median_difference_m": float(np.median(np.hypot(*e.T))),
            **_z2_stats(e, _covs(maps[a], i) + _covs(maps[b], j)),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--vp", action="store_true", help="also the Victoria Park consistency check")
    a = ap.parse_args()
    out: dict[str, Any] = {"simulated": [simulated(s) for s in a.seeds]}
    if a.vp:
        out["victoria_park"] = victoria_park()
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
