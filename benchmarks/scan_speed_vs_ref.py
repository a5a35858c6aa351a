"""The ``stemmap`` preset's 361-beam detection speed, this checkout against another checkout of
stemmap (e.g. main's worktree), in one process (issue 11's speed rule: a ratio within one run,
never a single wall-clock number).

Both packages are imported in turn under the name ``stemmap`` (the modules of the first are
dropped from ``sys.modules`` before the second is imported; each detector keeps the functions
it was built with), then timed alternately on the same batch: ``scan_detection.py``'s 10 000
tiled scans of the seed-1 drive, ``--rounds`` rounds of best-of-3 process-CPU times. Reports
scans per CPU second, the ratio of this checkout (``branch``) and of this checkout with
``--set`` (``branch+set``) to the reference per round, and the detections of each (equal
detections: the same output).

Usage::

    python benchmarks/scan_speed_vs_ref.py --ref ../../main
    python benchmarks/scan_speed_vs_ref.py --ref ../../main --set '{"scan_noise_batch": 2.5}'

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "src"


def _import_from(src: Path) -> tuple[ModuleType, ModuleType]:
    """``stemmap.scan.detect`` and ``stemmap.types`` of the checkout whose ``src`` is ``src``."""
    for name in [k for k in sys.modules if k == "stemmap" or k.startswith("stemmap.")]:
        del sys.modules[name]
    sys.path.insert(0, str(src))
    try:
        import stemmap.scan.detect as detect
        import stemmap.types as types
    finally:
        sys.path.remove(str(src))
    if not Path(detect.__file__).resolve().is_relative_to(src.resolve()):
        raise RuntimeError(f"imported {detect.__file__}, not from {src}")
    return detect, types


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", type=Path, required=True, help="the other checkout (its root)")
    ap.add_argument("--set", type=json.loads, default={}, help="overrides for branch+set")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--batch", type=int, default=10000, help="scans in the speed batch")
    args = ap.parse_args(argv)
    # the batch, drawn with this checkout's simulator
    _import_from(SRC)
    sys.path.insert(0, str(SRC))
    try:
        from scan_detection import _batch_of, make_run

        big = _batch_of(make_run(400, 1), args.batch)
    finally:
        sys.path.remove(str(SRC))
    arrays = (big.ranges, big.times, big.angle_min, big.angle_increment)
    limits = (big.range_min, big.range_max)
    dets: dict[str, tuple[Any, Any, int]] = {}
    for name, src, overrides in (
        ("ref", args.ref / "src", {}),
        ("branch", SRC, {}),
        ("branch+set", SRC, args.set),
    ):
        detect, types = _import_from(src)
        det = detect.ScanTrunkDetector(detect.DetectorConfig.preset("stemmap", **overrides))
        batch = types.ScanBatch(*arrays, *limits)
        dets[name] = (det, batch, len(det.detect_batch(batch)))  # JIT warm-up
    rates: dict[str, list[float]] = {k: [] for k in dets}
    load_before = os.getloadavg()[0]
    for _ in range(args.rounds):
        for name, (det, batch, _) in dets.items():
            best = np.inf
            for _ in range(3):
                c0 = time.process_time()
                det.detect_batch(batch)
                best = min(best, time.process_time() - c0)
            rates[name].append(args.batch / best)
    ratio = [b / r for b, r in zip(rates["branch"], rates["ref"], strict=True)]
    ratio_set = [b / r for b, r in zip(rates["branch+set"], rates["ref"], strict=True)]
    print(
        json.dumps(
            {
                "benchmark": "scan_speed_vs_ref",
                "ref": str(args.ref),
                "set": args.set,
                "batch_scans": args.batch,
                "detections": {k: v[2] for k, v in dets.items()},
                "scans_per_cpu_s": {k: [round(x) for x in v] for k, v in rates.items()},
                "ratio_branch_to_ref": [round(x, 3) for x in ratio],
                "median_ratio": round(float(np.median(ratio)), 3),
                "ratio_set_to_ref": [round(x, 3) for x in ratio_set],
                "median_ratio_set": round(float(np.median(ratio_set)), 3),
                "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
