"""Benchmark: tape (girth) and caliper DBH against the least-squares circle, on the real clouds
and their thinned / noisy exports (docs/algorithms/cloud.md "Out-of-round stems: tape and
calipers").

Per cloud of ``_cloud_refs`` (every stem with a ring seed) and per transform of
``cloud_robustness`` (the same random draws: ``--seeds``), two measurements of each stem:

* ``at_ref``: the section at the seed's ring height (half thickness as the seed's, or
  ``--half``), about the shipped cloud's converged ring (fixed centre and radius: no
  detector): the least-squares circle of the transformed cloud's ring (``ring_reference``
  from the shipped ring's circle), the girth and caliper diameters of
  :func:`_girth.section_girth`, and the raw convex hull of the same returns
  (perimeter / pi: what noise and sparse returns do to it);
* ``detector``: ``detect_stems_file`` (preset ours, default or ``--set``) on the transformed
  cloud written to LAS; each detection's section at its breast-height z (half thickness 5 cm,
  10 cm when the spacing is above 3 cm, as ``stem_references``), traced about the detected
  circle -- what a ``dbh_girth`` output column would hold.

Prints ONE JSON object: per cloud, stem and transform the values (cm), and a summary per stem of
each estimator's largest move from the shipped cloud's value and its error against the ring
(full rings). Usage: python benchmarks/cloud_girth.py [--clouds a,b] [--transforms t1,t2]
[--seeds 0,1,2,3,4] [--no-detector] [--half H] [--set key=value ...] (``--half``: the at_ref
sections' half thickness instead of the seed's, e.g. 0.3 for a tape over 1.0-1.6 m)
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from _cloud_refs import CLOUDS, fixed_references, load_seeds, match_stems
from _datasets import require_datasets_dir
from _girth import hull_perimeter, section_girth
from cloud_robustness import (
    TRANSFORMS,
    Context,
    run_baseline,
    set_overrides,
    transformed_files,
)
from stemmap.cloud.reference import ring_reference
from stemmap.cloud.result import BASE_SLICE, CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems_file

DEFAULT_TRANSFORMS = "subsample_50,subsample_20,subsample_10,noise_5mm,noise_1cm"
KEYS = ("circle", "girth", "caliper", "pair_lo", "pair_hi", "hull_raw")


def _cm(v: float) -> float | None:
    return round(100 * float(v), 2) if math.isfinite(v) else None


def _section(
    xyz: np.ndarray, cx: float, cy: float, z: float, r: float, half: float
) -> dict[str, Any]:
    """Every estimator on the section ``|z_i - z| <= half`` about the circle (cx, cy, r)."""
    m = (np.abs(xyz[:, 2] - z) <= half) & (np.hypot(xyz[:, 0] - cx, xyz[:, 1] - cy) <= 1.5 * r)
    q = xyz[m, :2]
    g = section_girth(q, (cx, cy), r)
    ring = ring_reference(xyz, (cx, cy), z, r, half_thickness=half)
    rho = np.hypot(q[:, 0] - cx, q[:, 1] - cy)
    raw = q[rho >= 0.5 * r]
    return {
        "circle": _cm(ring.diameter) if ring else None,
        "girth": _cm(g.girth_dbh),
        "caliper": _cm(g.caliper_max_perp),
        "pair_lo": _cm(g.caliper_pair_min),
        "pair_hi": _cm(g.caliper_pair_max),
        "hull_raw": _cm(hull_perimeter(raw) / math.pi),
        "n": g.n_points,
        "sectors": g.n_sectors,
        "gap_deg": round(g.max_gap_deg),
        **({"why": g.reason} if g.reason else {}),
    }


def _half(det: CloudStems) -> float:
    return 0.05 if det.spacing < 0.03 else 0.1


def _detected(xyz: np.ndarray, det: CloudStems) -> list[dict[str, Any]]:
    """The estimators about each detection (its breast-height z; a slice: the cloud's median)."""
    z_slice = float(np.median(xyz[:, 2]))
    out = []
    for i in range(len(det)):
        z = z_slice if det.base == BASE_SLICE else float(det.z[i])
        row = _section(
            xyz, float(det.xy[i, 0]), float(det.xy[i, 1]), z, det.diameter[i] / 2, _half(det)
        )
        row["circle"] = _cm(det.diameter[i])  # the detector's DBH
        row["dbh_std"] = _cm(det.diameter_std[i])
        out.append(row)
    return out


def _moves(
    rows: list[dict[str, Any] | None], bases: list[dict[str, Any]]
) -> dict[str, float | None]:
    """Largest |value - shipped value| (cm) per estimator over the transformed rows (each
    against the shipped row at the same place of ``bases``)."""
    out: dict[str, float | None] = {}
    for k in KEYS:
        d = [
            abs(r[k] - b[k])
            for r, b in zip(rows, bases, strict=True)
            if r is not None and r.get(k) is not None and b.get(k) is not None
        ]
        out[k] = round(max(d), 2) if d else None
    return out


def _vs_ring(rows: list[dict[str, Any] | None], rings: list[float | None]) -> dict[str, Any]:
    """Per estimator over the rows with a full ring: RMSE and mean of (value - ring) (cm), and
    how many rows it measured of those it was asked for."""
    out: dict[str, Any] = {}
    for k in KEYS:
        e = [
            r[k] - ring
            for r, ring in zip(rows, rings, strict=True)
            if ring is not None and r is not None and r.get(k) is not None
        ]
        asked = sum(1 for ring in rings if ring is not None)
        out[k] = {
            "rmse": round(float(np.sqrt(np.mean(np.square(e)))), 2) if e else None,
            "bias": round(float(np.mean(e)), 2) if e else None,
            "measured": f"{len(e)}/{asked}",
        }
    return out


def _summary(res: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """Per transform, over all seeds: each estimator against the full rings (``at_ref`` and
    ``detector``: the detection paired with the ring's stem), and its largest move from the
    shipped cloud's value (``detector``: every detected stem)."""
    refs = res["at_ref"]
    full = [r["ring"] if r["full"] else None for r in refs]
    ring_of = res["ring_of_detection"]
    det_full = [None if k is None else full[k] for k in ring_of]
    out: dict[str, Any] = {
        "shipped": {
            "at_ref": _vs_ring([r["shipped"] for r in refs], full),
            "detector": _vs_ring([d["shipped"] for d in res["detector"]], det_full)
            if res["detector"]
            else None,
        }
    }
    for name in names:
        cells = [c for cn, c in res["cells"].items() if cn.startswith(name + "/")]
        at = [row for c in cells for row in c["at_ref"]]
        det = [row for c in cells for row in c.get("detector", [])]
        out[name] = {
            "at_ref": _vs_ring(at, full * len(cells)),
            "detector": _vs_ring(det, det_full * len(cells)) if det else None,
            "detector_move_max": _moves(det, [d["shipped"] for d in res["detector"]] * len(cells))
            if det
            else None,
        }
    return out


def run_cloud(
    key: str,
    path: Path,
    names: list[str],
    seeds: list[int],
    tmp: Path,
    detector: bool,
    overrides: dict[str, Any],
    half: float | None = None,
) -> dict[str, Any]:
    bl = run_baseline(key, path)
    refs = fixed_references(bl.xyz, load_seeds()[key])
    stems = [
        (s if half is None else replace(s, half=half), r)
        for s, r in zip(bl.seeds, refs, strict=True)
        if r is not None
    ]
    cells: dict[str, Any] = {}
    ref_rows = [
        {
            "ring": _cm(r.diameter),
            "ring_rms": _cm(r.rms),
            "full": r.full,
            "shipped": _section(bl.xyz, r.x, r.y, s.z, r.diameter / 2, s.half),
        }
        for s, r in stems
    ]
    base_det = _detected(bl.xyz, bl.det) if detector else []
    cfg = replace(StemConfig(), **overrides)
    for seed in seeds:
        ctx = Context(bl.xyz, bl.ground, seed)
        for name in names:
            prep = TRANSFORMS[name](ctx)
            if prep is None:
                continue
            at_ref = [_section(prep.xyz, r.x, r.y, s.z, r.diameter / 2, s.half) for s, r in stems]
            cells[f"{name}/{seed}"] = {"at_ref": at_ref}
        if detector:
            for name, prep, f in transformed_files(bl, names, tmp, seed):
                det = detect_stems_file(f, cfg)
                rows = _detected(prep.xyz, det)
                pairs = match_stems(bl.det.xy, bl.det.diameter, det.xy)
                cells[f"{name}/{seed}"]["detector"] = [
                    next((rows[j] for i, j in pairs if i == b), None) for b in range(len(bl.det))
                ]
    summary = []
    for k, ref in enumerate(ref_rows):
        s: dict[str, Any] = {"ring": ref["ring"], "full": ref["full"], "shipped": ref["shipped"]}
        for name in names:
            rows = [c["at_ref"][k] for cn, c in cells.items() if cn.startswith(name + "/")]
            s[f"at_ref_move_{name}"] = _moves(rows, [ref["shipped"]] * len(rows))
        summary.append(s)
    det_summary = []
    for b, base in enumerate(base_det):
        s = {"shipped": base}
        for name in names:
            rows = [
                c["detector"][b]
                for cn, c in cells.items()
                if cn.startswith(name + "/") and "detector" in c
            ]
            s[f"move_{name}"] = _moves(rows, [base] * len(rows))
            s[f"lost_{name}"] = sum(1 for r in rows if r is None)
        det_summary.append(s)
    ring_xy = np.array([[r.x, r.y] for _, r in stems]).reshape(-1, 2)
    ring_d = np.array([r.diameter for _, r in stems])
    ring_of: list[int | None] = [None] * len(bl.det)
    for a, j in match_stems(ring_xy, ring_d, bl.det.xy):
        ring_of[j] = a
    res = {
        "at_ref": summary,
        "detector": det_summary,
        "ring_of_detection": ring_of,
        "cells": cells,
    }
    res["summary"] = _summary(res, names)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--transforms", default=DEFAULT_TRANSFORMS)
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--no-detector", action="store_true")
    ap.add_argument(
        "--half", type=float, default=None, help="at_ref section half thickness (m; the seed's)"
    )
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    args = ap.parse_args()
    root = require_datasets_dir()
    names = args.transforms.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as td:
        out = {
            k: run_cloud(
                k,
                root / CLOUDS[k],
                names,
                seeds,
                Path(td),
                not args.no_detector,
                set_overrides(args.set),
                args.half,
            )
            for k in args.clouds.split(",")
        }
    print(
        json.dumps(
            {
                "benchmark": "cloud_girth",
                "seeds": seeds,
                "cpu_s": round(time.process_time() - t0, 1),
                "clouds": out,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
