"""Calibration of the per-tree uncertainty of :mod:`stemmap.slam.uncertainty` on the simulator.

For the demo scenario (``stemmap demo``: 120 trees + clutter, a loop, wheel odometry) and
several seeds and back-ends, map, annotate, match the map to the simulator's trees (1 m gate)
and report:

* diameter: z = (mapped DBH - true DBH) / diameter_std over matched trees; a calibrated
  standard error gives median |z| = 0.674 and 68 % of |z| < 1. Also the intra-trunk
  correlation ``rho`` that would make median |z| = 0.674 (solved per run, then pooled);
* position: z^2 = e^T cov^-1 e (chi-square with 2 dof if calibrated: median 1.386, 39 % < 1);
* confidence: per bin of confidence, the share of map trees matched to a real tree; the log
  loss and Brier score of confidence as the probability of that match; how many trees with
  >= 50 detections have confidence < 0.01 (and how many of those are real).

Usage: python benchmarks/uncertainty_calibration.py --seeds 1 2 3 --backends isam2 ekf
Prints JSON. The machine is shared; times are not reported.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math

import numpy as np
from scipy.optimize import brentq

from stemmap.cli._demo import _stand_and_run
from stemmap.cli._map import sim_problem
from stemmap.eval.matching import match_points
from stemmap.scan.detect import ScanTrunkDetector
from stemmap.slam.base import make_backend
from stemmap.slam.uncertainty import DIAMETER_BIAS, DIAMETER_RHO, annotate_uncertainty


def run_one(seed: int, backend: str) -> dict[str, object]:
    run = _stand_and_run(seed, 120)
    obs = ScanTrunkDetector().detect_batch(run.scans)
    problem, _ = sim_problem(run, obs, name=f"seed {seed}")
    result = make_backend(backend).run(problem)
    sm, rep = annotate_uncertainty(result, problem, rho=0.0)
    truth_xy, truth_d = run.stand.trees_xy, run.stand.diameters
    m = match_points(sm.xy, truth_xy, gate=1.0)
    mi, ti = m.pairs[:, 0], m.pairs[:, 1]
    d_err = sm.diameters[mi] - truth_d[ti]
    se = np.array([sm.trees[i].diameter_std for i in mi])
    n = np.array([sm.trees[i].n_obs for i in mi], dtype=float)
    ok = np.isfinite(se) & (se > 0)
    pos_z2 = []
    for i, t in zip(mi, ti, strict=True):
        c = sm.trees[i].cov
        if np.all(np.isfinite(c)) and np.linalg.det(c) > 0:
            e = sm.xy[i] - truth_xy[t]
            pos_z2.append(float(e @ np.linalg.solve(c, e)))
    conf = np.array([t.confidence for t in sm.trees])
    real = np.zeros(len(sm), dtype=bool)
    real[mi] = True
    return {
        "seed": seed,
        "backend": backend,
        "d_err": d_err[ok].tolist(),
        "se0": se[ok].tolist(),
        "n": n[ok].tolist(),
        "dbh": sm.diameters[mi][ok].tolist(),
        "pos_z2": pos_z2,
        "conf": conf.tolist(),
        "real": real.tolist(),
        "n_obs": [t.n_obs for t in sm.trees],
        "report": rep.to_dict(),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--backends", nargs="+", default=["isam2", "ekf", "fastslam"])
    ap.add_argument("--runs-out", help="write the per-run rows to this JSON file")
    ap.add_argument("--runs-in", help="read the per-run rows from this JSON file (no runs)")
    a = ap.parse_args()
    if a.runs_in:
        with open(a.runs_in) as f:
            runs = [r for r in json.load(f) if r["backend"] in a.backends and r["seed"] in a.seeds]
    else:
        runs = [run_one(s, b) for b in a.backends for s in a.seeds]
    if a.runs_out:
        with open(a.runs_out, "w") as f:
            json.dump(runs, f)
    out: dict[str, object] = {"scenario": "stemmap demo, 120 trees", "seeds": a.seeds}
    for b in a.backends:
        rs = [r for r in runs if r["backend"] == b]
        e = np.concatenate([np.asarray(r["d_err"]) for r in rs])
        se0 = np.concatenate([np.asarray(r["se0"]) for r in rs])
        n = np.concatenate([np.asarray(r["n"]) for r in rs])
        spread = se0 * np.sqrt(n)

        def abs_z(rho: float, bias: float = 0.0, e=e, spread=spread, n=n) -> np.ndarray:
            return np.abs(e) / np.sqrt(spread**2 * (1 + (n - 1) * rho) / n + bias**2)

        def med_z(rho: float, bias: float = 0.0) -> float:
            return float(np.median(abs_z(rho, bias)))

        rho = brentq(lambda r: med_z(r) - 0.6745, 0.0, 1.0) if med_z(0.0) > 0.6745 else 0.0
        z2 = np.concatenate([np.asarray(r["pos_z2"]) for r in rs])
        conf = np.concatenate([np.asarray(r["conf"]) for r in rs])
        real = np.concatenate([np.asarray(r["real"]) for r in rs])
        nobs = np.concatenate([np.asarray(r["n_obs"]) for r in rs])
        bins = [0.0, 0.01, 0.5, 0.9, 0.99, 1.0001]
        cal = []
        for lo, hi in itertools.pairwise(bins):
            sel = (conf >= lo) & (conf < hi)
            cal.append(
                {
                    "confidence": f"[{lo}, {min(hi, 1.0)}]",
                    "n_trees": int(sel.sum()),
                    "mean_confidence": float(conf[sel].mean()) if sel.any() else math.nan,
                    "share_real": float(real[sel].mean()) if sel.any() else math.nan,
                }
            )
        out[b] = {
            "default_rho": DIAMETER_RHO,
            "n_matched_trees": int(e.size),
            "dbh_abs_err_median_cm": 100 * float(np.median(np.abs(e))),
            "dbh_se_rho0_median_cm": 100 * float(np.median(se0)),
            "dbh_spread_median_cm": 100 * float(np.median(spread)),
            "median_abs_z_rho0": med_z(0.0),
            "share_abs_z_below_1_rho0": float(np.mean(np.abs(e) / se0 < 1)),
            "rho_for_median_z_0.674": rho,
            "share_abs_z_below_1_at_rho": float(np.mean(abs_z(rho) < 1)),
            "median_abs_z_at_default_rho": med_z(DIAMETER_RHO),
            "share_abs_z_below_1_at_default_rho": float(np.mean(abs_z(DIAMETER_RHO) < 1)),
            "default_bias_m": DIAMETER_BIAS,
            "dbh_se_default_median_cm": 100
            * float(
                np.median(np.sqrt(spread**2 * (1 + (n - 1) * DIAMETER_RHO) / n + DIAMETER_BIAS**2))
            ),
            "median_abs_z_at_default": med_z(DIAMETER_RHO, DIAMETER_BIAS),
            "share_abs_z_below_1_at_default": float(
                np.mean(abs_z(DIAMETER_RHO, DIAMETER_BIAS) < 1)
            ),
            "position_z2_median": float(np.median(z2)) if z2.size else math.nan,
            "position_share_z2_below_1": float(np.mean(z2 < 1)) if z2.size else math.nan,
            "confidence_calibration": cal,
            # proper scores of confidence as the probability of matching a stand tree
            "confidence_log_loss": float(
                -np.mean(np.log(np.clip(np.where(real, conf, 1 - conf), 1e-12, 1.0)))
            ),
            "confidence_brier": float(np.mean((conf - real) ** 2)),
            "real_trees_n_obs_50_confidence_below_0.01": int(
                np.sum(real & (nobs >= 50) & (conf < 0.01))
            ),
            "trees_n_obs_50_confidence_below_0.01": int(np.sum((nobs >= 50) & (conf < 0.01))),
            "mixture": [r["report"] for r in rs],
        }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
