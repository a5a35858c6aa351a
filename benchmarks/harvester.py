"""Harvester head targeting benchmark: simulated captures over many random stands and targets.

Prints one JSON object with --json: capture success rate, final position error (against the
true trunk axis), cycles to capture, plan time per cycle, and the joint-limit utilisation reached.
Paper budget (Zheng et al. 2012 §4-5): < 10 ms per control period, < 15 cm accuracy.

    python benchmarks/harvester.py --json [--runs 100]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict

import numpy as np

from stemmap.harvester.capture import (
    PlannerConfig,
    ScannerMount,
    plan_capture,
    warm_up_planner,
)
from stemmap.harvester.kinematics import ForestryCrane, UnreachableError
from stemmap.harvester.simulate import (
    CaptureNoise,
    harvester_stand,
    simulate_capture,
    zheng2012_scanner,
)
from stemmap.types import FloatArray


def isolated_plan_times(
    crane: ForestryCrane, n: int = 200, repeat: int = 5, seed: int = 0
) -> FloatArray:
    """Best-of-``repeat`` wall time (ms) of ``plan_capture`` for ``n`` random reachable targets
    from random joint states: the planner's own cost, with the machine's load spikes removed
    (the per-cycle times of the capture runs include them)."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(crane.lower), np.asarray(crane.upper)
    best: list[float] = []
    while len(best) < n:
        q0 = lo + (hi - lo) * rng.uniform(0.2, 0.8, 5)
        target = np.array([rng.uniform(-9.0, 9.0), rng.uniform(-9.0, 9.0), 0.7])
        qd = rng.normal(0.0, 0.1, 5)
        try:
            plan_capture(crane, q0, target, qdot_now=qd)
        except UnreachableError:
            continue
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            plan_capture(crane, q0, target, qdot_now=qd)
            times.append(time.perf_counter() - t0)
        best.append(1e3 * min(times))
    return np.asarray(best)


def run(n_runs: int = 100, seed: int = 0) -> dict[str, object]:
    crane = ForestryCrane()
    warm_up_planner()  # compile / load the planner's kernel before anything is timed
    scanner = zheng2012_scanner()
    noise = CaptureNoise()
    planner = PlannerConfig()
    mount = ScannerMount()
    rng = np.random.default_rng(seed)
    results = []
    modes = []
    t0 = time.perf_counter()
    for k in range(n_runs):
        stand = harvester_stand(25, rng=rng)
        # half the runs target the nearest trunk, half the trunk nearest a random bearing
        if k % 2 == 0:
            mode, bearing = "nearest", None
        else:
            mode, bearing = "bearing", float(rng.uniform(-2.0, 2.0))
        modes.append(mode)
        res = simulate_capture(
            stand, crane=crane, scanner=scanner, noise=noise, planner=planner, mount=mount,
            mode=mode, bearing=bearing, rng=rng,
        )  # fmt: skip
        results.append(res)
    wall = time.perf_counter() - t0
    iso_ms = isolated_plan_times(crane, seed=seed)
    ok = np.array([r.success for r in results])
    attempted = np.array([r.target_tree >= 0 for r in results])
    err = np.array([r.final_error for r in results if math.isfinite(r.final_error)])
    cycles = np.array([r.cycles for r in results if r.success])
    plan_ms = np.concatenate([np.asarray(r.planning_ms) for r in results if r.planning_ms])
    failures: dict[str, int] = {}
    for r in results:
        if not r.success:
            key = r.reason.split(":")[0][:60]
            failures[key] = failures.get(key, 0) + 1
    return {
        "benchmark": "harvester",
        "runs": n_runs,
        "seed": seed,
        "scenario": {
            "stand": "25 trees in an 11 m disc around the crane, none within 2 m, "
            "DBH ~ N(25, 8) cm",
            "targets": "alternate nearest reachable trunk / trunk nearest a random bearing",
            "scanner": asdict(scanner),
            "mount": asdict(mount),
            "noise": asdict(noise),
            "planner": asdict(planner),
            "crane": asdict(crane),
            "detector": "stemmap.scan.detect default preset",
        },
        "success_rate": float(ok.mean()),
        "success_rate_of_attempted": float(ok[attempted].mean()) if attempted.any() else None,
        "final_error_cm": {
            "mean": float(err.mean() * 100) if err.size else None,
            "p95": float(np.percentile(err, 95) * 100) if err.size else None,
            "max": float(err.max() * 100) if err.size else None,
        },
        "cycles_to_capture": {
            "mean": float(cycles.mean()) if cycles.size else None,
            "max": int(cycles.max()) if cycles.size else None,
        },
        "plan_ms_per_cycle": {
            "median": float(np.median(plan_ms)),
            "p95": float(np.percentile(plan_ms, 95)),
            "max": float(plan_ms.max()),
        },
        "plan_ms_isolated_best_of_5": {
            "median": float(np.median(iso_ms)),
            "p95": float(np.percentile(iso_ms, 95)),
            "max": float(iso_ms.max()),
            "n_plans": int(iso_ms.size),
        },
        "max_joint_velocity_ratio": float(max(r.max_velocity_ratio for r in results)),
        "max_joint_acceleration_ratio": float(max(r.max_acceleration_ratio for r in results)),
        "failures": failures,
        "wall_s": wall,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out = run(args.runs, args.seed)
    print(json.dumps(out, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
