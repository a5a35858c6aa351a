"""2D laser trunk detection: accuracy per circle-fit method, paper presets, and speed.

Scenario (every parameter is echoed in the JSON): a simulated stand with clutter (bushes,
branches, a wall, a fence, rocks), a SICK LMS-like scanner (0.5 deg, 180 deg, 1 cm range noise,
0.25 deg beam divergence with mixed pixels), a drive through the stand. Each scan is scored
against the truth in the sensor frame with ``stemmap.eval.detection.scan_detection_metrics``:
a tree counts if it has >= 5 returns, DBH >= 10 cm and lies within 15 m; detections whose
centre lies beyond 15.5 m are not scored. Issue 11's simulated accuracy targets (recall,
precision >= 0.95; DBH RMSE <= 1.2 cm at <= 5 m) are each reported this run's seed alone
(``meets_targets.<target>_this_seed``), on the mean over ``--precision-seeds`` (default 1-10;
recall and precision on each of the two simulated drives, this 400-scan one and the ``stemmap
demo`` drive: ``<target>_mean_over_seeds``, what ``meets_targets.all`` reads, the rule of
precision since Dec 3 and of the ``real_geometry.py`` grid's admission since Dec 5) and on
every one of those seeds (``<target>_every_seed``, what ``meets_targets.all_every_seed``
reads): :func:`seed_verdicts`. Which reading the issue means is the owner's decision
(docs/algorithms/scan-detection.md, "Per seed or on the mean").

Usage: python benchmarks/scan_detection.py --json [--scans 400] [--seed 1] [--no-real] [--crlb]
       python benchmarks/scan_detection.py --speed-set '{"sigma_from_scan": true}' --rounds 5
       python benchmarks/scan_detection.py --seeds 1 2 3 [--set '{...}'] [--worst 5]
       python benchmarks/scan_detection.py --speed-seeds 1 2 3

``--seeds``: issue 11's simulated targets over seeds (each a new stand, clutter and drive; the
400-scan drive and the ``stemmap demo`` drive of ``_scan_sim.simulated_precision_seeds``): per
seed and mean / smallest / largest recall, precision, DBH RMSE and bias at <= 5 m, the verdict
of each of the three targets on the mean and on every seed (``verdicts``, :func:`seed_verdicts`),
and per seed the DBH RMSE split into whole and partial trunks with the trees that weigh most in
it, and the Cramer-Rao bound over the same matched pairs (``crlb_same_pairs_cm``).
``--speed-seeds``: scans per CPU second of the default on each seed's drive (tiled to
``--batch`` scans, best of 3), each next to seed 1's batch timed in the same turn (the ratio
is what a loaded machine leaves comparable).
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # one core, as the targets are stated
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import hashlib
import json
import math
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from _scan_fits import crlb_diameter_var, load_rings, run_real_geometry  # of scan_fits_real.py
from _scan_sim import (  # shared with real_geometry.py
    SCENARIO,
    SIM_PRECISION_MIN,
    SIM_SEEDS,
    benchmark_drive,
    edge_status,
    make_run,
    score,
    set_sim_hit_fraction,
    simulated_precision_seeds,
    tree_errors,
    worst_trees,
)
from sim_dbh_trunks import pair_bounds
from stemmap.datasets import find_datasets_dir
from stemmap.eval.matching import match_points
from stemmap.scan.detect import PRESETS, DetectorConfig, ScanTrunkDetector
from stemmap.sim.scanner import ScannerModel, simulate_scans
from stemmap.types import LaserScan, ScanBatch, StemObservations

FIT_METHODS = ("kasa", "fletcher_reeves", "three_point", "chord_width", "ours")

#: The simulated targets. DBH RMSE at <= 5 m and the speed are issue 11's ("simulated targets
#: keep holding": 1.2 cm, 25 000 scans/s; until Dec 3 this held the earlier 1.0 cm and 20 000);
#: the 5-10 m, bias and latency rows are the first issue's.
TARGETS = {
    "recall_min": 0.95,
    "precision_min": SIM_PRECISION_MIN,  # 0.95, the real_geometry.py grid's admission too
    "dbh_rmse_cm_le5_max": 1.2,
    "dbh_rmse_cm_5_10_max": 2.5,
    "abs_dbh_bias_cm_max": 0.5,
    "scans_per_second_361_min": 25000,
    "latency_ms_1081_max": 0.5,
}


def timed(fn: Any, repeats: int) -> float:
    """Best wall time of ``repeats`` calls (seconds)."""
    return timed_both(fn, repeats)[0]


def timed_both(fn: Any, repeats: int) -> tuple[float, float]:
    """Best wall time and best process CPU time of ``repeats`` calls (seconds). On a shared
    machine the CPU time is the steadier of the two (time spent waiting for a core is not
    counted)."""
    best_wall = best_cpu = math.inf
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        best_wall = min(best_wall, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best_wall, best_cpu


def speed(run: Any, n_batch: int, seed: int) -> dict[str, Any]:
    det = ScanTrunkDetector("stemmap")
    scans = run.scans
    big = _batch_of(run, n_batch)
    det.detect_batch(ScanBatch.from_scans([big[0]]))  # JIT warm-up
    load_before = os.getloadavg()[0]
    t_batch, c_batch = timed_both(lambda: det.detect_batch(big), 3)
    n_obs = len(det.detect_batch(big))
    kasa = ScanTrunkDetector(DetectorConfig.preset("stemmap", fit_method="kasa"))
    t_kasa = timed(lambda: kasa.detect_batch(big), 3)
    # one 1081-beam scan: 270 deg at 0.25 deg (LMS1xx / UTM-30LX class)
    m1081 = ScannerModel(
        angle_min=math.radians(-135.0),
        angle_max=math.radians(135.0),
        angle_increment=math.radians(0.25),
        range_max=30.0,
        range_noise=0.01,
    )
    poses = run.true_poses.poses[:: max(1, len(run.true_poses.poses) // 20)][:20]
    b1081, _, _ = simulate_scans(run.stand, poses, m1081, rng=seed)
    one = [b1081[i] for i in range(len(b1081))]
    for s in one[:3]:
        det.detect(s)
    lat, lat_cpu = [], []
    for s in one:
        w, c = timed_both(lambda s=s: det.detect(s), 20)
        lat.append(w)
        lat_cpu.append(c)
    # CPU time of one call is below the clock's resolution on some systems: also time the
    # whole set of scans, 20 rounds
    c0 = time.process_time()
    for _ in range(20):
        for s in one:
            det.detect(s)
    lat_cpu_mean = (time.process_time() - c0) / (20 * len(one))
    return {
        "n_beams": int(scans.n_beams),
        "batch_scans": n_batch,
        "observations_in_batch": n_obs,
        "scans_per_second_361": round(n_batch / t_batch),
        "scans_per_second_361_cpu": round(n_batch / c_batch),
        "scans_per_second_361_kasa": round(n_batch / t_kasa),
        "latency_ms_1081": round(1e3 * float(np.median(lat)), 4),
        "latency_ms_1081_max": round(1e3 * float(np.max(lat)), 4),
        "latency_ms_1081_cpu_mean": round(1e3 * lat_cpu_mean, 4),
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "latency_scans": len(one),
        "threads": 1,
        "method": "best of 3 (batch) / best of 20 per scan, median over scans (latency); "
        "_cpu: process CPU time (batch: best of 3; latency: mean over 20 rounds of all scans)",
    }


def _batch_of(run: Any, n_batch: int) -> ScanBatch:
    """The drive's scans tiled to ``n_batch`` scans (the speed batch)."""
    scans = run.scans
    reps = math.ceil(n_batch / len(scans))
    return ScanBatch(
        np.tile(scans.ranges, (reps, 1))[:n_batch],
        np.arange(n_batch, dtype=np.float64),
        scans.angle_min,
        scans.angle_increment,
        scans.range_min,
        scans.range_max,
    )


def detections_digest(obs: StemObservations) -> str:
    """SHA-256 of every detection's arrays (bit for bit): equal digests = identical output."""
    h = hashlib.sha256()
    for a in (obs.centers, obs.radii, obs.covs, obs.n_points, obs.arc_deg, obs.widths):
        h.update(np.ascontiguousarray(a).tobytes())
    for a in (obs.quality, obs.index, obs.times):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def speed_compare(run: Any, n_batch: int, overrides: dict[str, Any], rounds: int) -> dict[str, Any]:
    """The stemmap preset against the preset with ``overrides`` on the same batch, in one
    process, alternating, ``rounds`` rounds of best-of-3 process-CPU times: on a loaded machine
    only the ratio within a round is comparable. Also the digest of each one's detections."""
    big = _batch_of(run, n_batch)
    dets = {
        "default": ScanTrunkDetector("stemmap"),
        "set": ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides)),
    }
    out: dict[str, Any] = {"overrides": overrides, "batch_scans": n_batch, "rounds": rounds}
    for name, det in dets.items():
        obs = det.detect_batch(big)  # JIT warm-up, and the output compared
        out[f"{name}_detections"] = len(obs)
        out[f"{name}_digest"] = detections_digest(obs)
    load_before = os.getloadavg()[0]
    sps: dict[str, list[int]] = {"default": [], "set": []}
    for _ in range(rounds):
        for name, det in dets.items():
            _, cpu = timed_both(lambda det=det: det.detect_batch(big), 3)
            sps[name].append(round(n_batch / cpu))
    ratio = [round(a / b, 4) for a, b in zip(sps["set"], sps["default"], strict=True)]
    out.update(
        {
            "default_scans_per_cpu_second": sps["default"],
            "set_scans_per_cpu_second": sps["set"],
            "ratio_set_to_default": ratio,
            "median_ratio": float(np.median(ratio)),
            "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
    )
    return out


def accuracy_over_seeds(
    seeds: list[int], overrides: dict[str, Any], n_worst: int
) -> dict[str, Any]:
    """:func:`_scan_sim.simulated_precision_seeds` (recall, precision both drives; DBH RMSE /
    bias <= 5 m on the benchmark drive) plus, per seed, the <= 5 m DBH RMSE split into whole
    and partial trunks, the ``n_worst`` trees with the largest share of its squares
    (:func:`_scan_sim.worst_trees`) and the drive's Cramér-Rao bound at <= 5 m with footprint
    edges, all eligible trunks (``crlb_cm``) and whole trunks (``crlb_whole_cm``):
    :func:`benchmark_crlb`, scan-fits.md; and the bound of each matched pair's own scan over
    the same pairs the RMSE is taken on (``crlb_same_pairs_cm``: the RMSE an efficient fit of
    these very pairs would have, ``sim_dbh_trunks.pair_bounds``) with the share of the sum of
    squares held by the ``n_worst`` trees listed (``worst_sse_share``). ``verdicts``: each
    target on the mean and on every seed (:func:`seed_verdicts`)."""
    out = simulated_precision_seeds(overrides, seeds)
    out["verdicts"] = seed_verdicts(out)
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides))
    by_seed: dict[str, Any] = {}
    for s in seeds:
        run = benchmark_drive(s)
        err = tree_errors(det.detect_batch(run.scans), run)
        row = worst_trees(err, n=n_worst)
        bound = benchmark_crlb(run)
        row["crlb_cm"] = bound["crlb_footprint_edges_dbh_rmse_cm_0_5"]
        row["crlb_whole_cm"] = bound["crlb_footprint_edges_whole_trunks_dbh_rmse_cm_0_5"]
        pb = pair_bounds(run, err, err["range"] < 5.0)
        pb = pb[np.isfinite(pb)]
        row["crlb_same_pairs_cm"] = round(float(np.sqrt(np.mean(pb**2))), 3) if pb.size else None
        row["worst_sse_share"] = round(sum(float(t["sse_share"]) for t in row["worst"]), 3)
        by_seed[str(s)] = row
    out["dbh_le5_by_seed"] = by_seed
    return out


def speed_over_seeds(seeds: list[int], n_batch: int) -> dict[str, Any]:
    """Scans per CPU second of the ``stemmap`` preset on each seed's 400-scan drive tiled to
    ``n_batch`` scans (best of 3), and of seed 1's batch timed right before and right after it
    in the same process (the reference, the better of the two: on a shared machine the ratio is
    the comparable number, and timing it on both sides keeps the order out of the ratio)."""
    det = ScanTrunkDetector("stemmap")
    ref = _batch_of(benchmark_drive(1), n_batch)
    det.detect_batch(ref)  # JIT warm-up
    load_before = os.getloadavg()[0]
    rows = []
    for s in seeds:
        big = _batch_of(benchmark_drive(s), n_batch)
        _, c_before = timed_both(lambda: det.detect_batch(ref), 3)
        _, c = timed_both(lambda big=big: det.detect_batch(big), 3)
        _, c_after = timed_both(lambda: det.detect_batch(ref), 3)
        c_ref = min(c_before, c_after)
        rows.append(
            {
                "seed": int(s),
                "scans_per_cpu_second": round(n_batch / c),
                "reference_scans_per_cpu_second": round(n_batch / c_ref),
                "ratio_to_reference": round(c_ref / c, 4),
                "detections_per_scan": round(len(det.detect_batch(big)) / n_batch, 2),
                "returns_per_scan": round(float(np.isfinite(big.ranges).sum()) / n_batch, 1),
            }
        )
    sps = [r["scans_per_cpu_second"] for r in rows]
    ref_sps = [r["reference_scans_per_cpu_second"] for r in rows]
    return {
        "batch_scans": n_batch,
        "n_beams": int(ref.n_beams),
        "per_seed": rows,
        "scans_per_cpu_second_min": min(sps),
        "scans_per_cpu_second_median": float(np.median(sps)),
        "reference_scans_per_cpu_second_min": min(ref_sps),
        "reference_scans_per_cpu_second_median": float(np.median(ref_sps)),
        "ratio_to_reference_median": float(np.median([r["ratio_to_reference"] for r in rows])),
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "threads": 1,
        "method": "process CPU time, best of 3 per batch; reference = seed 1's batch, timed "
        "before and after each seed's (the better of the two)",
    }


REAL: dict[str, Any] = {
    "dataset": "fortls_slice/diameters.laz (TLS slice 1.2-1.4 m, ~20 trunks as full rings)",
    "reference": "ring fit of _scan_fits.load_rings (full ring, geometric)",
    "scanner": "virtual nearest-return scanner: 360 deg, one beam per bin, the nearest slice "
    "point whose bearing lies within the beam footprint, reported at the beam's nominal bearing",
    "angle_increment_deg": 0.5,
    "footprint_deg": 0.5,
    "range_noise_m": 0.01,
    "vantage_radii_m": [0.0, 5.0, 10.0],
    "vantage_bearings_deg": [0, 45, 90, 135, 180, 225, 270, 315],
    "vantage_min_clearance_m": 0.3,
    "min_returns": 5,
    "max_range_m": 15.0,
    "gate_m": 0.5,
}


def virtual_laser_scan(
    xy: np.ndarray,
    vantage: np.ndarray,
    *,
    angle_increment: float,
    footprint: float,
    noise: float,
    rng: np.random.Generator,
    range_max: float = 30.0,
) -> tuple[LaserScan, np.ndarray]:
    """A 360 deg scan of a 2D point set: beam k (bearing -pi + (k + 1/2) * increment) returns the
    nearest point within +-footprint/2 of its bearing, plus N(0, noise) range noise.

    Returns the scan and, per beam, the index of the point it returned (-1 = none)."""
    n = round(2 * math.pi / angle_increment)
    q = xy - vantage
    rho = np.hypot(q[:, 0], q[:, 1])
    u = (np.arctan2(q[:, 1], q[:, 0]) + math.pi) / angle_increment
    beam = np.floor(u).astype(np.int64) % n
    inside = np.abs(u - np.floor(u) - 0.5) * angle_increment <= footprint / 2 + 1e-12
    cand = np.flatnonzero(inside)
    order = cand[np.lexsort((rho[cand], beam[cand]))]
    first = np.ones(order.shape[0], dtype=bool)
    first[1:] = beam[order[1:]] != beam[order[:-1]]
    nearest = order[first]
    ranges = np.full(n, np.inf)
    ranges[beam[nearest]] = rho[nearest] + rng.normal(0.0, noise, nearest.shape[0])
    src = np.full(n, -1, dtype=np.int64)
    src[beam[nearest]] = nearest
    scan = LaserScan(ranges, -math.pi + angle_increment / 2, angle_increment, range_max=range_max)
    return scan, src


def run_real_detection(datasets_dir: Path, seed: int) -> dict[str, Any]:
    """End-to-end detection on virtual scans of the real TLS slice, per fit method, without and
    with the footprint correction; DBH error against each trunk's full-ring reference."""
    xy, labels, refs = load_rings(datasets_dir)
    ref = np.array([[r["x"], r["y"], r["diameter"]] for r in refs])
    inc = math.radians(REAL["angle_increment_deg"])
    foot = math.radians(REAL["footprint_deg"])
    vantages = [np.zeros(2)]
    for rad in REAL["vantage_radii_m"][1:]:
        for b in REAL["vantage_bearings_deg"]:
            vantages.append(rad * np.array([math.cos(math.radians(b)), math.sin(math.radians(b))]))
    rng = np.random.default_rng(seed)
    scans = []
    for v in vantages:
        gap = np.hypot(ref[:, 0] - v[0], ref[:, 1] - v[1]) - ref[:, 2] / 2
        if np.min(gap) < REAL["vantage_min_clearance_m"]:
            continue
        scan, src = virtual_laser_scan(
            xy, v, angle_increment=inc, footprint=foot, noise=REAL["range_noise_m"], rng=rng
        )
        hit = labels[src[src >= 0]]
        counts = np.bincount(hit[hit >= 0], minlength=ref.shape[0])
        local = ref[:, :2] - v
        elig = (counts >= REAL["min_returns"]) & (np.hypot(*local.T) <= REAL["max_range_m"])
        scans.append((scan, local, elig))
    out: dict[str, Any] = {
        "scenario": {**REAL, "seed": seed, "n_scans": len(scans), "n_trunks": len(refs)},
        "trunk_dbh_cm_range": [round(100 * ref[:, 2].min(), 1), round(100 * ref[:, 2].max(), 1)],
    }
    for corr in (False, True):
        section: dict[str, Any] = {}
        for m in FIT_METHODS:
            # the virtual scanner reports the nearest return (first echo), not a footprint
            # average: no averaging-scanner edge model (beam_divergence_deg = 0)
            cfg = DetectorConfig.preset(
                "stemmap",
                fit_method=m,
                beam_footprint_deg=REAL["footprint_deg"] if corr else 0.0,
                beam_divergence_deg=0.0,
            )
            det = ScanTrunkDetector(cfg)
            errs: list[float] = []
            n_elig = fa = 0
            for scan, local, elig in scans:
                obs = det.detect(scan)
                mt = match_points(obs.centers, local, REAL["gate_m"])
                ok = elig[mt.pairs[:, 1]] if mt.n_matched else np.zeros(0, dtype=bool)
                for (i, j), good in zip(mt.pairs, ok, strict=True):
                    if good:
                        errs.append(2 * obs.radii[i] - ref[j, 2])
                n_elig += int(elig.sum())
                near = np.hypot(*obs.centers.T) <= REAL["max_range_m"] if len(obs) else []
                fa += int(np.sum(np.isin(np.flatnonzero(near), mt.unmatched_detections)))
            e = 100 * np.asarray(errs)
            section[m] = {
                "eligible": n_elig,
                "detected": len(errs),
                "recall": round(len(errs) / max(n_elig, 1), 4),
                "unmatched_detections": fa,
                "dbh_rmse_cm": round(float(np.sqrt(np.mean(e**2))), 3) if e.size else None,
                "dbh_bias_cm": round(float(np.mean(e)), 3) if e.size else None,
                "dbh_median_abs_cm": round(float(np.median(np.abs(e))), 3) if e.size else None,
            }
        out["footprint_corrected" if corr else "uncorrected"] = section
    return out


def real_geometry(seed: int) -> dict[str, Any] | None:
    ddir = find_datasets_dir(Path(__file__).resolve().parent)
    if ddir is None:
        return None
    res: dict[str, Any] = run_real_geometry(ddir)
    return res


def benchmark_crlb(run: Any) -> dict[str, Any]:
    """Cramer-Rao bound on the DBH error for this drive's own geometry (docs: scan-fits.md).

    For every eligible tree of every scan (the scorer's rules) the returns are the beams whose
    ground truth is that tree and whose range is the trunk's (within 0.1 m: mixed pixels that
    blend in the background are not trunk returns); each side is a silhouette edge unless the
    beam beyond hit a nearer object or lies outside the field of view. Fisher information of
    range noise on those returns plus Gaussian tangent priors: std 1/sqrt(12) beams, or
    (1 - 2h)/sqrt(12) where the beam beyond returned from behind the trunk (background: the
    tangent is in the gap between two footprints, h = half the footprint in beams). RMS of the
    bound per range bin, cm; also over whole trunks (both edges visible) only. The
    ``crlb_footprint_edges`` keys (with background narrowing) model the two edge returns as the
    footprint-averaged ranges the scanner reports (the ours fit's edge model) instead of thin
    rays, whose grazing range overstates what an averaging scanner's edge return tells."""
    sc = SCENARIO["scoring"]
    scans = run.scans
    inc = abs(scans.angle_increment)
    h = run.scanner.beam_divergence / (2.0 * inc)
    ang = scans.angles
    poses = run.true_poses.poses
    cth, sth = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    sigma = run.scanner.range_noise
    var: dict[str, list[float]] = {"0_5": [], "5_10": []}
    var_bg: dict[str, list[float]] = {"0_5": [], "5_10": []}
    var_fp: dict[str, list[float]] = {"0_5": [], "5_10": []}
    foot = run.scanner.beam_divergence
    whole: dict[str, list[bool]] = {"0_5": [], "5_10": []}
    for k in range(len(scans)):
        hit = run.hit_ids[k]
        for j in np.unique(hit[hit >= 0]):
            beams = np.flatnonzero(hit == j)
            dbh = run.stand.diameters[j]
            if beams.shape[0] < sc["min_returns"] or dbh < sc["min_dbh_m"]:
                continue
            d = run.stand.trees_xy[j] - poses[k, :2]
            c = np.array([cth[k] * d[0] + sth[k] * d[1], -sth[k] * d[0] + cth[k] * d[1]])
            dist = float(np.hypot(*c))
            key = "0_5" if dist <= 5.0 else "5_10" if dist <= 10.0 else None
            if key is None:
                continue
            std = np.full(2, 1.0 / math.sqrt(12.0)) * inc
            std_bg = std.copy()
            for side, st in enumerate(edge_status(scans.ranges[k], beams, dist, dbh)):
                if st in ("fov", "occluded"):
                    std[side] = std_bg[side] = math.inf  # no tangent seen on that side
                elif st == "background" and 0.0 < h < 0.5:
                    std_bg[side] = (1.0 - 2.0 * h) / math.sqrt(12.0) * inc
            r = dbh / 2.0
            th = ang[beams]
            # a return carries the trunk's range unless it blends in a background (a mixed
            # pixel with something behind: tens of cm off); footprint-averaged trunk-only edge
            # returns are within ~1.5 cm of the centre ray's range
            u = np.column_stack((np.cos(th), np.sin(th)))
            bb = u @ c
            rho_true = bb - np.sqrt(np.maximum(bb * bb - (c @ c - r * r), 0.0))
            th = th[np.abs(scans.ranges[k, beams] - rho_true) < 0.1]
            if th.shape[0] < 3:
                continue
            var[key].append(crlb_diameter_var(c, r, th, sigma, std))
            var_bg[key].append(crlb_diameter_var(c, r, th, sigma, std_bg))
            var_fp[key].append(crlb_diameter_var(c, r, th, sigma, std_bg, footprint=foot))
            whole[key].append(bool(np.all(np.isfinite(std))))

    def rms(v: list[float], sel: list[bool] | None = None) -> float | None:
        a = np.asarray(v)
        if sel is not None:
            a = a[np.asarray(sel, dtype=bool)]
        a = a[np.isfinite(a)]
        return round(100.0 * math.sqrt(float(np.mean(a))), 3) if a.size else None

    out: dict[str, Any] = {
        "model": "range noise on the returns + Gaussian tangent priors (scan-fits.md)"
    }
    for k in var:
        out[f"crlb_dbh_rmse_cm_{k}"] = rms(var[k])
        out[f"crlb_with_background_dbh_rmse_cm_{k}"] = rms(var_bg[k])
        out[f"crlb_whole_trunks_dbh_rmse_cm_{k}"] = rms(var[k], whole[k])
        out[f"crlb_whole_trunks_with_background_dbh_rmse_cm_{k}"] = rms(var_bg[k], whole[k])
        out[f"crlb_footprint_edges_dbh_rmse_cm_{k}"] = rms(var_fp[k])
        out[f"crlb_footprint_edges_whole_trunks_dbh_rmse_cm_{k}"] = rms(var_fp[k], whole[k])
        out[f"n_{k}"] = len(var[k])
        out[f"n_whole_{k}"] = int(np.sum(whole[k]))
    return out


#: The two simulated drives of :func:`_scan_sim.simulated_precision`.
DRIVES = ("benchmark", "demo")


def seed_verdicts(over_seeds: dict[str, Any]) -> dict[str, Any]:
    """Issue 11's three simulated accuracy targets over the seeds of ``over_seeds``
    (:func:`_scan_sim.simulated_precision_seeds`), each read both ways the docs discuss:

    - ``met_on_mean``: the mean over the seeds >= / <= the target (precision and recall: each
      drive's mean; DBH RMSE at <= 5 m: the mean of the benchmark drive's per-seed RMSE), the
      rule of the ``real_geometry.py`` grid's admission (:func:`_scan_sim.admitted_over_seeds`)
      and of precision since Dec 3;
    - ``met_every_seed``: every seed keeps it on its own (``failing_seeds`` lists those that do
      not; recall and precision: on either drive).

    Per target also the mean / smallest / largest the verdicts read (DBH: and pooled over every
    pair). Which reading the issue means is the owner's decision (scan-detection.md, "Per seed
    or on the mean"); this reports both, the same numbers."""
    rows = over_seeds["per_seed"]
    out: dict[str, Any] = {"seeds": over_seeds["seeds"]}
    for key, lo in (("recall", TARGETS["recall_min"]), ("precision", TARGETS["precision_min"])):
        means = {d: float(np.mean([float(r[d][key]) for r in rows])) for d in DRIVES}
        failing = [r["seed"] for r in rows if min(float(r[d][key]) for d in DRIVES) < lo]
        out[key] = {
            "target_min": lo,
            **{f"{d}_mean": round(means[d], 4) for d in DRIVES},
            **{
                f"{d}_{stat}": round(fn([float(r[d][key]) for r in rows]), 4)
                for d in DRIVES
                for stat, fn in (("min", min), ("max", max))
            },
            "met_on_mean": all(m >= lo for m in means.values()),
            "met_every_seed": not failing,
            "failing_seeds": failing,
        }
    hi = TARGETS["dbh_rmse_cm_le5_max"]
    v = [r["benchmark"].get("dbh_rmse_cm_0_5") for r in rows]
    have = [float(x) for x in v if x is not None]
    mean = float(np.mean(have)) if have and len(have) == len(v) else math.nan
    failing = [r["seed"] for r, x in zip(rows, v, strict=True) if x is None or float(x) > hi]
    out["dbh_rmse_le5"] = {
        "target_max_cm": hi,
        "drive": "benchmark",
        "benchmark_mean_cm": round(mean, 3) if math.isfinite(mean) else None,
        "benchmark_min_cm": round(min(have), 3) if have else None,
        "benchmark_max_cm": round(max(have), 3) if have else None,
        "benchmark_pooled_cm": over_seeds.get("benchmark_dbh_rmse_cm_0_5_pooled"),
        "met_on_mean": bool(mean <= hi),  # NaN (a seed without a pair): not met
        "met_every_seed": not failing,
        "failing_seeds": failing,
    }
    return out


def meets_targets(
    ours: dict[str, Any], sp: dict[str, Any], over_seeds: dict[str, Any], seed: int
) -> dict[str, Any]:
    """Which of :data:`TARGETS` the ``stemmap`` preset meets: ``ours`` its :func:`score` on
    this run's drive (seed ``seed``), ``sp`` :func:`speed`, ``over_seeds``
    :func:`_scan_sim.simulated_precision_seeds` of the preset.

    Issue 11's three simulated accuracy targets (recall, precision, DBH RMSE at <= 5 m) are
    each reported three ways, under names that say which: ``<target>_this_seed`` (this run's
    seed, benchmark drive), ``<target>_mean_over_seeds`` (the mean over the seeds, recall and
    precision on each drive: :func:`seed_verdicts` ``met_on_mean``) and
    ``<target>_every_seed`` (every seed on its own, both drives). One seed's precision has an
    sd of 0.020-0.027 over seeds (a clutter object seen in tens of scans moves it by
    0.02-0.04) and its DBH RMSE 0.03-0.06 cm with the noise draw alone (scan-detection.md), so
    ``all`` reads the three targets on the mean, the rule the docs state for precision since
    Dec 3 and the ``real_geometry.py`` grid admits by since Dec 5
    (:func:`_scan_sim.admitted_over_seeds`); ``all_every_seed`` reads them per seed (every
    seed, both drives). The 5-10 m DBH, bias, speed and latency targets (the first issue's)
    are this run's in both. ``failing`` / ``failing_every_seed``: the names not met under
    each reading (``_this_seed`` names are reported, never judged)."""
    v = seed_verdicts(over_seeds)
    met: dict[str, Any] = {
        "recall_this_seed": (ours["recall"] or 0.0) >= TARGETS["recall_min"],
        "recall_mean_over_seeds": v["recall"]["met_on_mean"],
        "recall_every_seed": v["recall"]["met_every_seed"],
        "precision_this_seed": (ours["precision"] or 0.0) >= TARGETS["precision_min"],
        "precision_mean_over_seeds": v["precision"]["met_on_mean"],
        "precision_every_seed": v["precision"]["met_every_seed"],
        "dbh_rmse_le5_this_seed": (ours["dbh_rmse_cm_le5"] or 1e9)
        <= TARGETS["dbh_rmse_cm_le5_max"],
        "dbh_rmse_le5_mean_over_seeds": v["dbh_rmse_le5"]["met_on_mean"],
        "dbh_rmse_le5_every_seed": v["dbh_rmse_le5"]["met_every_seed"],
        "dbh_rmse_5_10": (ours["dbh_rmse_cm_5_10"] or 1e9) <= TARGETS["dbh_rmse_cm_5_10_max"],
        "dbh_bias": max(abs(ours["dbh_bias_cm_le5"] or 1e9), abs(ours["dbh_bias_cm_5_10"] or 1e9))
        <= TARGETS["abs_dbh_bias_cm_max"],
        "speed_361": sp["scans_per_second_361"] >= TARGETS["scans_per_second_361_min"],
        "latency_1081": sp["latency_ms_1081"] <= TARGETS["latency_ms_1081_max"],
    }
    others = ("dbh_rmse_5_10", "dbh_bias", "speed_361", "latency_1081")
    failing = [
        k for k, ok in met.items() if not ok and (k.endswith("_mean_over_seeds") or k in others)
    ]
    failing_every = [
        k for k, ok in met.items() if not ok and (k.endswith("_every_seed") or k in others)
    ]
    return {
        **met,
        "all": not failing,
        "failing": failing,
        "all_every_seed": not failing_every,
        "failing_every_seed": failing_every,
        "failing_seeds": {
            k: v[k]["failing_seeds"] for k in ("recall", "precision", "dbh_rmse_le5")
        },
        "rule": f"all: recall and precision (each drive, benchmark and stemmap demo) and the"
        f" benchmark drive's DBH RMSE <= 5 m on their mean over seeds {over_seeds['seeds']};"
        f" all_every_seed: the same on every one of those seeds; _this_seed (seed {seed},"
        " benchmark drive) is reported, not judged; the other targets are this run's",
    }


def precision_summary(
    ours: dict[str, Any], over_seeds: dict[str, Any], seed: int
) -> dict[str, Any]:
    """The precisions :func:`meets_targets` reads: this run's seed (benchmark drive) and the
    mean / smallest / largest over seeds per drive with the seeds below the target on either
    drive (``failing_seeds``)."""
    return {
        "this_seed": {"seed": seed, "benchmark": ours["precision"]},
        "over_seeds": {
            "seeds": over_seeds["seeds"],
            **{
                f"{drive}_{stat}": over_seeds[f"{drive}_precision_{stat}"]
                for drive in DRIVES
                for stat in ("mean", "min", "max")
            },
            "failing_seeds": over_seeds["failing_seeds"],
        },
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--scans", type=int, default=400, help="scans of the drive to score")
    ap.add_argument("--batch", type=int, default=10000, help="scans in the speed batch")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-real", action="store_true", help="skip the real-geometry section")
    ap.add_argument(
        "--crlb", action="store_true", help="only the Cramer-Rao bound of the drive's geometry"
    )
    ap.add_argument(
        "--speed-set",
        type=json.loads,
        default=None,
        help="only time the stemmap preset against it with these overrides, alternating in one "
        "process, e.g. '{\"sigma_from_scan\": true}' ('{}': the preset against itself)",
    )
    ap.add_argument("--rounds", type=int, default=3, help="--speed-set: rounds")
    ap.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=None,
        help="only the simulated targets over these seeds (400-scan drive and demo drive)",
    )
    ap.add_argument(
        "--set",
        type=json.loads,
        default=None,
        help="--seeds: overrides of the stemmap preset, e.g. '{\"arc_refit\": false}'",
    )
    ap.add_argument("--worst", type=int, default=5, help="--seeds: trees listed per seed")
    ap.add_argument(
        "--sim-hit-fraction",
        type=float,
        default=None,
        help="the simulated SICK's return threshold on both drives, the share of its footprint"
        " that must hit for a beam to return (default: the sick_lms preset's own)",
    )
    ap.add_argument(
        "--precision-seeds",
        type=int,
        nargs="+",
        default=list(SIM_SEEDS),
        help="the full run: seeds over which recall, precision (each drive) and the DBH RMSE"
        " <= 5 m are judged, on their mean and on every seed"
        f" (default {' '.join(map(str, SIM_SEEDS))})",
    )
    ap.add_argument(
        "--speed-seeds",
        type=int,
        nargs="+",
        default=None,
        help="only the 361-beam speed on these seeds' drives, each against seed 1's",
    )
    args = ap.parse_args(argv)
    set_sim_hit_fraction(args.sim_hit_fraction)
    if args.seeds is not None:
        acc = accuracy_over_seeds(args.seeds, args.set or {}, args.worst)
        head = {"set": args.set, "sim_hit_fraction": args.sim_hit_fraction}
        print(json.dumps({"benchmark": "scan_detection_seeds", **head, **acc}))
        return 0
    if args.speed_seeds is not None:
        sp_seeds = speed_over_seeds(args.speed_seeds, args.batch)
        print(json.dumps({"benchmark": "scan_detection_speed_seeds", **sp_seeds}))
        return 0

    run = make_run(args.scans, args.seed)
    if args.speed_set is not None:
        out = {
            "benchmark": "scan_detection_speed_compare",
            "seed": args.seed,
            **speed_compare(run, args.batch, args.speed_set, args.rounds),
        }
        print(json.dumps(out))
        return 0
    if args.crlb:
        out = {"benchmark": "scan_detection_crlb", "seed": args.seed, **benchmark_crlb(run)}
        print(json.dumps(out))
        return 0
    result: dict[str, Any] = {
        "benchmark": "scan_detection",
        "scenario": {**SCENARIO, "seed": args.seed, "n_scans": len(run.scans)},
        "targets": TARGETS,
        "detector_default": DetectorConfig.preset("stemmap").to_dict(),
    }
    methods: dict[str, Any] = {}
    for m in FIT_METHODS:
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", fit_method=m))
        methods[m] = score(det.detect_batch(run.scans), run)
    result["methods"] = methods
    presets: dict[str, Any] = {}
    for name in PRESETS:
        det = ScanTrunkDetector(name)
        presets[name] = {"fit": det.config.fit_method, **score(det.detect_batch(run.scans), run)}
    result["presets"] = presets
    sp = speed(run, args.batch, args.seed)
    result["speed"] = sp
    result["scans_per_second_361"] = sp["scans_per_second_361"]
    result["latency_ms_1081"] = sp["latency_ms_1081"]
    ours = methods["ours"]
    over_seeds = simulated_precision_seeds({}, args.precision_seeds)
    result["precision"] = precision_summary(ours, over_seeds, args.seed)
    result["meets_targets"] = meets_targets(ours, sp, over_seeds, args.seed)
    if not args.no_real:
        ddir = find_datasets_dir(Path(__file__).resolve().parent)
        result["real_detection"] = None if ddir is None else run_real_detection(ddir, args.seed)
        try:
            result["real_geometry"] = real_geometry(args.seed)
        except Exception as exc:  # the section belongs to scan-fit; report, do not crash
            result["real_geometry"] = {"error": f"{type(exc).__name__}: {exc}"}
    result["machine"] = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "cpu_count": os.cpu_count(),
        "note": "shared 2-core machine under load from other jobs; timings are noisy",
    }
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
