"""Why trunks are missed on the real-geometry benchmark's noisy first-echo rows (issue 11,
Dec 5, "Noisy first-echo rows" in docs/algorithms/scan-detection.md).

Replays :func:`real_geometry.run_dataset`'s draws exactly (seed 11 + the slice's index, the
vantage points, then one noise draw per scanner row of ``FULL_SCANNERS`` in order), runs
grid 80 of :mod:`_loo_grid` (``--set``: overrides on top of it) on the nearest-return rows of
the given noise levels, and classifies every visible trunk view as
:func:`real_geometry_diagnose.diagnose` does (found, or the test that dropped the candidate
over it, ``merge:`` when that candidate held more than one foreign return), with the noise
estimate of its scan (``scan_own_noise`` 0: the scan has no estimate of its own and the tests
read the configured sigma unless ``scan_noise_batch`` gives it the batch's) and, for a found
view, the fit's own DBH standard deviation ``2 sqrt(C_rr)``.

Return rule: nearest-return scans only. The averaging (SICK-class) scans ``scene_scans``
draws besides are skipped; their rule is passed by name, ``_real_scanning.ANY_HIT`` (any
sub-ray), and changes no draw here (the noise is drawn by the scans' shape).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/noisy_rows_why.py > why80.json
    PYTHONPATH=src:benchmarks python benchmarks/noisy_rows_why.py --set '{"scan_noise_batch": 2.5}'

Per row on stderr: the classes, recall, DBH RMSE and bias at <= 10 m (cm); JSON on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from dataclasses import replace
from typing import Any

import numpy as np

import _loo_grid
from _datasets import require_datasets_dir
from _real_scanning import (
    ANY_HIT,
    FULL_SCANNERS,
    dataset_seed,
    matched,
    scene_scans,
    vantage_points,
)
from real_geometry_diagnose import miss_class, view_row, visible_views
from stemmap.eval.real_slices import load_slice, noisy_batch
from stemmap.scan.detect import ScanTrunkDetector
from stemmap.scan.plausibility import scan_noise

TRAINING = ("fortls_slice", "treels_pine_plot", "treels_pine")


def classify(sl: Any, vp: np.ndarray, hit: np.ndarray, obs: Any, rej: dict) -> list[dict]:
    """One row per visible trunk view (>= 4 own returns, <= 15 m, DBH 10-100 cm)."""
    rej_scan = np.asarray(rej["scan_index"])
    reasons = np.asarray(rej["reason"], dtype=object)
    diam = sl.diameters
    rows = []
    for s, t, rel, rng_t, m, match, own in visible_views(sl, vp, hit, obs, 4):
        err = sd = math.nan
        if match[t] >= 0:
            c = "found"
            err = float(2.0 * obs.radii[m][match[t]] - diam[t]) * 100.0
            sd = 200.0 * math.sqrt(max(float(obs.covs[m][match[t]][2, 2]), 0.0))
        else:
            c = miss_class(rej, rej_scan, reasons, s, rel[t], float(diam[t]), own)[1]
        rows.append(
            {
                **view_row(s, t, float(diam[t]), float(rng_t[t]), own, c),
                "dbh_sd": None if math.isnan(sd) else round(sd, 2),
                "err": None if math.isnan(err) else round(err, 2),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--set", default="{}", help="JSON overrides on top of grid 80")
    ap.add_argument("--only", nargs="*", default=list(TRAINING))
    ap.add_argument("--noise", type=float, nargs="*", default=[0.03], help="metres")
    args = ap.parse_args(argv)
    preset = ScanTrunkDetector.from_preset("stemmap").config
    cfg0 = replace(preset, **{**_loo_grid.LOO_GRID[80], **json.loads(args.set)})
    ddir = require_datasets_dir()
    out: dict[str, Any] = {}
    for name in args.only:
        sl = load_slice(ddir, name, "circle")
        seed = dataset_seed(11, name)
        rng = np.random.default_rng(seed)
        vp = vantage_points(sl, 20, rng)
        for model, res, noise in FULL_SCANNERS:
            ranges0, hit = scene_scans(sl, vp, model, res, "none", seed, return_rule=ANY_HIT)
            batch = noisy_batch(ranges0, res, noise, rng)  # every row draws, as the benchmark
            if model != "nearest" or noise not in args.noise:
                continue
            cfg = matched(cfg0, model, res)
            det = ScanTrunkDetector(cfg)
            obs = det.detect_batch(batch)
            rows = classify(sl, vp, hit, obs, det.rejected(batch))
            own = scan_noise(batch.ranges, cfg.scan_noise_jump, cfg.scan_noise_surface, 0.0)
            for r in rows:
                r["scan_own_noise"] = round(100.0 * float(own[r["scan"]]), 2)
            e = np.array([r["err"] for r in rows if r["err"] is not None and r["range_m"] <= 10])
            cls = Counter(r["class"] for r in rows)
            key = f"{name} {res:g}deg {100 * noise:g}cm"
            out[key] = {
                "classes": dict(cls),
                "recall": round(cls["found"] / max(1, len(rows)), 3),
                "rmse10": round(float(np.sqrt(np.mean(e * e))), 2) if e.size else None,
                "bias10": round(float(np.mean(e)), 2) if e.size else None,
                "rows": rows,
            }
            print(key, dict(cls), out[key]["recall"], out[key]["rmse10"], file=sys.stderr)
    json.dump(out, sys.stdout)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
