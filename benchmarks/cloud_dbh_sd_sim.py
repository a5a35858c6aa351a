"""Benchmark: the stated cloud DBH std on the simulator's clouds (a check, not a tuning).

The stands of ``cloud_stems.py`` (30 trees on 25 x 25 m, shrubs, low branches, slope, lean;
one terrestrial scan at the centre, nine stations, a 16-beam mobile pass), seeds 1-3, preset
``ours`` with ``StemConfig.dbh_sd_scatter`` = each k of ``--k``: per detected stem matched to a
simulated tree (0.5 m gate), ``z = (DBH - true DBH) / diameter_std``; per scenario and k, n,
median |z| (0.674 calibrated) and the fractions within 1 and 2 sd. The simulator's stems are
circles with point noise (no bark, no out-of-round section), so the section term has little
to read there.

Prints ONE JSON object. Usage: python benchmarks/cloud_dbh_sd_sim.py [--k 0 1] [--seeds 1 2 3]
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from typing import Any

import numpy as np

from cloud_stems import GATE, TLS_MULTI_POSITIONS
from stemmap.cloud.stems import StemConfig, detect_stems
from stemmap.eval.matching import match_points
from stemmap.sim.lidar import lidar_preset, random_stand3d, simulate_mobile, simulate_tls


def _cloud(scen: str, seed: int) -> tuple[np.ndarray, Any]:
    stand = random_stand3d(n_trees=30, size=(25.0, 25.0), rng=seed)
    if scen == "terrestrial":
        cl = simulate_tls(stand, [np.array([12.5, 12.5])], lidar_preset("tls"), rng=100 + seed)
        return cl.xyz, stand
    if scen == "terrestrial_multi":
        cl = simulate_tls(stand, TLS_MULTI_POSITIONS, lidar_preset("tls"), rng=300 + seed)
        return cl.xyz, stand
    path = np.column_stack((np.linspace(0.5, 24.5, 60), np.full(60, 12.3)))
    return simulate_mobile(stand, path, lidar_preset("vlp16"), rng=200 + seed).cloud.xyz, stand


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--k", type=float, nargs="+", default=[0.0, 1.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args()
    t0 = time.process_time()
    out: dict[str, Any] = {}
    for scen in ("terrestrial", "terrestrial_multi", "mobile"):
        z: dict[float, list[float]] = {k: [] for k in args.k}
        for seed in args.seeds:
            xyz, stand = _cloud(scen, seed)
            for k in args.k:
                det = detect_stems(xyz, replace(StemConfig(), dbh_sd_scatter=k))
                m = match_points(det.xy, stand.trees_xy, GATE)
                i, j = m.pairs[:, 0], m.pairs[:, 1]
                z[k] += list((det.diameter[i] - stand.dbh[j]) / det.diameter_std[i])
        out[scen] = {}
        for k, v in z.items():
            a = np.abs(np.asarray(v))
            a = a[np.isfinite(a)]
            out[scen][f"k={k}"] = {
                "n": int(a.size),
                "med_abs_z": round(float(np.median(a)), 2),
                "cov1": round(float(np.mean(a <= 1)), 2),
                "cov2": round(float(np.mean(a <= 2)), 2),
            }
    out["cpu_s"] = round(time.process_time() - t0, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
