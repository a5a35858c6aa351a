"""The outline floor each real-geometry batch reads (issue 11, Dec 6; ``outline_floor_points``,
docs/algorithms/scan-detection.md "The outline floor read from the batch").

For every slice x scanner configuration of the real-geometry benchmark (the batches
``real_geometry.py`` scores: ``--vantage`` scans from the same vantage points, seeds and return
threshold), the outline term, the pooled interior residual scale and the batch's measured range
noise that :meth:`~stemmap.scan.detect.ScanTrunkDetector.outline_estimate` reads, and the
floors every scan then takes (:func:`stemmap.scan._outline_floor.scan_floors`), in mm; NaN where
the batch has no estimate (every scan keeps ``sigma``). Prints one JSON object.

Usage::

    python benchmarks/outline_floor.py --set '<grid json>' [--points 10] [--only fortls_slice]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from _real_scanning import ReturnRule, matched, scene_batches
from stemmap.datasets import find_datasets_dir
from stemmap.scan._outline_floor import outline_floor_on, scan_floors
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector


def _mm(v: float) -> float | None:
    return None if not math.isfinite(v) else round(1000.0 * v, 2)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", default="{}", help="overrides of the stemmap preset (JSON)")
    ap.add_argument("--points", type=int, default=10, help="outline_floor_points")
    ap.add_argument("--only", nargs="*", default=None, help="slices (default: all)")
    ap.add_argument("--vantage", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hit-fraction", type=float, default=0.3)
    args = ap.parse_args(argv)
    cfg = DetectorConfig.preset(
        "stemmap", **{**json.loads(args.set), "outline_floor_points": args.points}
    )
    rule = ReturnRule(min_hit_fraction=args.hit_fraction)
    out: dict[str, Any] = {}
    for sc in scene_batches(
        find_datasets_dir(), args.vantage, args.seed, return_rule=rule, names=args.only
    ):
        det = ScanTrunkDetector(matched(cfg, sc.model, sc.res))
        b = sc.batch
        if not outline_floor_on(det.config):
            continue  # first-echo configurations: fit_noise_floor's own floor
        outline, pooled, noise, scan_noise, n = det.outline_estimate(
            b.ranges, b.angle_min, b.angle_increment, b.range_min, b.range_max
        )
        floors = scan_floors(det.config, outline, noise, scan_noise, n)
        out.setdefault(sc.sl.name, {})[sc.config] = {
            "outline_mm": _mm(outline),
            "pooled_mm": _mm(pooled),
            "batch_noise_mm": _mm(noise),
            "floor_mm_median": _mm(float(np.median(floors))),
            "floor_mm_min": _mm(float(floors.min())),
            "floor_mm_max": _mm(float(floors.max())),
        }
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
