"""Calibration of the per-tree ``confidence`` on ``stemmap sim scans`` runs (CLI end to end).

The demo scenario of benchmarks/uncertainty_calibration.py hardly has landmarks whose
detection rate departs from the fitted ``p_d(range)``; the default ``stemmap sim scans`` stand
(60 trees of 10-55 cm, 40 m, bushes, branches, rocks, walls) has: thin trunks and clutter.
For each seed and path this simulates a run, maps it with ``stemmap map`` (iSAM2), aligns the
simulator's trees to the map frame (the rigid fit of the true to the estimated trajectory)
and matches map trees to them within 1 m. Prints, per confidence bin, the trees, their mean
confidence and the share matched to a stand tree; the log loss and Brier score; and the
trees with >= 50 detections and confidence < 0.01 (and how many of those are real).

Usage: python benchmarks/confidence_sim_scans.py --seeds 1 2 3 --paths loop lawnmower --work DIR
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree


def _csv(p: Path) -> np.ndarray:
    return np.genfromtxt(p, delimiter=",", names=True)


def _rigid(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising |R a + t - b| (Umeyama without scale)."""
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ma).T @ (b - mb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, d]) @ u.T
    return r, mb - r @ ma


def run_one(work: Path, seed: int, path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = work / f"s{seed}_{path}"
    d.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    cli = [sys.executable, "-m", "stemmap"]
    sim = [*cli, "sim", "scans", "--out", str(d / "run.npz"), "--seed", str(seed)]
    subprocess.run([*sim, "--path", path], check=True, env=env, capture_output=True)
    mp = [*cli, "map", str(d / "run.npz"), "--out", str(d / "map"), "--no-progress"]
    subprocess.run(mp, check=True, env=env, capture_output=True)
    t, tr = _csv(d / "map" / "trees.csv"), _csv(d / "run_trees.csv")
    est, true = _csv(d / "map" / "trajectory.csv"), _csv(d / "run_poses.csv")
    r, off = _rigid(np.c_[true["x"], true["y"]], np.c_[est["x"], est["y"]])
    truth = np.c_[tr["x"], tr["y"]] @ r.T + off
    dist, _ = cKDTree(truth).query(np.c_[t["x"], t["y"]])
    return np.atleast_1d(t["confidence"]), np.atleast_1d(dist < 1.0), np.atleast_1d(t["n_obs"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--paths", nargs="+", default=["loop", "lawnmower"])
    ap.add_argument("--work", type=Path, required=True)
    a = ap.parse_args()
    runs = [run_one(a.work, s, p) for s in a.seeds for p in a.paths]
    conf = np.concatenate([r[0] for r in runs])
    real = np.concatenate([r[1] for r in runs])
    nobs = np.concatenate([r[2] for r in runs])
    cal = []
    for lo, hi in itertools.pairwise([0.0, 0.01, 0.5, 0.9, 0.99, 1.0001]):
        s = (conf >= lo) & (conf < hi)
        cal.append(
            {
                "confidence": f"[{lo}, {min(hi, 1.0)}]",
                "n_trees": int(s.sum()),
                "mean_confidence": float(conf[s].mean()) if s.any() else None,
                "share_real": float(real[s].mean()) if s.any() else None,
            }
        )
    p_obs = np.clip(np.where(real, conf, 1 - conf), 1e-12, 1.0)
    many = (nobs >= 50) & (conf < 0.01)
    out = {
        "scenario": "stemmap sim scans (defaults) + stemmap map (isam2)",
        "seeds": a.seeds,
        "paths": a.paths,
        "n_trees": int(conf.size),
        "n_real": int(real.sum()),
        "confidence_calibration": cal,
        "confidence_log_loss": float(-np.mean(np.log(p_obs))),
        "confidence_brier": float(np.mean((conf - real) ** 2)),
        "trees_n_obs_50_confidence_below_0.01": int(many.sum()),
        "real_trees_n_obs_50_confidence_below_0.01": int((many & real).sum()),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
