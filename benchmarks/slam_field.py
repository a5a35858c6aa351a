"""Benchmark: mapping in the field on Victoria Park -- GNSS fusion, relocalisation, online latency.

Prints one JSON object with ``--json``. Parts (``--parts``, default all):

* ``gnss`` (benchmarks/_slam_field_gnss.py): iSAM2 fusing every 10th GPS fix kept by
  ``screen_gps``, scored on the screened fixes NOT fused, without any alignment. Both products
  of ``stemmap map --gnss``: ``gnss_ate_unused_m`` the GNSS-frame track (trajectory_gnss.csv,
  the trajectory in the GNSS frame: the path as the receiver reads it, its Gauss-Markov error
  model estimated from the run's own fused fixes) and ``gnss_path_ate_unused_m`` the
  tree-consistent path (trajectory.csv, the command's default; kernel and sigma by 2-fold CV
  inside the fused fixes: ``gnss_path_cv_ate_unused_m``), each per half, the track also with
  the model of the first half only (``gnss_track_heldout``) and causal;
  ``gnss_never_worse_than_without`` against the no-GNSS path (aligned); where the score comes
  from (``gps_error_floor``, ``gnss_tight_gaussian``, chi2 per dof).
* ``reloc``: map 0-800 s, then relocalise the 800-1549 s session in that map from start
  guesses off by U(-20, 20) m in x and y and U(-30, 30) deg (``--trials``, seed 0); success =
  accepted within 30 s of driving, within 1 m and 2 deg of session 1's end pose carried over
  the gap by odometry (``reloc_success_rate``, ``reloc_time_s_*``). Session 2 is then mapped on
  the prior map (default: each tree held by its own Huber prior on its marginal inflated x4,
  ``Isam2Config.prior_map_inflation``; session 1's odometry calibration carried over) and
  scored on the screened fixes after 800 s with its own alignment, next to the same with the
  trees held jointly by session 1's tree information
  (``session2_prior_map_joint``), on Gaussian per-tree priors without the calibration,
  without the prior map, and to the full single run on the same fixes.
  ``--reloc-per-trial``: session 2 mapped from every accepted trial's pose, joint vs Huber;
  ``--reloc-splits 400,600``: other session pairs (map 0-s, relocalise and map s-1549 s),
  Huber (inflated / not) vs joint vs session 1's saved graph continued (``graph_m``,
  inflation 4; ``graph_f1_m``: 1) vs the full run, the prior's consistency, and the process
  CPU per keyframe step of session 2 for Huber and graph (``*_step``: p50 / p99 / max); per
  split the success rate over ``--trials`` start offsets, false relocalisations, and
  acceptances from guesses whose 30-m search excludes the truth. ``--reloc-splits-only``:
  only those rows (and the full run). The code is in _slam_field_reloc.py.
* ``online``: :class:`stemmap.slam.online.OnlineMapper` replaying the log at sensor rate
  (``latency_ms_p50/p99`` per scan, process CPU time per scan) and a 10x-length replay (the
  log driven ten times, each pass shifted in time and placed 1 km apart so the map keeps
  growing) for the peak RSS (``replay10x_peak_rss_mb``), each in a fresh subprocess.

Usage::

    python benchmarks/slam_field.py --json [--data DIR] [--parts gnss,reloc,online]
        [--trials 20] [--write-gnss-csv FILE] [--reloc-diagnosis] [--reloc-per-trial]
        [--reloc-splits 400,600] [--reloc-splits-only]

``--write-gnss-csv`` writes the fused fixes as the CSV ``stemmap map --gnss`` reads (to repeat
the GNSS part from the command line). The machine is shared and loaded: latency is wall time
per scan (the load average is reported).
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

from _slam_field_gnss import gnss_part
from _slam_field_reloc import _reloc


def _online(data: str | None, passes: int) -> dict[str, Any]:
    from stemmap.datasets.victoria_park import load_victoria_park
    from stemmap.slam.online import replay

    vp = load_victoria_park(data)
    st = replay(vp.problem(), passes=passes)
    lat = np.asarray(st["latency_s"]) * 1e3
    cpu = np.asarray(st["cpu_s"]) * 1e3
    return {
        "cpu_ms_p50": round(float(np.percentile(cpu, 50)), 3),
        "cpu_ms_p99": round(float(np.percentile(cpu, 99)), 3),
        "passes": passes,
        "scans": int(lat.size),
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 3),
        "latency_ms_p99": round(float(np.percentile(lat, 99)), 3),
        "latency_ms_max": round(float(lat.max()), 3),
        "trees": st["trees"],
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "rss_mb_by_pass": st.get("rss_mb_by_pass"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--data", default=None, help="Victoria Park folder (default: shared)")
    ap.add_argument("--parts", default="gnss,reloc,online", help="comma list")
    ap.add_argument("--trials", type=int, default=20, help="relocalisation trials")
    ap.add_argument("--write-gnss-csv", default=None, help="write the fused fixes here")
    ap.add_argument(
        "--reloc-diagnosis",
        action="store_true",
        help="reloc part: also the keyframe-phase spread and the prior-map checks (~10 runs)",
    )
    ap.add_argument(
        "--reloc-per-trial",
        action="store_true",
        help="reloc part: map session 2 from every trial's pose, joint vs Huber prior (~40 runs)",
    )
    ap.add_argument(
        "--reloc-splits",
        default="",
        help="reloc part: also these session splits (s, comma list), the priors of SPLIT_PRIORS",
    )
    ap.add_argument(
        "--reloc-splits-only",
        action="store_true",
        help="reloc part: only the --reloc-splits rows (and the full run they compare to)",
    )
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--passes", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        if args.worker == "gnss":
            r = gnss_part(args.data, args.write_gnss_csv)
        elif args.worker == "reloc":
            splits = [float(x) for x in args.reloc_splits.split(",") if x]
            r = _reloc(
                args.data, args.trials, args.reloc_diagnosis, args.reloc_per_trial, splits,
                splits_only=args.reloc_splits_only,
            )  # fmt: skip
        else:
            r = _online(args.data, args.passes)
        print(json.dumps(r))
        return
    parts = [p for p in args.parts.split(",") if p]
    jobs: list[tuple[str, list[str]]] = []
    for p in parts:
        if p == "online":
            jobs += [("online", ["--passes", "1"]), ("online10x", ["--passes", "10"])]
        else:
            jobs.append((p, []))
    results: dict[str, Any] = {}
    for name, extra in jobs:
        cmd = [sys.executable, __file__, "--worker", name.replace("10x", ""), *extra]
        cmd += ["--trials", str(args.trials)]
        if args.data:
            cmd += ["--data", args.data]
        if args.reloc_diagnosis and name == "reloc":
            cmd += ["--reloc-diagnosis"]
        if args.reloc_per_trial and name == "reloc":
            cmd += ["--reloc-per-trial"]
        if args.reloc_splits and name == "reloc":
            cmd += ["--reloc-splits", args.reloc_splits]
        if args.reloc_splits_only and name == "reloc":
            cmd += ["--reloc-splits-only"]
        if args.write_gnss_csv and name == "gnss":
            cmd += ["--write-gnss-csv", args.write_gnss_csv]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            results[name] = {"error": proc.stderr.strip().splitlines()[-3:] or ["failed"]}
            continue
        results[name] = json.loads(proc.stdout.strip().splitlines()[-1])
        results[name]["wall_s"] = round(time.perf_counter() - t0, 1)
    summary: dict[str, Any] = {}
    for key, part in (
        ("gnss_ate_unused_m", "gnss"),
        ("gnss_path_ate_unused_m", "gnss"),
        ("gnss_never_worse_than_without", "gnss"),
        ("reloc_success_rate", "reloc"),
        ("latency_ms_p99", "online"),
    ):
        summary[key] = results.get(part, {}).get(key)
    summary["replay10x_peak_rss_mb"] = results.get("online10x", {}).get("peak_rss_mb")
    out = {
        "benchmark": "slam_field",
        **summary,
        "results": results,
        "scenario": {
            "dataset": "ACFR Victoria Park (text redistribution), isam2 defaults",
            "cpu_count": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
        },
    }
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        for k, v in out.items():
            print(k, v)


if __name__ == "__main__":
    main()
