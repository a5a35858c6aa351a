"""Speed of the step split on the compiled path: the ``stemmap`` preset (the step split on,
``step_split`` with ``step_noise_pool="batch"``: grid 59, the default since Dec 5) against the
same preset without it (``step_split=False``), and the preset on the numpy path, in one process
(issue 11's speed rule: ratios within one run, never a single wall-clock number). Until Dec 5
the script compared grid 59 with the default of the time (grid 36); after the flip both were
the same setting, so it compares the default with the default minus the step split.

The batch is ``scan_detection.py``'s: the seed-1 400-scan drive (361-beam scans) tiled to
``--batch`` scans; ``--rounds`` rounds of best-of-3 process-CPU times, the three detectors
alternating in each round. The numpy path runs a tenth of the batch (it is ~3-4x slower; scans
per CPU second are per scan either way). Reports scans per CPU second per round, the ratio of
each to the compiled preset without the step split (``default_compiled``'s is the cost of the
step split), and how the compiled and numpy paths' detections differ for both settings (the
largest absolute difference per output column: the arc extent, width and quality columns
differ by round-off).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/step_split_speed.py

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import os
from typing import Any

import numpy as np

from _scan_sim import make_run
from scan_detection import _batch_of, timed_both
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.types import ScanBatch

#: What the default's step split is made of (benchmarks/_loo_grid.py ``_STEP_BATCH_59``); the
#: comparison is the preset with ``step_split=False`` (``step_noise_pool`` only acts with it).
STEP_SPLIT: dict[str, Any] = {"step_split": True, "step_noise_pool": "batch"}


def _numpy(det: ScanTrunkDetector, b: ScanBatch) -> Any:
    return det._run_numpy(
        b.ranges, b.times, b.angle_min, b.angle_increment, b.range_min, b.range_max, b.frame,
        None, None,
    )  # fmt: skip


#: The output columns compared between the two paths.
_FIELDS = ("index", "n_points", "centers", "radii", "covs", "arc_deg", "widths", "quality")


def _paths(det: ScanTrunkDetector, b: ScanBatch) -> dict[str, Any]:
    """Detections of ``det`` on ``b`` by both paths and the largest absolute difference of
    each output column (None: the detections differ in number)."""
    fast, ref = det.detect_batch(b), _numpy(det, b)
    out: dict[str, Any] = {"detections": [len(fast), len(ref)]}
    if len(fast) == len(ref):
        for f in _FIELDS:
            d = np.abs(np.asarray(getattr(fast, f), float) - np.asarray(getattr(ref, f), float))
            out[f] = float(d.max()) if d.size else 0.0
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=10000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    run = make_run(400, args.seed)
    big = _batch_of(run, args.batch)
    small = _batch_of(run, max(args.batch // 10, 400))
    default = ScanTrunkDetector("stemmap")
    cfg = default.config
    if any(getattr(cfg, k) != v for k, v in STEP_SPLIT.items()):
        raise SystemExit(f"the stemmap preset no longer has the step split {STEP_SPLIT}")
    no_split = ScanTrunkDetector(DetectorConfig.preset("stemmap", step_split=False))
    assert default._compiled(None, None) and no_split._compiled(None, None)
    paths = {k: _paths(d, small) for k, d in (("default", default), ("no_step_split", no_split))}
    runs = {
        "no_step_split_compiled": (lambda: no_split.detect_batch(big), args.batch),
        "default_compiled": (lambda: default.detect_batch(big), args.batch),
        "default_numpy": (lambda: _numpy(default, small), small.ranges.shape[0]),
    }
    load_before = os.getloadavg()[0]
    sps: dict[str, list[int]] = {k: [] for k in runs}
    for _ in range(args.rounds):
        for name, (fn, n) in runs.items():
            _, cpu = timed_both(fn, 3)
            sps[name].append(round(n / cpu))
    base = np.array(sps["no_step_split_compiled"], dtype=float)
    out = {
        "benchmark": "step_split_speed",
        "batch_scans": args.batch,
        "numpy_batch_scans": small.ranges.shape[0],
        "beams": big.ranges.shape[1],
        "default": {"preset": "stemmap", **STEP_SPLIT},
        "no_step_split": {"preset": "stemmap", "step_split": False},
        "scans_per_cpu_second": sps,
        "ratio_to_no_step_split_compiled": {
            k: [round(v, 3) for v in (np.array(sps[k]) / base).tolist()] for k in sps
        },
        "compiled_vs_numpy_on_the_numpy_batch": paths,
        "load_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
