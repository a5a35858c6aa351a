"""Why real trunks are missed or biased: per-trunk diagnosis of the real-geometry benchmark
(issue 11, fifth round).

Same slices, vantage points and seeds as ``benchmarks/real_geometry.py --loo`` (seed 11 +
the dataset's index in :data:`stemmap.eval.real_slices.SLICES`). For one scanner configuration
(default: 0.5 deg nearest-return, no noise) and the ``stemmap`` preset (``--set`` overrides its
fields), every visible trunk of every scan is classified:

- ``found`` / ``found_extra``: detected; ``found_extra`` when the detection holds more than one
  return beyond the trunk's own beams (a neighbour's returns were fitted with it);
- ``merge:<reason>``: missed; the rejected candidate over the trunk holds more than one return
  beyond the trunk's own beams (segmentation merged it with a branch, stem or twig) and was
  dropped by the test ``<reason>`` (:data:`stemmap.scan.plausibility.REASONS`);
- ``split:<reasons>``: missed; several rejected candidates lie over the trunk;
- ``<reason>``: missed; one candidate of the trunk's own returns, dropped by that test;
- ``no_candidate``: missed; no candidate over the trunk.

"Over the trunk": the candidate's mean return lies within its half width (plus the trunk's
angular radius) of the trunk's bearing and within the trunk diameter plus the candidate's
width of its range. Next to it, *perfect segmentation*: the same detector (and the textbook
Kasa detector) on scans that keep only the trunk's own beams (every other beam masked):
what is left when nothing is merged. And per reference trunk its quality: ring RMS, coverage,
sectors filled with the reference circle itself, and the spread of the reference diameter
when each 30-degree sector of the ring is left out in turn (jackknife).

Usage::

    python benchmarks/real_geometry_diagnose.py                    # 0.5 deg nearest, no noise
    python benchmarks/real_geometry_diagnose.py --model averaging --noise 0.01
    python benchmarks/real_geometry_diagnose.py --set '{"arc_refit": true}'

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.datasets import find_datasets_dir
from stemmap.eval.real_slices import (
    SLICES,
    RealSlice,
    load_slice,
    noisy_batch,
    reference_jackknife,
    virtual_scans,
)
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.types import ScanBatch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_geometry import TEXTBOOK, _match, _stats, matched, vantage_points


def _over(rej: dict[str, Any], rows: np.ndarray, rel: np.ndarray, diam: float) -> np.ndarray:
    """Rejected candidates (indices ``rows`` of ``rej``) lying over a trunk at ``rel``."""
    b_t = math.atan2(rel[1], rel[0])
    r_t = math.hypot(rel[0], rel[1])
    half_t = math.asin(min(1.0, 0.5 * diam / r_t))
    br = np.radians(rej["bearing_deg"][rows])
    rr = rej["range"][rows]
    w = rej["width"][rows]
    dang = np.abs(np.angle(np.exp(1j * (br - b_t))))
    ok = dang <= 0.5 * w / np.maximum(rr, 1e-9) + half_t
    ok &= np.abs(rr - r_t) <= diam + w
    return rows[ok]


def diagnose(
    sl: RealSlice,
    cfg: DetectorConfig,
    model: str,
    res: float,
    noise: float,
    seed: int,
    n_vantage: int,
    min_returns: int,
) -> dict[str, Any]:
    """Classify every visible trunk of one slice (module docstring)."""
    rng = np.random.default_rng(seed)
    vp = vantage_points(sl, n_vantage, rng)
    ranges0, hit = virtual_scans(
        sl.xy,
        sl.labels,
        vp,
        resolution_deg=res,
        model=model,
        centers=sl.centers,  # type: ignore[arg-type]
    )
    batch = noisy_batch(ranges0, res, noise, rng)
    det = ScanTrunkDetector(matched(cfg, model, res))
    obs = det.detect_batch(batch)
    rej = det.rejected(batch)
    rej_scan = np.asarray(rej["scan_index"])
    reasons = np.asarray(rej["reason"], dtype=object)
    dets = {"stemmap": det, "textbook_kasa": ScanTrunkDetector(TEXTBOOK)}
    classes: Counter[str] = Counter()
    err: list[float] = []
    alone: dict[str, list[tuple[float, float]]] = {k: [] for k in dets}
    misses: list[dict[str, Any]] = []
    diam = sl.diameters
    for s in range(vp.shape[0]):
        rel = sl.centers - vp[s]
        rng_t = np.hypot(rel[:, 0], rel[:, 1])
        m = obs.index == s
        match = _match(obs.centers[m], rel, diam / 2.0 + 0.05)
        for t in range(len(sl.refs)):
            own = int((hit[s] == t).sum())
            if not (own >= min_returns and rng_t[t] <= 15.0 and 0.1 <= diam[t] <= 1.0):
                continue
            # perfect segmentation: only the trunk's own beams
            solo = ScanBatch(
                ranges=np.where(hit[s] == t, batch.ranges[s], np.inf)[None, :],
                times=batch.times[s : s + 1],
                angle_min=batch.angle_min,
                angle_increment=batch.angle_increment,
                range_min=batch.range_min,
                range_max=batch.range_max,
            )
            for name, d in dets.items():
                o = d.detect_batch(solo)
                k = _match(o.centers, rel[t : t + 1], diam[t : t + 1] / 2.0 + 0.05)[0]
                e = (2.0 * o.radii[k] - diam[t]) * 100.0 if k >= 0 else math.nan
                alone[name].append((float(rng_t[t]), e))
            if match[t] >= 0:
                n = int(obs.n_points[m][match[t]])
                classes["found_extra" if n > own + 1 else "found"] += 1
                if rng_t[t] <= 10.0:
                    err.append((2.0 * obs.radii[m][match[t]] - diam[t]) * 100.0)
                continue
            near = _over(rej, np.flatnonzero(rej_scan == s), rel[t], float(diam[t]))
            if near.size == 0:
                c = "no_candidate"
            elif near.size > 1:
                c = "split:" + "/".join(sorted(set(reasons[near].tolist())))
            else:
                j = int(near[0])
                c = ("merge:" if int(rej["n_points"][j]) > own + 1 else "") + str(reasons[j])
            classes[c] += 1
            misses.append(
                {
                    "scan": s,
                    "trunk": t,
                    "diameter_cm": round(100.0 * float(diam[t]), 1),
                    "range_m": round(float(rng_t[t]), 2),
                    "own_returns": own,
                    "class": c,
                    "candidate_returns": [int(rej["n_points"][j]) for j in near],
                    "candidate_width_cm": [round(100.0 * float(rej["width"][j]), 1) for j in near],
                }
            )

    def summary(rows: list[tuple[float, float]]) -> dict[str, Any]:
        a = np.asarray(rows, dtype=np.float64).reshape(-1, 2)
        out = {"recall": round(float(np.isfinite(a[:, 1]).mean()), 3) if a.size else None}
        return {**out, **_stats(a[a[:, 0] <= 10.0, 1])}

    visible = sum(classes.values())
    found = classes["found"] + classes["found_extra"]
    return {
        "visible": visible,
        "recall": round(found / visible, 3) if visible else None,
        "found_within_10m": _stats(np.asarray(err)),
        "classes": dict(sorted(classes.items())),
        "perfect_segmentation": {k: summary(v) for k, v in alone.items()},
        "misses": misses,
        "references": [reference_jackknife(sl, t) for t in range(len(sl.refs))],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--model", choices=("nearest", "averaging"), default="nearest")
    ap.add_argument("--res", type=float, default=0.5, help="angular step, degrees")
    ap.add_argument("--noise", type=float, default=0.0, help="range noise, metres")
    ap.add_argument("--vantage", type=int, default=20)
    ap.add_argument("--min-returns", type=int, default=4)
    ap.add_argument("--seed", type=int, default=11, help="as real_geometry.py (--loo: 11)")
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--set", default="{}", help="JSON overrides of the stemmap preset")
    args = ap.parse_args(argv)
    ddir = args.datasets or find_datasets_dir(Path(__file__).resolve().parent)
    if ddir is None:
        print("error: shared datasets folder not found (set STEMMAP_DATASETS)", file=sys.stderr)
        return 2
    overrides = json.loads(args.set)
    cfg = DetectorConfig.preset("stemmap", **overrides)
    out: dict[str, Any] = {
        "benchmark": "real_geometry_diagnose",
        "scanner": {"model": args.model, "res_deg": args.res, "noise_m": args.noise},
        "vantage_points_per_dataset": args.vantage,
        "overrides": overrides,
        "datasets": {},
    }
    for i, name in enumerate(SLICES):
        if args.only and name not in args.only:
            continue
        sl = load_slice(ddir, name)
        if not sl.refs or not any(0.1 <= d <= 1.0 for d in sl.diameters):
            continue
        out["datasets"][name] = diagnose(
            sl,
            cfg,
            args.model,
            args.res,
            args.noise,
            args.seed + i,
            args.vantage,
            args.min_returns,
        )
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
