"""Benchmark: every SLAM back-end (and dead reckoning) on the full Victoria Park run.

Prints one JSON object with ``--json``. Each back-end runs in a fresh subprocess so that its peak
RSS is its own. Scoring: ATE of the laser position against the GPS fixes kept by
:func:`stemmap.eval.trajectory.screen_gps` (a rule that only looks at GPS and wheel odometry),
after one SE(2) alignment, over every kept fix (no trimming).

Usage::

    python benchmarks/slam_victoria_park.py --json [--data DIR] [--backends isam2,ekf]
        [--t-end SECONDS] [--set KEY=VALUE ...]

``--set`` overrides one setting of the back-ends' config (e.g. ``--set update_every=1`` for
iSAM2; repeatable; values are parsed as JSON, else kept as strings) for A/B runs; the
overrides are echoed in the output. Give one back-end with ``--backends`` when a setting
exists only in its config.

``--backends`` lists registered back-ends; the two dead-reckoning rows always run (naming them
is allowed). Per back-end: ATE (RMSE, p95, max), trees in the map, duplicate pairs < 1 m and their
rate, ``runtime_s`` (wall time), ``cpu_s`` (the worker's CPU time), peak RSS of the worker process
and the 1-min load average at its start and end (compare runs made on a loaded machine by CPU
time or by ratios within one run).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from typing import Any

import numpy as np


def _parse_settings(items: list[str]) -> dict[str, Any]:
    """``["a=1", "b=true", "c=x"]`` -> ``{"a": 1, "b": True, "c": "x"}`` (values as JSON, else
    the raw string)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise SystemExit(f"--set expects KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out


def _score(
    name: str, data: str | None, t_end: float | None, settings: dict[str, Any]
) -> dict[str, Any]:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.eval.trajectory import ate, screen_gps
    from stemmap.slam.base import (
        BACKENDS,
        dead_reckoning,
        duplicate_pairs,
        make_backend,
        sensor_poses,
    )
    from stemmap.slam.motion import preintegrate

    load_start = os.getloadavg()[0]
    vp = load_victoria_park(data)
    if t_end is not None:
        vp = vp.slice(0.0, t_end)
    problem = vp.problem()
    m = vp.model
    pre = preintegrate(m, vp.controls, vp.gps_times)
    sp = sensor_poses(pre.poses, m.sensor_offset)
    screen = screen_gps(
        vp.gps_times, vp.gps_xy, sp[:, :2], np.concatenate(([0.0], np.cumsum(pre.distance)))
    )
    t0 = time.perf_counter()
    c0 = time.process_time()
    if name in ("dead_reckoning", "dead_reckoning_raw"):
        if name == "dead_reckoning_raw":  # the steering signal as recorded (no offset)
            from stemmap.datasets.victoria_park import victoria_park_model

            problem = vp.problem(model=victoria_park_model(steer_offset=0.0))
        traj = dead_reckoning(problem)
        n_trees: int | None = None
        dups: int | None = None
        stats: dict[str, Any] = {}
    else:
        if name not in BACKENDS:
            raise SystemExit(f"unknown back-end {name}")
        res = make_backend(name, **settings).run(problem)
        traj = res.trajectory
        n_trees = len(res.stem_map)
        dups = duplicate_pairs(res.stem_map, 1.0)
        stats = {k: v for k, v in res.stats.items() if k != "backend"}
    runtime = time.perf_counter() - t0
    cpu = time.process_time() - c0
    r = ate(traj, vp.gps_times, vp.gps_xy, offset=m.sensor_offset, keep=screen.keep)
    return {
        "ate_rmse_m": round(r.rmse, 3),
        "ate_p95_m": round(r.p95, 3),
        "ate_max_m": round(r.max, 3),
        "ate_n_fixes": r.n,
        "n_trees": n_trees,
        "duplicates": dups,
        "duplicate_rate": (round(dups / n_trees, 4) if n_trees else None),
        "runtime_s": round(runtime, 2),
        "cpu_s": round(cpu, 2),  # this process's CPU time: steadier than wall on a shared box
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        # the machine is shared: the 1-min load average at the start and end of this worker
        "load_avg_1min": [round(load_start, 2), round(os.getloadavg()[0], 2)],
        "gps_fixes_kept": screen.n_kept,
        "gps_fixes_total": screen.n_total,
        "stats": stats,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--backends", default=None, help="comma list (default: all that import)")
    ap.add_argument("--t-end", type=float, default=None, help="use the run up to this time (s)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a back-end config setting (repeatable; value parsed as JSON)",
    )
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    settings = _parse_settings(args.set)
    if args.worker:
        print(json.dumps(_score(args.worker, args.data, args.t_end, settings)))
        return

    from stemmap.slam.base import BACKENDS

    names = args.backends.split(",") if args.backends else list(BACKENDS)
    available = []
    skipped = {}
    import importlib

    for n in names:
        if n in ("dead_reckoning", "dead_reckoning_raw"):
            continue  # always run (first two rows)
        if n not in BACKENDS:
            skipped[n] = f"unknown back-end (known: {', '.join(BACKENDS)})"
            continue
        mod = BACKENDS[n].split(":")[0]
        try:
            importlib.import_module(mod)
            available.append(n)
        except ImportError as exc:
            skipped[n] = f"not importable: {exc}"
    results: dict[str, Any] = {}
    for n in ["dead_reckoning_raw", "dead_reckoning", *available]:
        cmd = [sys.executable, __file__, "--worker", n]
        if args.data:
            cmd += ["--data", args.data]
        if args.t_end is not None:
            cmd += ["--t-end", str(args.t_end)]
        for item in args.set:
            cmd += ["--set", item]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            results[n] = {"error": proc.stderr.strip().splitlines()[-1:] or ["failed"]}
        else:
            results[n] = json.loads(proc.stdout.strip().splitlines()[-1])
    out = {
        "benchmark": "slam_victoria_park",
        "scenario": {
            "dataset": "ACFR Victoria Park (text redistribution)",
            "t_end_s": args.t_end,
            "vehicle": {"L": 2.83, "H": 0.76, "a": 3.78, "b": 0.50},
            "steer_offset_rad": "0.0055, estimated without GPS (estimate_steer_offset); "
            "dead_reckoning_raw uses 0",
            "ate_point": "laser (a, b) in the vehicle frame",
            "gps_screening": "keep a fix if its displacement from the previous kept fix "
            "matches the wheel odometry within 0.5 m + 10 % of the distance driven",
            "alignment": "one best-fit SE(2) over all kept fixes, no trimming",
            "duplicates": "mapped-tree pairs closer than 1.0 m",
            "backend_defaults": "each back-end's default config",
            "config_overrides": settings,
            "cpu_count": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
        },
        "results": results,
        "skipped": skipped,
    }
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for n, r in results.items():
            print(n, r)


if __name__ == "__main__":
    main()
