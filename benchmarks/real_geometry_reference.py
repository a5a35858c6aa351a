"""An independent check of a real slice's reference trunk, and every view of it (issue 11,
Dec 5, "aRchi tree 1: the reference settled").

For one slice of :data:`stemmap.eval.real_slices.SLICES` (default ``archi_tree1``) and one of
its reference trunks (``--trunk``, default 0), one JSON object on stdout:

- ``reference``: the benchmark's ring reference (:func:`~stemmap.eval.real_slices.load_slice`)
  next to the same ring fit under 20 RANSAC seeds (on the stem's points as the slice takes
  them), the girth-tape and area-equivalent diameters of the outline (sector medians,
  ``real_geometry_diagnose.reference_check``), a plain geometric circle fit of every stem point
  (no RANSAC, no trim; its RMS) and the second-harmonic (elliptic) part of the outline: the
  largest and smallest caliper width of the closed outline (real points and fill) over 180
  directions.
- ``qsm`` (``--qsm FILE``, a TreeQSM cylinder table as aRchi ships it, path under the datasets
  folder): the stem cylinder (branch order 0) at the slice's mid height, its diameter, tilt,
  z range, and the share of the slice's stem points outside it (median radial residual).
  Columns of the TreeQSM text export as aRchi's ``read_QSM`` names them (umr-amap/aRchi,
  ``R/read_QSM.R``): radius (m), length (m), start x y z (m), axis x y z (unit), parent,
  extension, added (1 = filled, no points), UnmodRadius (m, before TreeQSM's radius
  correction), branch, BranchOrder (0 = stem), PositionInBranch.
- ``cloud``: ``stemmap stems`` (preset ours, :func:`stemmap.cloud.stems.detect_stems_file`) on
  the slice's whole cloud: the stem's DBH, its height and the base it is measured from.
- ``views``: every view of the trunk by the LOO's vantage points and seed (0.5 deg
  nearest-return, no noise, the ``stemmap`` preset with ``--grid``, default 59 = the preset):
  range, bearing of the sensor from the trunk centre (degrees, x axis = 0), own returns and how
  many of them come from the points filling the unseen sectors, foreign returns within 3 beams
  of the trunk's, the caliper width of the closed outline across the view, and the DBH error
  against the reference (or the rejected candidates over the trunk, ``reason:returns:rms cm``).

Usage::

    python benchmarks/real_geometry_reference.py --qsm archi/Tree_1_TreeQSM.txt
    python benchmarks/real_geometry_reference.py --no-cloud --fill outline
    python benchmarks/real_geometry_reference.py --only treels_pine --grid 60
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _loo_grid import LOO_GRID
from _real_scanning import greedy_match, matched, scene_scans, vantage_points
from real_geometry_diagnose import _over, reference_check
from stemmap.eval.real_slices import (
    FILLS,
    SLICES,
    RealSlice,
    _read_xyz,
    load_slice,
    noisy_batch,
    ring_reference,
)
from stemmap.scan.circle import fit_circle_ours
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

#: TreeQSM text export columns (aRchi's ``read_QSM`` names; module docstring).
QSM_COLUMNS = (
    "radius",
    "length",
    "start_x",
    "start_y",
    "start_z",
    "axis_x",
    "axis_y",
    "axis_z",
    "parent",
    "extension",
    "added",
    "unmod_radius",
    "branch",
    "branch_order",
    "position_in_branch",
)


def _stem_points(sl: RealSlice, t: int) -> np.ndarray:
    """The slice's own points (no fill) within 0.5 m of reference ``t``'s centre."""
    n_fill = sum(
        int(np.count_nonzero(sl.labels == k)) - int(r["n_points"]) for k, r in enumerate(sl.refs)
    )
    own = sl.xy[: sl.xy.shape[0] - n_fill]
    c = sl.centers[t]
    return np.asarray(own[np.hypot(*(own - c).T) <= 0.5])


def _calipers(pts: np.ndarray, n_dir: int = 180) -> np.ndarray:
    """Width of ``pts`` across each of ``n_dir`` directions over 180 degrees (metres)."""
    a = np.linspace(0.0, math.pi, n_dir, endpoint=False)
    proj = pts @ np.vstack((np.cos(a), np.sin(a)))
    return np.asarray(proj.max(axis=0) - proj.min(axis=0))


def reference(sl: RealSlice, t: int) -> dict[str, Any]:
    """The ring reference next to the independent readings of the same outline."""
    ref = sl.refs[t]
    pts = _stem_points(sl, t)
    seeds = []
    for s in range(20):
        got = ring_reference(pts, seed=s)
        seeds.append([round(100 * got[0]["diameter"], 1), got[0]["coverage_deg"]] if got else None)
    geo = fit_circle_ours(pts, edges=(False, False))
    res = np.hypot(*(pts - geo.center).T) - geo.radius
    closed = sl.xy[sl.labels == t]
    cal = _calipers(np.vstack((closed, pts)))
    return {
        "ring_diameter_cm": round(100 * ref["diameter"], 2),
        "ring_rms_mm": round(1000 * ref["ring_rms_m"], 1),
        "coverage_deg": ref["coverage_deg"],
        "ring_points": int(ref["n_points"]),
        "stem_points": int(pts.shape[0]),
        "ring_by_ransac_seed_cm_deg": seeds,
        **reference_check(sl, t),
        "circle_all_points_cm": round(200 * float(geo.radius), 2),
        "circle_all_points_rms_mm": round(1000 * float(np.sqrt(np.mean(res * res))), 1),
        "caliper_min_max_cm": [round(100 * float(cal.min()), 1), round(100 * float(cal.max()), 1)],
    }


def qsm_check(path: Path, sl: RealSlice, t: int, z: float, shift: np.ndarray) -> dict[str, Any]:
    """The TreeQSM stem cylinder at height ``z`` (cloud frame) against the slice's stem points
    (``shift``: the slice's offset from the cloud frame)."""
    q = np.loadtxt(path, ndmin=2)
    if q.shape[1] != len(QSM_COLUMNS):
        raise SystemExit(f"error: {path}: {q.shape[1]} columns, expected {len(QSM_COLUMNS)}")
    col = {n: q[:, i] for i, n in enumerate(QSM_COLUMNS)}
    stem = np.flatnonzero(col["branch_order"] == 0)
    for i in stem:
        s = (z - col["start_z"][i]) / col["axis_z"][i]
        if 0.0 <= s <= col["length"][i]:
            c = np.array([col["start_x"][i], col["start_y"][i]]) + s * np.array(
                [col["axis_x"][i], col["axis_y"][i]]
            )
            pts = _stem_points(sl, t) + shift
            res = np.hypot(*(pts - c).T) - col["radius"][i]
            z1 = col["start_z"][i] + col["length"][i] * col["axis_z"][i]
            return {
                "cylinders": int(q.shape[0]),
                "stem_cylinders": int(stem.size),
                "cylinder": int(i) + 1,
                "diameter_cm": round(200 * float(col["radius"][i]), 2),
                "unmodified_diameter_cm": round(200 * float(col["unmod_radius"][i]), 2),
                "z_m": [round(float(col["start_z"][i]), 3), round(float(z1), 3)],
                "tilt_deg": round(math.degrees(math.acos(min(1.0, col["axis_z"][i]))), 1),
                "centre_offset_from_ring_cm": round(
                    100 * float(np.hypot(*(c - shift - sl.centers[t]))), 1
                ),
                "points_outside_share": round(float(np.mean(res > 0)), 2),
                "median_residual_mm": round(1000 * float(np.median(res)), 1),
            }
    return {"cylinders": int(q.shape[0]), "stem_cylinders": int(stem.size), "cylinder": None}


def cloud_check(path: Path) -> dict[str, Any]:
    """``stemmap stems`` (preset ours) on the whole cloud."""
    from stemmap.cloud.stems import detect_stems_file

    st = detect_stems_file(path)
    return {
        "stems": len(st),
        "diameter_cm": [round(100 * float(d), 2) for d in st.diameter],
        "z_m": [round(float(z), 3) for z in st.z],
        "base": str(st.base),
    }


def views(sl: RealSlice, t: int, seed: int, grid: int) -> list[dict[str, Any]]:
    """Every view of trunk ``t`` (module docstring)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    vp = vantage_points(sl, 20, rng)
    ranges0, hit = scene_scans(sl, vp, "nearest", 0.5, "none", seed)
    batch = noisy_batch(ranges0, 0.5, 0.0, rng)
    cfg = matched(DetectorConfig.preset("stemmap", **LOO_GRID[grid]), "nearest", 0.5)
    det = ScanTrunkDetector(cfg)
    obs = det.detect_batch(batch)
    rej = det.rejected(batch)
    rej_scan = np.asarray(rej["scan_index"])
    ref = sl.refs[t]
    idx = np.flatnonzero(sl.labels == t)
    fill = np.zeros(sl.xy.shape[0], dtype=bool)
    fill[idx[int(ref["n_points"]) :]] = True
    tree = cKDTree(sl.xy)
    closed = np.vstack((sl.xy[idx], _stem_points(sl, t)))
    ang = batch.angle_min + np.arange(batch.ranges.shape[1]) * batch.angle_increment
    c, d_ref = sl.centers[t], float(ref["diameter"])
    out = []
    for s in range(vp.shape[0]):
        rel = c - vp[s]
        rng_t = float(np.hypot(*rel))
        own = np.flatnonzero(hit[s] == t)
        if not (own.size >= 4 and rng_t <= 15.0 and 0.1 <= d_ref <= 1.0):
            continue
        p = vp[s] + batch.ranges[s, own, None] * np.column_stack(
            (np.cos(ang[own]), np.sin(ang[own]))
        )
        near = tree.query(p)[1]
        span = np.arange(max(own.min() - 3, 0), min(own.max() + 4, hit.shape[1]))
        u = rel / rng_t
        row: dict[str, Any] = {
            "scan": s,
            "range_m": round(rng_t, 2),
            "bearing_deg": round(math.degrees(math.atan2(-rel[1], -rel[0]))),
            "own_returns": int(own.size),
            "fill_returns": int(fill[near].sum()),
            "foreign_near": int(((hit[s, span] != t) & np.isfinite(batch.ranges[s, span])).sum()),
            "caliper_cm": round(100 * float(np.ptp(closed @ np.array([-u[1], u[0]]))), 1),
        }
        m = obs.index == s
        k = greedy_match(obs.centers[m], rel[None], np.array([0.5 * d_ref + 0.05]))[0]
        if k >= 0:
            row["err_cm"] = round(100 * (2 * float(obs.radii[m][k]) - d_ref), 2)
        else:
            hits = _over(rej, np.flatnonzero(rej_scan == s), rel, d_ref)
            row["missed"] = [
                f"{rej['reason'][j]}:{int(rej['n_points'][j])}:{100 * float(rej['rms'][j]):.1f}"
                for j in hits
            ]
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", type=Path, default=None)
    ap.add_argument("--only", default="archi_tree1", help="slice (default archi_tree1)")
    ap.add_argument("--trunk", type=int, default=0)
    ap.add_argument("--qsm", default=None, help="TreeQSM cylinder table under the datasets")
    ap.add_argument("--grid", type=int, default=59, help="LOO_GRID setting (default 59)")
    ap.add_argument("--no-cloud", action="store_true", help="skip stemmap stems on the cloud")
    ap.add_argument("--fill", choices=FILLS, default="circle", help="unseen sectors (load_slice)")
    args = ap.parse_args(argv)
    ddir = require_datasets_dir(args.datasets)
    spec = SLICES[args.only]
    sl = load_slice(ddir, args.only, args.fill)
    out: dict[str, Any] = {
        "benchmark": "real_geometry_reference",
        "slice": args.only,
        "fill": args.fill,
        "trunk": args.trunk,
        "reference": reference(sl, args.trunk),
    }
    if args.qsm or not args.no_cloud:
        xyz = _read_xyz(Path(ddir) / spec.path)
        z0 = float(np.quantile(xyz[:, 2], 0.001)) if spec.heights == "lowest" else 0.0
        band = xyz[(xyz[:, 2] - z0 >= spec.z_lo) & (xyz[:, 2] - z0 <= spec.z_hi), :2]
        if spec.heights == "as_is":
            band = xyz[:, :2]
        shift = 0.5 * (band.min(axis=0) + band.max(axis=0))
        if args.qsm:
            if spec.heights == "ground":
                raise SystemExit("error: --qsm needs a single tree ('lowest') or a cut slice")
            zc = z0 + 0.5 * (spec.z_lo + spec.z_hi)
            out["qsm"] = qsm_check(Path(ddir) / args.qsm, sl, args.trunk, zc, shift)
        if not args.no_cloud:
            out["cloud"] = cloud_check(Path(ddir) / spec.path)
    out["views"] = views(sl, args.trunk, 11 + list(SLICES).index(args.only), args.grid)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
