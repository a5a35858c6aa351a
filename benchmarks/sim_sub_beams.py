"""Cost of the simulator's sub-beam count (docs/algorithms/sim-eval.md, "Mixed pixels: one
footprint model (Dec 5)").

    python benchmarks/sim_sub_beams.py [--poses 2000] [--rounds 3] [--k 5 15 25 35]

:func:`stemmap.sim.simulate_scans` with the ``sick_lms`` preset (30 m) and ``K`` sub-beams on
the stand of ``benchmarks/_scan_sim.py`` (seed 1; 90 trees and its clutter), from random poses
inside it. Process-CPU time, the counts alternating within each round, best of the rounds per
count; prints one JSON object with scans per CPU second and the time ratio to the first count.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from _scan_sim import SCENARIO
from stemmap.sim import stand_from_spec
from stemmap.sim.scanner import scanner_preset, simulate_scans


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--k", type=int, nargs="+", default=[5, 15, 25, 35])
    args = ap.parse_args(argv)
    s = SCENARIO
    stand = stand_from_spec(s["stand"], s["clutter"], rng=np.random.default_rng(1))
    pr = np.random.default_rng(2)
    n = args.poses
    lo, hi = 5.0, float(s["stand"]["size_m"][0]) - 5.0
    poses = np.column_stack((pr.uniform(lo, hi, n), pr.uniform(lo, hi, n), pr.uniform(-3, 3, n)))
    models = {k: scanner_preset("sick_lms", range_max=30.0, sub_beams=k) for k in args.k}
    for m in models.values():  # compile
        simulate_scans(stand, poses[:10], m, rng=0)
    cpu: dict[int, list[float]] = {k: [] for k in args.k}
    load0 = os.getloadavg()[0]
    for _ in range(args.rounds):
        for k, m in models.items():
            t = time.process_time()
            simulate_scans(stand, poses, m, rng=0)
            cpu[k].append(time.process_time() - t)
    best0 = min(cpu[args.k[0]])
    out = {
        "benchmark": "sim_sub_beams",
        "poses": n,
        "rounds": args.rounds,
        "load_average_1min": [round(load0, 2), round(os.getloadavg()[0], 2)],
        "sub_beams": {
            str(k): {
                "best_cpu_s": round(min(v), 3),
                "scans_per_cpu_s": round(n / min(v)),
                "time_ratio": round(min(v) / best0, 2),
            }
            for k, v in cpu.items()
        },
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
