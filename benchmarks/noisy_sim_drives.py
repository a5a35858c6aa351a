"""The simulated drives of the ``real_geometry.py`` admission (``scan_detection.py``'s 400
scans and the ``stemmap demo`` drive) with a noisier scanner (issue 11, Dec 4, "Range noise on
sparse scans"): Gaussian range noise added to every return so that the total is ``--noise``
(the simulator's own is 1 cm), then the ``stemmap`` preset, the preset with ``--set`` and the
preset told the true noise (``sigma`` = ``--noise``, what an operator who knew it would pass
as ``--sigma``), each scored as the admission scores them.

Per seed and drive: the scans without their own range-noise estimate, the median of the scans'
own estimates and the batch's estimate (every scan's interior triples; both less the 6 mm
surface share, cm), and recall / precision / detections of each detector.

Usage::

    python benchmarks/noisy_sim_drives.py --seeds 1 2 3 --set '{"scan_noise_batch": 2.5}'

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

from _scan_sim import _runs, demo_score, score
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import scan_noise
from stemmap.types import ScanBatch

#: The simulator's own range noise (``sick_lms``-class scanner preset of both drives), metres.
SIM_NOISE = 0.01


def noisier(scans: ScanBatch, noise: float, rng: np.random.Generator) -> ScanBatch:
    """``scans`` with Gaussian range noise added to every return for a total of ``noise``
    (kept >= 5 cm; no return stays no return)."""
    extra = math.sqrt(max(noise**2 - SIM_NOISE**2, 0.0))
    r = scans.ranges + rng.normal(0.0, extra, scans.ranges.shape)
    r = np.where(np.isfinite(scans.ranges), np.maximum(r, 0.05), scans.ranges)
    return ScanBatch(
        r, scans.times, scans.angle_min, scans.angle_increment, scans.range_min, scans.range_max
    )


def drive_row(run: Any, scans: ScanBatch, demo: bool, dets: dict[str, Any]) -> dict[str, Any]:
    """The noise estimates and each detector's scores on one drive."""
    r = scans.ranges
    g = np.where((r > scans.range_min) & (r < scans.range_max), r, np.nan)
    cfg = DetectorConfig.preset("stemmap")
    own = scan_noise(g, cfg.scan_noise_jump, cfg.scan_noise_surface)
    every = scan_noise(g, cfg.scan_noise_jump, cfg.scan_noise_surface, batch_min=0.0)
    lack = own == 0
    row: dict[str, Any] = {
        "scans": int(r.shape[0]),
        "without_own_estimate": int(lack.sum()),
        "own_median_cm": round(100 * float(np.median(own[~lack])), 2) if (~lack).any() else None,
        "batch_cm": round(100 * float(every[lack][0]), 2) if lack.any() else None,
    }
    for name, det in dets.items():
        obs = det.detect_batch(scans)
        s: dict[str, Any] = demo_score(obs, run) if demo else score(obs, run)
        row[name] = {"recall": s["recall"], "precision": s["precision"], "detections": len(obs)}
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--noise", type=float, default=0.03, help="total range noise, metres")
    ap.add_argument("--set", type=json.loads, default={}, help="overrides of the stemmap preset")
    args = ap.parse_args(argv)
    dets = {
        "default": ScanTrunkDetector("stemmap"),
        "set": ScanTrunkDetector(DetectorConfig.preset("stemmap", **args.set)),
        "sigma_true": ScanTrunkDetector(DetectorConfig.preset("stemmap", sigma=args.noise)),
    }
    out: dict[str, Any] = {}
    for seed in args.seeds:
        bench, demo = _runs(seed)
        rng = np.random.default_rng(1000 + seed)
        out[str(seed)] = {
            "benchmark": drive_row(bench, noisier(bench.scans, args.noise, rng), False, dets),
            "demo": drive_row(demo, noisier(demo.scans, args.noise, rng), True, dets),
        }
    print(
        json.dumps(
            {
                "benchmark": "noisy_sim_drives",
                "noise_m": args.noise,
                "set": args.set,
                "noise_seed": "1000 + seed",
                "seeds": out,
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
