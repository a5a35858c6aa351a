"""True against estimated range noise of the batch estimate, MAD or biweight (issue 11, Dec 5,
"The batch's noise from few triples").

On the virtual 2D scans of ``benchmarks/real_geometry.py`` (same slices, vantage points, seeds
and noise draws as ``--loo``: :func:`_real_scanning.scene_batches`), per slice and scanner
configuration, the range-noise estimate over every scan's interior triples (what
``fit_noise_floor``, ``step_noise_pool="batch"`` and ``scan_noise_batch`` give a scan without
an estimate of its own; :func:`stemmap.scan.plausibility.scan_noise` with ``batch_min=0``,
less the preset's 6 mm surface share) with each statistic of ``batch_noise_scale``:

- ``triples``: the interior triples of the batch (20 scans);
- ``mad_cm`` / ``biweight_cm``: the estimate on the benchmark's own noise draw;
- ``redraw_mad_cm`` / ``redraw_biweight_cm`` (``--redraws K`` > 0): median and 5-95 % over K
  fresh Gaussian draws of the configuration's noise added to the same noise-free scans (the
  configuration's 0 cm ranges), i.e. the estimator's sampling spread at that geometry.

The true noise is the benchmark's added Gaussian range noise (0 / 1 / 3 cm); the no-noise rows
read the slices' own shape, bark and TLS noise.

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/batch_noise_scale.py --vantage 20 --redraws 200

One JSON object on stdout (``--table``: a markdown table instead).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _real_scanning import ANY_HIT, ReturnRule, add_hit_fraction, scene_batches
from stemmap.scan.config import DetectorConfig
from stemmap.scan.plausibility import (
    SCAN_NOISE_MIN_TRIPLES,
    _noise_estimate,
    interior_triples,
)

SCALES = ("mad", "biweight")


def batch_estimate(r: np.ndarray, cfg: DetectorConfig, scale: str) -> float | None:
    """The batch's estimate of the gated ranges ``r`` (S, N), metres, under
    :func:`~stemmap.scan.plausibility.scan_noise`'s two rules (None: refused)."""
    vals, runs = interior_triples(r, cfg.scan_noise_jump)
    v = np.concatenate(vals)
    if v.size < SCAN_NOISE_MIN_TRIPLES or 2 * max(runs) > v.size:
        return None
    return _noise_estimate(v, cfg.scan_noise_surface, scale)


def pct(x: list[float]) -> list[float] | None:
    """Median, 5 % and 95 % of ``x``, cm (None when empty)."""
    a = np.asarray([v for v in x if v is not None], dtype=float)
    if a.size == 0:
        return None
    return [round(float(v), 2) for v in 100.0 * np.percentile(a, [50, 5, 95])]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--vantage", type=int, default=20, help="vantage points per dataset")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--redraws", type=int, default=0, help="fresh noise draws per row")
    ap.add_argument("--table", action="store_true", help="print a markdown table")
    add_hit_fraction(ap, ANY_HIT)
    args = ap.parse_args(argv)
    ddir = require_datasets_dir(args.datasets)
    cfg = DetectorConfig.preset("stemmap")
    lo, hi = cfg.range_min or 0.0, cfg.range_max or np.inf
    t0 = time.perf_counter()
    rng = np.random.default_rng(12345)
    clean: dict[tuple[str, str, float], np.ndarray] = {}
    rows: list[dict[str, Any]] = []
    for sc in scene_batches(
        ddir, args.vantage, args.seed, return_rule=ReturnRule(args.hit_fraction)
    ):
        r = sc.batch.ranges
        gate = (r > lo) & (r < hi)
        g = np.where(gate, r, np.nan)
        key = (sc.sl.name, sc.model, sc.res)
        if sc.noise == 0.0:
            clean[key] = sc.batch.ranges
        row: dict[str, Any] = {
            "slice": sc.sl.name,
            "scanner": sc.model,
            "step_deg": sc.res,
            "true_cm": round(100.0 * sc.noise, 2),
            "triples": int(sum(v.size for v in interior_triples(g, cfg.scan_noise_jump)[0])),
        }
        for scale in SCALES:
            e = batch_estimate(g, cfg, scale)
            row[f"{scale}_cm"] = None if e is None else round(100.0 * e, 2)
        if args.redraws > 0 and sc.noise > 0.0:
            r0 = clean[key]
            draws: dict[str, list[float]] = {s: [] for s in SCALES}
            for _ in range(args.redraws):
                rn = r0 + rng.normal(0.0, sc.noise, r0.shape)
                rn = np.where(np.isfinite(r0), np.maximum(rn, 0.05), np.inf)
                gn = np.where((rn > lo) & (rn < hi), rn, np.nan)
                for scale in SCALES:
                    e = batch_estimate(gn, cfg, scale)
                    if e is not None:
                        draws[scale].append(e)
            for scale in SCALES:
                row[f"redraw_{scale}_cm"] = pct(draws[scale])
        rows.append(row)
    if args.table:
        print(
            "| slice | scanner | step | true cm | triples | MAD | biweight "
            "| MAD redrawn: median (5-95 %) | biweight redrawn |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for x in rows:

            def band(v: list[float] | None) -> str:
                return "—" if v is None else f"{v[0]:.2f} ({v[1]:.2f}-{v[2]:.2f})"

            def val(v: float | None) -> str:
                return "—" if v is None else f"{v:.2f}"

            print(
                f"| {x['slice']} | {x['scanner']} | {x['step_deg']:g}° | {x['true_cm']:g} "
                f"| {x['triples']} | {val(x['mad_cm'])} | {val(x['biweight_cm'])} "
                f"| {band(x.get('redraw_mad_cm'))} | {band(x.get('redraw_biweight_cm'))} |"
            )
        return 0
    print(
        json.dumps(
            {
                "benchmark": "batch_noise_scale",
                "scenario": {
                    "vantage_points_per_dataset": args.vantage,
                    "seed": args.seed,
                    "redraws": args.redraws,
                    "jump_m": cfg.scan_noise_jump,
                    "surface_m": cfg.scan_noise_surface,
                },
                "rows": rows,
                "runtime_s": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
