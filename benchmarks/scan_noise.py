"""How well a scan's own range-noise estimate recovers the sensor noise on real geometry
(issue 11, sixth round): :func:`stemmap.scan.plausibility.scan_noise` on the virtual 2D scans
of ``benchmarks/real_geometry.py`` (same slices, vantage points and seeds as ``--loo``).

For every slice with reference trunks, scanner model (nearest-return / SICK-class averaging),
resolution (0.25 / 0.5 / 1 deg) and added Gaussian range noise (0 / 1 / 3 cm): the median and
the 10th / 90th percentiles over the vantage points of the per-scan estimate, cm (raw, and
less the surfaces' share ``--surface`` in quadrature as the detector's ``scan_noise_surface``
does), the number of continuous beam triples it used, and (with noise) the ratio of the raw
median estimate to the added noise. Noise-free scans show what the geometry and the bark
add on their own.

``--background ground`` (fifteenth round) estimates on the scans with the ground and
understory of ``real_geometry.py``'s default (:func:`_real_scanning.scene_scans`), with the
micro-relief ``--relief-std`` / ``--relief-corr`` and the pitch ``--pitch``; ``none`` (the
default here, as the sixth round measured) on the trunks-only scans.

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    python benchmarks/scan_noise.py --vantage 20
    python benchmarks/scan_noise.py --jump 0.1
    python benchmarks/scan_noise.py --background ground --relief-std 0.01

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
from _real_scanning import (  # shared with real_geometry.py
    ANY_HIT,
    FULL_SCANNERS,
    MOUNT,
    ReturnRule,
    add_hit_fraction,
    scene_note,
    slice_scan_batches,
)
from stemmap.eval.scan_background import RELIEF_CORR, RELIEF_STD, Mount
from stemmap.scan.plausibility import scan_noise


def _triples(r: np.ndarray, jump: float) -> np.ndarray:
    """Continuous beam triples per scan (the estimate's sample size)."""
    a, b, c = r[:, :-2], r[:, 1:-1], r[:, 2:]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(c)
        ok &= (np.abs(b - a) <= jump) & (np.abs(c - b) <= jump)
    out: np.ndarray = ok.sum(axis=1)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--vantage", type=int, default=20, help="vantage points per dataset")
    ap.add_argument("--jump", type=float, default=0.2, help="continuity step, metres")
    ap.add_argument("--surface", type=float, default=0.01, help="surface share, metres")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--background", choices=("none", "ground"), default="none")
    ap.add_argument("--relief-std", type=float, default=RELIEF_STD, help="metres")
    ap.add_argument("--relief-corr", type=float, default=RELIEF_CORR, help="metres")
    ap.add_argument("--pitch", type=float, default=MOUNT.pitch_deg, help="degrees down")
    add_hit_fraction(ap, ANY_HIT)
    args = ap.parse_args(argv)
    mount = Mount(MOUNT.height, args.pitch, MOUNT.band)
    ddir = require_datasets_dir(args.datasets)
    t0 = time.perf_counter()
    out: dict[str, Any] = {}
    batches = slice_scan_batches(
        ddir, args.vantage, args.seed, args.background, mount, args.relief_std, args.relief_corr,
        return_rule=ReturnRule(args.hit_fraction),
    )  # fmt: skip
    for name, config, r in batches:
        r = np.where(r < 30.0, r, np.nan)  # the benchmark's range_max
        est = 100.0 * scan_noise(r, args.jump)
        net = 100.0 * scan_noise(r, args.jump, args.surface)
        p10, p50, p90 = np.percentile(est, [10, 50, 90])
        noise = float(config.split("noise")[1].removesuffix("cm")) / 100.0
        out.setdefault(name, {})[config] = {
            "estimate_cm_p10_p50_p90": [round(float(v), 3) for v in (p10, p50, p90)],
            "ratio_median_to_noise": round(float(p50) / (100 * noise), 3) if noise else None,
            "no_estimate_share": round(float(np.mean(est == 0.0)), 3),
            "less_surface_cm_p10_p50_p90": [
                round(float(v), 3) for v in np.percentile(net, [10, 50, 90])
            ],
            "triples_median": int(np.median(_triples(r, args.jump))),
        }
    print(
        json.dumps(
            {
                "benchmark": "scan_noise",
                "scenario": {
                    "vantage_points_per_dataset": args.vantage,
                    "jump_m": args.jump,
                    "surface_m": args.surface,
                    "seed": args.seed,
                    "background": scene_note(args.background),
                    "relief_std_m": args.relief_std if args.background == "ground" else None,
                    "relief_corr_m": args.relief_corr if args.background == "ground" else None,
                    "pitch_deg": args.pitch if args.background == "ground" else None,
                    "scanners_model_res_deg_noise_m": [list(s) for s in FULL_SCANNERS],
                },
                "datasets": out,
                "runtime_s": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
