"""Why the scan's own range-noise estimate fails on sparse scans, and what a batch or a stream
of scans can estimate instead (issue 11, Dec 4, "Range noise on sparse scans").

On the virtual 2D scans of ``benchmarks/real_geometry.py`` (same slices, vantage points, seeds
and noise draws as ``--loo``: :func:`real_geometry.run_dataset`'s order of random draws), per
slice and scanner configuration:

- ``triples``: interior continuous beam triples per scan (the sample of
  :func:`stemmap.scan.plausibility.scan_noise`; 10th / 50th / 90th percentile) and the share of
  scans with their own estimate (>= ``SCAN_NOISE_MIN_TRIPLES`` triples and no run holding
  more than half of them), refused for too few triples, refused for one dominating run;
- ``own_cm``: the median of the scans' own estimates where they exist (raw, before the
  surface share is taken out; what the detector uses is ``sigma_cm_*`` below);
- ``pool_cm``: the estimate the scans without one share under ``scan_noise_pool`` (raw:
  the union of the sparse scans' triples);
- ``batch_cm``: the estimate over every scan's triples, less the 6 mm surface share (what
  ``scan_noise_batch`` shares where it is at least ``--floor`` x sigma), and its triples;
- ``window_cm``: a stream's running estimate -- the raw statistic over the ``--window``
  scans up to each scan (median and 10-90 % over the scans that have one, and their share);
- ``sigma_cm_default`` / ``sigma_cm_batch``: the sigma the detector's RMS test then reads
  (10 / 50 / 90 % over scans): ``max(1 cm, estimate less the 6 mm surface share)``, and the
  same with ``scan_noise_batch`` = ``--floor``.

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    python benchmarks/scan_noise_sparse.py --vantage 20 > sparse.json

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _real_scanning import ANY_HIT, ReturnRule, add_hit_fraction, slice_scan_batches
from stemmap.scan.config import DetectorConfig
from stemmap.scan.plausibility import SCAN_NOISE_MIN_TRIPLES, interior_triples, scan_noise

_ROUGH = 1.4826 / np.sqrt(6.0)


def mad(v: np.ndarray) -> float:
    """The raw statistic of :func:`scan_noise` (1.4826 MAD / sqrt 6), metres."""
    return float(_ROUGH * np.median(np.abs(v - np.median(v))))


def pct(x: np.ndarray, scale: float = 100.0) -> list[float] | None:
    """10 / 50 / 90 % of ``x`` x ``scale`` (None when empty)."""
    x = x[np.isfinite(x)]
    if x.size == 0:
        return None
    return [round(float(v), 2) for v in scale * np.percentile(x, [10, 50, 90])]


def window_estimates(vals: list[np.ndarray], longest: np.ndarray, w: int) -> np.ndarray:
    """A stream's running estimate: the statistic over the interior triples of the ``w`` scans
    up to each scan, under :func:`scan_noise`'s two rules (NaN where they refuse)."""
    out = np.full(len(vals), np.nan)
    for s in range(len(vals)):
        lo = max(0, s - w + 1)
        v = np.concatenate(vals[lo : s + 1])
        if v.size >= SCAN_NOISE_MIN_TRIPLES and 2 * int(longest[lo : s + 1].max()) <= v.size:
            out[s] = mad(v)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--vantage", type=int, default=20, help="vantage points per dataset")
    ap.add_argument("--window", type=int, default=10, help="stream window, scans")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--floor", type=float, default=2.0, help="scan_noise_batch, x sigma")
    add_hit_fraction(ap, ANY_HIT)
    args = ap.parse_args(argv)
    ddir = require_datasets_dir(args.datasets)
    cfg = DetectorConfig.preset("stemmap")
    jump, surface, sigma = cfg.scan_noise_jump, cfg.scan_noise_surface, cfg.sigma
    t0 = time.perf_counter()
    out: dict[str, Any] = {}
    lo, hi = cfg.range_min or 0.0, cfg.range_max or np.inf
    rule = ReturnRule(args.hit_fraction)
    for name, config, ranges in slice_scan_batches(ddir, args.vantage, args.seed, return_rule=rule):
        r = np.where((ranges > lo) & (ranges < hi), ranges, np.nan)
        vals, runs = interior_triples(r, jump)
        longest = np.array(runs, dtype=int)
        m = np.array([v.size for v in vals])
        few = m < SCAN_NOISE_MIN_TRIPLES
        dominated = ~few & (2 * longest > m)
        own = np.array(
            [
                mad(v) if not (f or d) else np.nan
                for v, f, d in zip(vals, few, dominated, strict=True)
            ]
        )
        det = scan_noise(r, jump, surface)
        lacking = [v for v, f in zip(vals, few, strict=True) if f]
        pool_raw = np.concatenate(lacking) if lacking else np.zeros(0)
        lng = int(longest[few].max()) if few.any() else 0
        pool_ok = pool_raw.size >= SCAN_NOISE_MIN_TRIPLES and 2 * lng <= pool_raw.size
        # the batch's estimate (every scan's triples, less the surface share), unfloored
        every = scan_noise(r, jump, surface, batch_min=0.0)
        batch = float(every[det == 0][0]) if np.any(det == 0) else None
        floored = scan_noise(r, jump, surface, batch_min=args.floor * sigma)
        win = window_estimates(vals, longest, args.window)
        out.setdefault(name, {})[config] = {
            "triples_p10_p50_p90": pct(m.astype(float), 1.0),
            "share_own_few_dominated": [
                round(float(np.mean(~few & ~dominated)), 2),
                round(float(np.mean(few)), 2),
                round(float(np.mean(dominated)), 2),
            ],
            "own_cm": pct(own),
            "pool_cm": round(100 * mad(pool_raw), 2) if pool_ok else None,
            "pool_triples": int(pool_raw.size),
            "batch_cm": None if batch is None else round(100 * batch, 2),
            "batch_triples": int(m.sum()),
            "window_cm": pct(win),
            "window_share": round(float(np.mean(np.isfinite(win))), 2),
            "sigma_cm_default": pct(np.fmax(sigma, det)),
            "sigma_cm_batch": pct(np.fmax(sigma, floored)),
        }
    print(
        json.dumps(
            {
                "benchmark": "scan_noise_sparse",
                "scenario": {
                    "vantage_points_per_dataset": args.vantage,
                    "seed": args.seed,
                    "window_scans": args.window,
                    "batch_floor_sigmas": args.floor,
                    "jump_m": jump,
                    "surface_m": surface,
                    "sigma_m": sigma,
                    "min_triples": SCAN_NOISE_MIN_TRIPLES,
                },
                "datasets": out,
                "runtime_s": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
