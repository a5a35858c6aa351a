"""Benchmark of the vision-fusion area: calibration, segmentation, edges, DAIM and fusion.

Usage: python benchmarks/vision_fusion.py --json [--scenes 40] [--trials 20] [--quick]

Prints one JSON object with every scenario parameter and the measured numbers:

* calibration: held-out pixel error of G (Xue eq. 11, normalised DLT, DLT + LM, RANSAC) vs
  number of pairs at 1 px image noise and 5 mm laser noise; RANSAC with 30 % outliers; the full
  plate pipeline (scan -> edges A, B, C -> eqs. 4-6 -> image points -> G); PnP pose error;
* segmentation: trunk recall and mask IoU on the mangrove photos; images/s at 1280 x 720;
* edges: relative diameter error of Öhman's method and ours on simulated trunks;
* DAIM: centre / diameter error of the three-point arc (Munjer) and of our all-points fit;
* fusion: precision / recall / F1 of laser-only, vision-only, Xue fusion and ours on simulated
  cluttered scenes.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from typing import Any

import numpy as np

from stemmap.datasets import find_datasets_dir
from stemmap.fusion.scenes import evaluate_fusion
from stemmap.sim.camera import render_scene, simulate_plate_views, xue2018_rig
from stemmap.sim.forest import Stand
from stemmap.types import Pose2
from stemmap.vision.calibrate import (
    fit_homography,
    plate_edges_from_scan,
    reprojection_errors,
    solve_plate_points,
    solve_pnp,
)
from stemmap.vision.camera import (
    apply_homography,
    laser_plane_homography,
    project_laser_points,
    project_points,
)
from stemmap.vision.depth import DaimParams, daim_trunks
from stemmap.vision.edges import COLOUR_PCA, OHMAN2007, measure_diameter
from stemmap.vision.segment import evaluate_mangrove, segment_trunks

RIG = xue2018_rig()
G_TRUE = laser_plane_homography(RIG.camera, RIG.laser_to_camera)


def _laser_points(n: int, rng: np.random.Generator) -> np.ndarray:
    out: list[np.ndarray] = []
    while len(out) < n:
        r, a = rng.uniform(1.5, 7.0), rng.uniform(-0.5, 0.5)
        p = np.array([r * math.cos(a), r * math.sin(a)])
        uv, front = project_laser_points(p, RIG.camera, RIG.laser_to_camera)
        if front[0] and RIG.camera.in_image(uv)[0]:
            out.append(p)
    return np.asarray(out)


def _held_out(G: np.ndarray, rng: np.random.Generator) -> float:
    xy = _laser_points(200, rng)
    err = reprojection_errors(G, xy, apply_homography(G_TRUE, xy))
    return float(np.sqrt(np.mean(err**2)))


def bench_calibration(trials: int, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    px_noise, laser_noise = 1.0, 0.005
    methods = ("xue2018", "dlt", "dlt_refined", "ransac")
    counts = (7, 14, 28, 56)
    table: dict[str, dict[str, float]] = {m: {} for m in methods}
    for n in counts:
        errs: dict[str, list[float]] = {m: [] for m in methods}
        for _ in range(trials):
            xy = _laser_points(n, rng)
            uv = apply_homography(G_TRUE, xy) + rng.normal(0, px_noise, (n, 2))
            xy_m = xy + rng.normal(0, laser_noise, xy.shape)
            for m in methods:
                opts: dict[str, Any] = {"rng": rng} if m == "ransac" else {}
                fit = fit_homography(xy_m, uv, m, **opts)
                errs[m].append(_held_out(fit.G, rng) if fit else math.inf)
        for m in methods:
            table[m][str(n)] = round(float(np.median(errs[m])), 3)
    # Effect of noise at 28 pairs: image noise (laser noise 5 mm) and laser noise (image 1 px).
    by_noise: dict[str, dict[str, float]] = {"xue2018": {}, "dlt_refined": {}}
    for label, pxn, lzn in (
        ("px0.25_laser0.005", 0.25, 0.005),
        ("px1_laser0.005", 1.0, 0.005),
        ("px4_laser0.005", 4.0, 0.005),
        ("px1_laser0", 1.0, 0.0),
        ("px1_laser0.02", 1.0, 0.02),
    ):
        e2: dict[str, list[float]] = {m: [] for m in by_noise}
        for _ in range(trials):
            xy = _laser_points(28, rng)
            uv = apply_homography(G_TRUE, xy) + rng.normal(0, pxn, (28, 2))
            xy_m = xy + rng.normal(0, lzn, xy.shape)
            for m in by_noise:
                fit = fit_homography(xy_m, uv, m)
                e2[m].append(_held_out(fit.G, rng) if fit else math.inf)
        for m in by_noise:
            by_noise[m][label] = round(float(np.median(e2[m])), 3)
    # RANSAC vs plain DLT with 30 % gross outliers (40 pairs).
    out_r, out_d = [], []
    for _ in range(trials):
        xy = _laser_points(40, rng)
        uv = apply_homography(G_TRUE, xy) + rng.normal(0, 0.5, (40, 2))
        bad = rng.choice(40, 12, replace=False)
        uv[bad] += rng.uniform(40, 200, (12, 2)) * rng.choice([-1, 1], (12, 2))
        out_r.append(_held_out(fit_homography(xy, uv, "ransac", rng=rng).G, rng))
        out_d.append(_held_out(fit_homography(xy, uv, "dlt_refined").G, rng))
    # Plate pipeline: 7 poses (Xue §3.1) -> 21 pairs.
    plate_err: dict[str, list[float]] = {"xue2018": [], "dlt_refined": []}
    edge_err, plate_coord_err = [], []
    for _ in range(max(3, trials // 4)):
        views = simulate_plate_views(RIG, 7, rng=rng)
        xy_l, uv_l = [], []
        for v in views:
            abc, ok, _ = plate_edges_from_scan(v.scan.points())
            if not ok:
                continue
            edge_err.extend(np.linalg.norm(abc - v.abc_laser, axis=1).tolist())
            lab = float(np.linalg.norm(abc[0] - abc[1]))
            lbc = float(np.linalg.norm(abc[1] - abc[2]))
            pp = solve_plate_points(lab, lbc)
            if not pp:
                continue
            plate_coord_err.extend(np.linalg.norm(pp.as_array() - v.abc_plate, axis=1).tolist())
            P = v.plate_to_laser3d(pp.as_array(), 0.2)
            uv, _ = project_points(RIG.laser_to_camera.apply(P), RIG.camera)
            xy_l.append(abc)
            uv_l.append(uv + rng.normal(0, 0.5, uv.shape))  # reading the plate marks
        xy_a, uv_a = np.vstack(xy_l), np.vstack(uv_l)
        for m in plate_err:
            fit = fit_homography(xy_a, uv_a, m)
            plate_err[m].append(_held_out(fit.G, rng) if fit else math.inf)
    # PnP with known intrinsics: 3D points (laser plane + vertical structure), 0.5 px noise.
    rot, trans, rms = [], [], []
    for _ in range(trials):
        xy = _laser_points(30, rng)
        P = np.column_stack((xy, rng.uniform(-0.5, 1.0, 30)))
        uv, _ = project_points(RIG.laser_to_camera.apply(P), RIG.camera)
        k = RIG.camera.in_image(uv)
        fit = solve_pnp(P[k], uv[k] + rng.normal(0, 0.5, (int(k.sum()), 2)), RIG.camera)
        if fit and fit.transform is not None:
            rot.append(math.degrees(fit.transform.rotation_angle_to(RIG.laser_to_camera)))
            trans.append(float(np.linalg.norm(fit.transform.t - RIG.laser_to_camera.t)))
            rms.append(fit.rms_px)
    return {
        "params": {
            "image": [RIG.camera.width, RIG.camera.height],
            "hfov_deg": 60.0,
            "tilt_deg": 15.0,
            "camera_above_laser_m": 0.3,
            "pixel_noise_px": px_noise,
            "laser_noise_m": laser_noise,
            "laser_points_range_m": [1.5, 7.0],
            "trials": trials,
            "held_out_points": 200,
        },
        "heldout_rms_px_median_by_pairs": table,
        "heldout_rms_px_median_28_pairs_by_noise": by_noise,
        "ransac_30pct_outliers_heldout_px_median": round(float(np.median(out_r)), 3),
        "dlt_refined_30pct_outliers_heldout_px_median": round(float(np.median(out_d)), 3),
        "plate_pipeline": {
            "poses": 7,
            "scanner_deg": 0.25,
            "image_mark_noise_px": 0.5,
            "edge_error_m_median": round(float(np.median(edge_err)), 4),
            "edge_error_m_max": round(float(np.max(edge_err)), 4),
            "plate_coord_error_units_median": round(float(np.median(plate_coord_err)), 4),
            "plate_coord_error_units_max": round(float(np.max(plate_coord_err)), 4),
            "heldout_px_median": {m: round(float(np.median(v)), 3) for m, v in plate_err.items()},
        },
        "pnp": {
            "points": 30,
            "pixel_noise_px": 0.5,
            "rotation_error_deg_median": round(float(np.median(rot)), 4),
            "translation_error_m_median": round(float(np.median(trans)), 4),
            "rms_px_median": round(float(np.median(rms)), 3),
        },
    }


def bench_segmentation(quick: bool) -> dict[str, Any]:
    sc = render_scene(
        Stand(np.array([[4.0, 0.5], [6.0, -1.5], [8.0, 2.0]]), np.array([0.3, 0.2, 0.25])),
        Pose2(0, 0, 0),
        RIG,
        rng=0,
    )
    n = 10 if quick else 50
    segment_trunks(sc.image)
    t0 = time.perf_counter()
    for _ in range(n):
        segment_trunks(sc.image)
    ips = n / (time.perf_counter() - t0)
    out: dict[str, Any] = {"images_per_s_1280x720": round(ips, 1), "timing_images": n}
    ds = find_datasets_dir()
    if ds is not None and (ds / "mangrove").is_dir():
        for preset in ("xue2018", "full_frame"):
            r = evaluate_mangrove(ds / "mangrove", preset, width=1152)
            out[f"mangrove_{preset}"] = {k: round(v, 4) for k, v in r.items()}
        out["mangrove_note"] = (
            "photos downscaled 4608 -> 1152 px (INTER_AREA); recall = trunks with >= 50 % of "
            "their polygon covered; no per-image tuning"
        )
    else:
        out["mangrove"] = "dataset not found"
    return out


def bench_edges_daim(seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    rig = xue2018_rig(width=640, height=360)
    errs: dict[str, list[float]] = {"ohman2007": [], "ours": [], "ohman2007_pinhole": []}
    fails = {"ohman2007": 0, "ours": 0}
    daim: dict[str, list[float]] = {"three_point": [], "ours": []}
    daim_d: dict[str, list[float]] = {"three_point": [], "ours": []}
    for k in range(16):
        d = float(rng.uniform(0.15, 0.45))
        r = float(rng.uniform(2.5, 9.0))
        a = float(rng.uniform(-0.4, 0.4))
        xy = np.array([[r * math.cos(a), r * math.sin(a)]])
        sc = render_scene(Stand(xy, np.array([d])), Pose2(0, 0, 0), rig, rng=k)
        if not sc.truth.tree_visible[0]:
            continue
        bx = sc.truth.tree_uv_box[0]
        box = (bx[0] - bx[2], bx[1] + bx[3] // 4, 3 * bx[2], bx[3] // 2)
        rng_m = r - d / 2
        for name, p in (("ohman2007", OHMAN2007), ("ours", COLOUR_PCA)):
            e = measure_diameter(
                sc.image,
                box,
                rng_m,
                (0.1, 0.6),
                rig.camera,
                p,
                laser_to_camera=rig.laser_to_camera,
            )
            if not e:
                fails[name] += 1
                continue
            if name == "ohman2007":
                errs[name].append(abs(e.diameter_pinhole - d) / d)
                errs["ohman2007_pinhole"].append(abs(e.diameter_pinhole - d) / d)
            else:
                errs[name].append(abs(e.diameter - d) / d)
        depth = sc.depth * (1 + rng.normal(0, 0.005, sc.depth.shape))
        for fit in daim:
            obs = daim_trunks(
                depth,
                rig.camera,
                sc.truth.tree_uv_box[:1],
                camera_to_body=rig.laser_to_camera.inverse(),
                params=DaimParams(fit=fit),
            )
            if len(obs):
                daim[fit].append(float(np.hypot(*(obs.centers[0] - xy[0]))))
                daim_d[fit].append(abs(float(obs.diameters[0]) - d))
    del errs["ohman2007_pinhole"]
    return {
        "edges": {
            "params": {
                "trees": 16,
                "dbh_m": [0.15, 0.45],
                "range_m": [2.5, 9.0],
                "image": [640, 360],
                "width_bounds_m": [0.1, 0.6],
            },
            "relative_diameter_error_median": {
                k: round(float(np.median(v)), 4) if v else None for k, v in errs.items()
            },
            "relative_diameter_error_p90": {
                k: round(float(np.quantile(v, 0.9)), 4) if v else None for k, v in errs.items()
            },
            "failures": fails,
            "note": "ohman2007 = luma, edge-count projection, 1 strip, pinhole conversion; "
            "ours = colour PCA, gradient-weighted projection, 4 strips, cylinder model",
        },
        "daim": {
            "params": {"depth_noise_rel": 0.005, "trees": 16},
            "centre_error_m_median": {k: round(float(np.median(v)), 4) for k, v in daim.items()},
            "diameter_error_m_median": {
                k: round(float(np.median(v)), 4) for k, v in daim_d.items()
            },
            "found": {k: len(v) for k, v in daim.items()},
        },
    }


def bench_fusion(scenes: int) -> dict[str, Any]:
    res = evaluate_fusion(range(scenes), rig=RIG)
    return {
        "params": {
            "scenes": scenes,
            "seeds": [0, scenes - 1],
            "trees_per_scene": 8,
            "bushes_per_scene": 4,
            "bark_coloured_posts_per_scene": 2,
            "walls_per_scene": 1,
            "depth_m": [2.5, 12.0],
            "laser_deg": 0.5,
            "laser_noise_m": 0.01,
            "bpa_preset_xue": "forest (w 0.08-0.6 m, dw 0.03 m, k1 = k2 = 0.9)",
            "segmentation": "xue2018 preset",
            "eligible": "trees hit by >= 3 beams and visible in the image",
        },
        **{
            k: {
                "tp": c.tp,
                "fp": c.fp,
                "fn": c.fn,
                "precision": round(c.precision, 4),
                "recall": round(c.recall, 4),
                "f1": round(c.f1, 4),
            }
            for k, c in res.items()
        },
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="fewer trials / scenes")
    a = ap.parse_args()
    if a.quick:
        a.scenes, a.trials = min(a.scenes, 8), min(a.trials, 5)
    t0 = time.perf_counter()
    out = {
        "benchmark": "vision_fusion",
        "python": platform.python_version(),
        "seed": a.seed,
        "calibration": bench_calibration(a.trials, a.seed),
        "segmentation": bench_segmentation(a.quick),
        **bench_edges_daim(a.seed),
        "fusion": bench_fusion(a.scenes),
    }
    out["wall_time_s"] = round(time.perf_counter() - t0, 1)
    out["note"] = "timings measured on a shared 2-core machine under load from other jobs"
    if a.json:
        print(json.dumps(out))
    else:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
