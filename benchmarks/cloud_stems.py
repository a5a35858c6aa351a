"""Benchmark: stems and DBH from 3D clouds -- EB-LiDAR (munjer2025) vs ours.

Prints ONE JSON object (with --json) holding every parameter of every scenario and:

* simulated stands (terrestrial single scan and 4-station plot, 5 mm; 16-beam mobile along a
  path, 3 cm), per
  method: recall (all, DBH >= 10 cm), precision (all detections, and detections >= 7.5 cm), DBH
  RMSE / bias, position RMSE, time and points per second;
* a 20-million-point LAS (tiled simulated TLS plots) processed by ``stemmap stems`` in a
  subprocess: wall time, points per second and peak RSS;
* the real clouds in ../shared/datasets (fortls_slice, treels, lidr_dbh): stems and DBH per stem;
  on fortls_slice (full rings) the DBH from single-side (half-ring) views vs the full-ring fit;
* optionally dendromatics (a peer library) on the same real clouds, run by a separate Python
  that has it installed (``--dendromatics-python``), with its stems, DBH and time.

Usage: python benchmarks/cloud_stems.py --json [--quick] [--no-big] [--dendromatics-python P]
       [--methods munjer2025 ...] [--sim-only]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.cloud.stems import (
    CloudStems,
    MunjerConfig,
    StemConfig,
    associate_proximity,
    detect_stems,
    detect_stems_munjer,
    get_preset,
)
from stemmap.datasets import find_datasets_dir
from stemmap.eval.matching import match_points
from stemmap.io.clouds import read_cloud
from stemmap.sim.lidar import Stand3D, lidar_preset, random_stand3d, simulate_mobile, simulate_tls

GATE = 0.5  # m, detection-to-truth matching gate


def _r(v: float, nd: int = 3) -> float | None:
    return None if not np.isfinite(v) else round(float(v), nd)


def score(det: CloudStems, stand: Stand3D) -> dict[str, Any]:
    m = match_points(det.xy, stand.trees_xy, GATE)
    big = stand.dbh >= 0.10
    matched_truth = np.zeros(stand.n_trees, bool)
    matched_truth[m.pairs[:, 1]] = True
    d = det.diameter[m.pairs[:, 0]] - stand.dbh[m.pairs[:, 1]]
    pe = det.xy[m.pairs[:, 0]] - stand.trees_xy[m.pairs[:, 1]]
    n75 = int((det.diameter >= 0.075).sum())
    tp75 = int((det.diameter[m.pairs[:, 0]] >= 0.075).sum())
    return {
        "n_truth": stand.n_trees,
        "n_detected": len(det),
        "n_matched": m.n_matched,
        "recall": _r(m.n_matched / stand.n_trees),
        "recall_dbh_ge_10cm": _r(matched_truth[big].mean() if big.any() else np.nan),
        "precision": _r(m.n_matched / len(det) if len(det) else np.nan),
        "precision_det_ge_7.5cm": _r(tp75 / n75 if n75 else np.nan),
        "dbh_rmse_cm": _r(100 * np.sqrt(np.mean(d**2)) if d.size else np.nan, 2),
        "dbh_bias_cm": _r(100 * np.mean(d) if d.size else np.nan, 2),
        "dbh_abs_max_cm": _r(100 * np.max(np.abs(d)) if d.size else np.nan, 2),
        "position_rmse_cm": _r(
            100 * np.sqrt(np.mean(np.sum(pe**2, axis=1))) if d.size else np.nan, 2
        ),
    }


def visible_trees(stand: Stand3D, xyz: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Trees with >= 20 simulated stem returns between 0.8 and 2.0 m above the ground (a tree
    hidden behind others in the slice band cannot be found from this cloud)."""
    h = xyz[:, 2] - stand.ground_z(xyz[:, :2])
    inb = (h > 0.8) & (h < 2.0) & (label >= 0)
    return np.bincount(label[inb], minlength=stand.n_trees) >= 20


def _pool(
    rows: list[dict[str, Any]], dets: list[tuple[CloudStems, Stand3D, np.ndarray]]
) -> dict[str, Any]:
    """Pool matches over several stands (metrics over all trees, not a mean of means)."""
    d_all, p_all = [], []
    n_truth = n_det = n_match = n_big = n_big_match = n75 = tp75 = n_vis = n_vis_match = 0
    for det, stand, vis in dets:
        m = match_points(det.xy, stand.trees_xy, GATE)
        n_vis += int(vis.sum())
        n_vis_match += int(vis[m.pairs[:, 1]].sum())
        d_all.append(det.diameter[m.pairs[:, 0]] - stand.dbh[m.pairs[:, 1]])
        p_all.append(det.xy[m.pairs[:, 0]] - stand.trees_xy[m.pairs[:, 1]])
        n_truth += stand.n_trees
        n_det += len(det)
        n_match += m.n_matched
        big = stand.dbh >= 0.10
        n_big += int(big.sum())
        n_big_match += int(big[m.pairs[:, 1]].sum())
        n75 += int((det.diameter >= 0.075).sum())
        tp75 += int((det.diameter[m.pairs[:, 0]] >= 0.075).sum())
    d = np.concatenate(d_all)
    p = np.concatenate(p_all)
    t = sum(r["time_s"] for r in rows)
    pts = sum(r["n_points"] for r in rows)
    return {
        "n_truth": n_truth,
        "n_detected": n_det,
        "recall": _r(n_match / n_truth),
        "recall_dbh_ge_10cm": _r(n_big_match / n_big if n_big else np.nan),
        "n_visible": n_vis,
        "recall_visible": _r(n_vis_match / n_vis if n_vis else np.nan),
        "precision": _r(n_match / n_det if n_det else np.nan),
        "precision_det_ge_7.5cm": _r(tp75 / n75 if n75 else np.nan),
        "dbh_rmse_cm": _r(100 * np.sqrt(np.mean(d**2)) if d.size else np.nan, 2),
        "dbh_bias_cm": _r(100 * np.mean(d) if d.size else np.nan, 2),
        "dbh_abs_p95_cm": _r(100 * np.quantile(np.abs(d), 0.95) if d.size else np.nan, 2),
        "position_rmse_cm": _r(100 * np.sqrt(np.mean(np.sum(p**2, 1))) if d.size else np.nan, 2),
        "time_s": _r(t),
        "points_per_second": _r(pts / t if t > 0 else np.nan, 0),
        "per_stand": rows,
    }


def munjer_tls(xyz: np.ndarray, origin: np.ndarray, cfg: MunjerConfig) -> CloudStems:
    """EB-LiDAR on a terrestrial scan: the paper's forward box in 4 headings (a robot turning
    on the spot at the scanner position), detections associated by proximity (1.0 m)."""
    parts = []
    for yaw in (0.0, np.pi / 2, np.pi, -np.pi / 2):
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        local = (xyz - origin) @ R  # world -> sensor frame
        d = detect_stems_munjer(local, cfg)
        parts.append(replace(d, xy=d.xy @ R[:2, :2].T + origin[:2]))
    return associate_proximity(parts, cfg.association_distance)


def munjer_mobile(frames: Any, poses: np.ndarray, cfg: MunjerConfig) -> CloudStems:
    parts = []
    for fr, pose in zip(frames, poses, strict=True):
        d = detect_stems_munjer(fr.xyz, cfg)
        c, s = np.cos(pose[3]), np.sin(pose[3])
        parts.append(replace(d, xy=d.xy @ np.array([[c, s], [-s, c]]) + pose[:2]))
    return associate_proximity(parts, cfg.association_distance)


#: Multi-scan TLS plot design: the plot centre plus three stations 7 m out at 90, 210 and 330
#: degrees (the usual way a terrestrial plot is scanned, so that trunks hidden from one station
#: are seen from another).
TLS_MULTI_POSITIONS = np.array(
    [[12.5, 12.5]]
    + [
        [12.5 + 7.0 * np.cos(np.radians(a)), 12.5 + 7.0 * np.sin(np.radians(a))]
        for a in (90, 210, 330)
    ]
)


def munjer_multi(
    xyz: np.ndarray, scan: np.ndarray, heads: np.ndarray, cfg: MunjerConfig
) -> CloudStems:
    """EB-LiDAR on a multi-station TLS plot: :func:`munjer_tls` on each station's own points,
    detections associated by proximity (1.0 m)."""
    parts = [munjer_tls(xyz[scan == k], heads[k], cfg) for k in range(heads.shape[0])]
    return associate_proximity(parts, cfg.association_distance)


METHODS = ("munjer2025", "ours", "ours_kasa", "ours_origins")


def run_sim(quick: bool, methods: tuple[str, ...] = METHODS) -> dict[str, Any]:
    seeds = [1, 2] if quick else [1, 2, 3]
    stand_kw = {"n_trees": 30, "size": (25.0, 25.0)}
    tls_model = lidar_preset("tls")
    vlp = lidar_preset("vlp16")
    n_path = 60
    out: dict[str, Any] = {
        "parameters": {
            "seeds": seeds,
            "stand": {
                **stand_kw,
                "dbh_mean": 0.28,
                "dbh_std": 0.09,
                "dbh_min": 0.08,
                "branches_per_tree": 8,
                "low_branch_fraction": 0.25,
                "n_shrubs": 15,
                "slope": [0.08, -0.05],
                "max_lean_deg": 4.0,
            },
            "terrestrial": {
                **{k: v for k, v in asdict(tls_model).items() if k != "elevations_deg"},
                "elevation_deg": [-40.0, 49.9, 0.1],
                "positions": "one scan at the plot centre",
                "height_m": 1.5,
            },
            "terrestrial_multi": {
                "model": "as terrestrial",
                "positions": TLS_MULTI_POSITIONS.round(3).tolist(),
                "height_m": 1.5,
                "note": "stations merged in the world frame; munjer2025 runs per station",
            },
            "mobile": {
                **{k: v for k, v in asdict(vlp).items() if k != "elevations_deg"},
                "elevations_deg": list(vlp.elevations_deg),
                "path": f"straight line through the plot centre, {n_path} revolutions",
                "height_m": 0.8,
            },
            "match_gate_m": GATE,
            "munjer2025_on_tls": "paper box in 4 headings at the scanner, associated at 1.0 m",
            "munjer2025_on_mobile": "paper box per revolution (sensor frame), associated at 1.0 m",
            "ours_origins": "preset ours plus each point's sensor position (the scanner; for "
            "the mobile scan the pose of the point's revolution): slice fits refined along rays",
        }
    }
    for scen in ("terrestrial", "terrestrial_multi", "mobile"):
        rows: dict[str, list[dict[str, Any]]] = {m: [] for m in methods}
        dets: dict[str, list[tuple[CloudStems, Stand3D, np.ndarray]]] = {m: [] for m in methods}
        for seed in seeds:
            stand = random_stand3d(**stand_kw, rng=seed)  # type: ignore[arg-type]
            if scen == "terrestrial":
                origin_xy = np.array([12.5, 12.5])
                cloud = simulate_tls(stand, [origin_xy], tls_model, rng=100 + seed)
                xyz = cloud.xyz
                vis = visible_trees(stand, xyz, cloud.fields["label"])
                origin = np.array([*origin_xy, stand.ground_z(origin_xy)[0] + 1.5])
                frames, poses = None, None
                origins = origin
            elif scen == "terrestrial_multi":
                pos = TLS_MULTI_POSITIONS
                cloud = simulate_tls(stand, pos, tls_model, rng=300 + seed)
                xyz = cloud.xyz
                vis = visible_trees(stand, xyz, cloud.fields["label"])
                heads = np.column_stack((pos, stand.ground_z(pos) + 1.5))
                scan_of = np.asarray(cloud.fields["scan"], dtype=np.int64)
                frames, poses = None, None
                origins = heads[scan_of]
            else:
                path = np.column_stack((np.linspace(0.5, 24.5, n_path), np.full(n_path, 12.3)))
                mob = simulate_mobile(stand, path, vlp, rng=200 + seed)
                xyz = mob.cloud.xyz
                vis = visible_trees(stand, xyz, mob.cloud.fields["label"])
                frames, poses = mob.frames, mob.poses
                origins = mob.poses[mob.cloud.fields["frame_index"], :3]
            for meth in methods:
                cfg = get_preset("ours" if meth == "ours_origins" else meth)
                t0 = time.perf_counter()
                if meth == "munjer2025":
                    assert isinstance(cfg, MunjerConfig)
                    if scen == "terrestrial_multi":
                        det = munjer_multi(xyz, scan_of, heads, cfg)
                    elif frames is None:
                        det = munjer_tls(xyz, origin, cfg)
                    else:
                        det = munjer_mobile(frames, poses, cfg)  # type: ignore[arg-type]
                else:
                    assert isinstance(cfg, StemConfig)
                    det = detect_stems(
                        xyz, cfg, origins=origins if meth == "ours_origins" else None
                    )
                dt = time.perf_counter() - t0
                row = {"seed": seed, "n_points": len(xyz), "time_s": _r(dt), **score(det, stand)}
                rows[meth].append(row)
                dets[meth].append((det, stand, vis))
        out[scen] = {m: _pool(rows[m], dets[m]) for m in methods}
    return out


def run_density(quick: bool) -> dict[str, Any]:
    """Same stand and scan, points randomly thinned: no configuration change between rows."""
    stand = random_stand3d(30, (25.0, 25.0), rng=1)
    cloud = simulate_tls(stand, [[12.5, 12.5]], lidar_preset("tls"), rng=101)
    vis = visible_trees(stand, cloud.xyz, cloud.fields["label"])
    gen = np.random.default_rng(0)
    u = gen.random(len(cloud))
    rows = []
    for frac in (1.0, 0.5, 0.25, 0.1) if quick else (1.0, 0.5, 0.25, 0.1, 0.05):
        xyz = cloud.xyz[u < frac]
        t0 = time.perf_counter()
        det = detect_stems(xyz)
        dt = time.perf_counter() - t0
        sc = score(det, stand)
        m = match_points(det.xy, stand.trees_xy, GATE)
        rows.append(
            {
                "fraction_of_points": frac,
                "n_points": len(xyz),
                "measured_spacing_m": _r(det.spacing, 4),
                "recall": sc["recall"],
                "recall_visible": _r(vis[m.pairs[:, 1]].sum() / max(vis.sum(), 1)),
                "precision": sc["precision"],
                "dbh_rmse_cm": sc["dbh_rmse_cm"],
                "dbh_bias_cm": sc["dbh_bias_cm"],
                "time_s": _r(dt),
            }
        )
    return {"scenario": "terrestrial seed 1 (tls preset), random thinning", "rows": rows}


# --------------------------------------------------------------------------------------------
# 20 million points, subprocess
# --------------------------------------------------------------------------------------------


def make_big_las(path: Path, n_target: int) -> dict[str, Any]:
    import laspy

    stand = random_stand3d(30, (25.0, 25.0), rng=7)
    cloud = simulate_tls(stand, [[12.5, 12.5]], lidar_preset("tls"), rng=8)
    # crop to the stand (+1 m) so that tiles do not overlap (each has its own sloped ground)
    inside = np.all((cloud.xyz[:, :2] >= -1.0) & (cloud.xyz[:, :2] <= 26.0), axis=1)
    base = cloud.xyz[inside]
    reps = int(np.ceil(n_target / len(base)))
    side = int(np.ceil(np.sqrt(reps)))
    header = laspy.LasHeader(point_format=0, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([0.0, 0.0, 0.0])
    written = 0
    with laspy.open(path, mode="w", header=header) as w:
        for k in range(reps):
            off = np.array([30.0 * (k % side), 30.0 * (k // side), 0.0])
            take = min(len(base), n_target - written)
            if take <= 0:
                break
            pts = laspy.ScaleAwarePointRecord.zeros(take, header=header)
            xyz = base[:take] + off
            pts.x, pts.y, pts.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            w.write_points(pts)
            written += take
    return {
        "n_points": written,
        "tiles": reps,
        "tile_points": len(base),
        "trees_per_tile": stand.n_trees,
        "tile_spacing_m": 30.0,
        "tile": "one simulated TLS scan (preset tls, 5 mm) of a 25 x 25 m stand, cropped to it",
    }


_CHILD = """
import json, resource, sys, time
t0 = time.perf_counter()
from stemmap.cloud.stems import detect_stems_file
det = detect_stems_file(sys.argv[1], chunk_size=int(sys.argv[2]))
dt = time.perf_counter() - t0
print(json.dumps({"stems": len(det), "time_s": dt,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run_big(n_points: int, chunk: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="stemmap_big_") as tmp:
        f = Path(tmp) / "big.las"
        t0 = time.perf_counter()
        info = make_big_las(f, n_points)
        t_make = time.perf_counter() - t0
        r = subprocess.run(
            [sys.executable, "-c", _CHILD, str(f), str(chunk)],
            capture_output=True,
            text=True,
            check=False,
        )
        if r.returncode != 0:
            return {"error": r.stderr[-2000:], **info}
        res = json.loads(r.stdout.strip().splitlines()[-1])
        return {
            **info,
            "format": "LAS 1.2 point format 0 (uncompressed)",
            "chunk_size": chunk,
            "make_time_s": _r(t_make, 1),
            "stems_found": res["stems"],
            "stems_expected_upper_bound": info["tiles"] * info["trees_per_tile"],
            "time_s": _r(res["time_s"], 2),
            "points_per_second": _r(info["n_points"] / res["time_s"], 0),
            "peak_rss_mb": _r(res["peak_rss_mb"], 0),
            "note": "end to end in a fresh subprocess: import, two streaming passes, detection",
        }


# --------------------------------------------------------------------------------------------
# real clouds
# --------------------------------------------------------------------------------------------

REAL = {
    "fortls_slice": "fortls_slice/diameters.laz",
    "treels_pine_plot": "treels/pine_plot.laz",
    "treels_pine": "treels/pine.laz",
    "treels_spruce": "treels/spruce.laz",
    "lidr_dbh": "lidr_dbh/dbh.laz",
}


def _stems_table(det: CloudStems) -> list[dict[str, Any]]:
    return [
        {
            "x": _r(det.xy[k, 0]),
            "y": _r(det.xy[k, 1]),
            "dbh_cm": _r(100 * det.diameter[k], 1),
            "quality": _r(det.quality[k], 2),
            "arc_deg": _r(det.arc_deg[k], 0),
            "n_points": int(det.n_points[k]),
        }
        for k in range(len(det))
    ]


def run_real(ddir: Path) -> dict[str, Any]:
    out: dict[str, Any] = {}
    band_munjer = MunjerConfig(box_x=None, box_y=None, box_z=None)
    for name, rel in REAL.items():
        f = ddir / rel
        if not f.exists():
            out[name] = {"error": f"missing {f}"}
            continue
        xyz = read_cloud(f).xyz
        entry: dict[str, Any] = {"file": rel, "n_points": len(xyz)}
        t0 = time.perf_counter()
        det = detect_stems(xyz)
        entry["ours"] = {
            "time_s": _r(time.perf_counter() - t0),
            "n_stems": len(det),
            "spacing_m": _r(det.spacing, 4),
            "stems": _stems_table(det),
        }
        # EB-LiDAR: the clouds are not lidar frames, so the pass-through box is opened (the
        # clouds are already cut or small) and only the rest of the pipeline runs
        if np.ptp(xyz[:, 2]) < 1.0:
            t0 = time.perf_counter()
            dm = detect_stems_munjer(xyz, band_munjer)
            entry["munjer2025_no_box"] = {
                "time_s": _r(time.perf_counter() - t0),
                "n_stems": len(dm),
                "stems": _stems_table(dm),
            }
        if name == "fortls_slice":
            entry["single_side_vs_full_ring"] = single_side(xyz, det)
        out[name] = entry
    return out


def single_side(xyz: np.ndarray, full: CloudStems) -> dict[str, Any]:
    """For 4 view directions, keep the half of each ring facing the viewer and refit."""
    from scipy.spatial import cKDTree

    _, k = cKDTree(full.xy).query(xyz[:, :2])
    res: dict[str, Any] = {"views": {}}
    all_d = []
    for name, u in (
        ("+x", (1.0, 0.0)),
        ("+y", (0.0, 1.0)),
        ("-x", (-1.0, 0.0)),
        ("-y", (0.0, -1.0)),
    ):
        keep = np.sum((xyz[:, :2] - full.xy[k]) * np.array(u), axis=1) > 0
        half = detect_stems(xyz[keep])
        m = match_points(half.xy, full.xy, 0.1)
        d = half.diameter[m.pairs[:, 0]] - full.diameter[m.pairs[:, 1]]
        all_d.append(d)
        res["views"][name] = {
            "matched": m.n_matched,
            "of": len(full),
            "dbh_diff_mean_cm": _r(100 * d.mean(), 3),
            "dbh_diff_rms_cm": _r(100 * np.sqrt(np.mean(d**2)), 3),
            "dbh_diff_absmax_cm": _r(100 * np.max(np.abs(d)), 3),
        }
    d = np.concatenate(all_d)
    res["all_views_dbh_diff_rms_cm"] = _r(100 * np.sqrt(np.mean(d**2)), 3)
    res["all_views_dbh_diff_absmax_cm"] = _r(100 * np.max(np.abs(d)), 3)
    return res


def run_dendromatics(python: str, ddir: Path) -> dict[str, Any]:
    runner = Path(__file__).with_name("_dendromatics_runner.py")
    files = [str(ddir / rel) for rel in REAL.values()]
    r = subprocess.run(
        [python, str(runner), *files], capture_output=True, text=True, check=False, timeout=3000
    )
    if r.returncode != 0:
        return {"error": r.stderr[-3000:]}
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--quick", action="store_true", help="2 stands per scenario, 5 M big cloud")
    ap.add_argument("--no-big", action="store_true", help="skip the 20-million-point run")
    ap.add_argument("--big-points", type=int, default=20_000_000)
    ap.add_argument("--chunk", type=int, default=2_000_000)
    ap.add_argument(
        "--dendromatics-python",
        default=os.environ.get("DENDROMATICS_PYTHON"),
        help="a Python interpreter with dendromatics installed (optional)",
    )
    ap.add_argument(
        "--methods",
        nargs="+",
        choices=METHODS,
        default=list(METHODS),
        help="simulated-stand methods to run (default all)",
    )
    ap.add_argument(
        "--sim-only",
        action="store_true",
        help="only the simulated stands (no density sweep, big cloud or real clouds)",
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    result: dict[str, Any] = {
        "benchmark": "cloud_stems",
        "machine": {
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "note": "shared 2-core machine, loaded by other jobs: times are noisy",
        },
    }
    result["simulated"] = run_sim(args.quick, tuple(args.methods))
    if args.sim_only:
        result["total_time_s"] = _r(time.perf_counter() - t0, 1)
        print(json.dumps(result, indent=1 if not args.json else None))
        return
    result["density_sweep_ours"] = run_density(args.quick)
    if not args.no_big:
        n = 5_000_000 if args.quick else args.big_points
        result["big_cloud"] = run_big(n, args.chunk)
    ddir = find_datasets_dir(Path(__file__).resolve().parent)
    if ddir is not None and ddir.is_dir():
        result["real"] = run_real(ddir)
        if args.dendromatics_python:
            result["dendromatics"] = run_dendromatics(args.dendromatics_python, ddir)
    else:
        result["real"] = {"error": "../shared/datasets not found"}
    result["total_time_s"] = _r(time.perf_counter() - t0, 1)
    result["self_peak_rss_mb"] = _r(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 0)
    print(json.dumps(result, indent=1 if not args.json else None))


if __name__ == "__main__":
    main()
