"""Circle fits on real trunk geometry: virtual 2D scans of the FORTLS TLS slice.

The slice (``fortls_slice/diameters.laz``, 1.2-1.4 m above ground, ~15 m around the scanner)
shows every trunk as a full ring, so a full-ring geometric fit gives a reference diameter per
trunk. From vantage points at 3-12 m around each trunk we build a virtual 2D scan of the whole
slice (all trunks occlude each other): the nearest return per angular bin, plus Gaussian range
noise. Only the visible arc of the target trunk remains; each fit method then estimates the
diameter from that arc and we report the error against the ring reference.

Usage::

    python benchmarks/scan_fits_real.py --json          # one JSON object on stdout
    python benchmarks/scan_fits_real.py --bin-deg 0.5 --noise 0.02 --json

Every parameter of the scenario is echoed in the output.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from stemmap.datasets import find_datasets_dir
from stemmap.errors import InputError
from stemmap.eval.real_slices import SLICES, load_slice
from stemmap.scan._fit_geometric import _footprint_range
from stemmap.scan.circle import FIT_METHODS, fit_circles_batch

SLICE = Path("fortls_slice") / "diameters.laz"

DEFAULTS: dict[str, Any] = {
    "bin_deg": 0.25,
    "range_noise_m": 0.01,
    "ranges_m": (3.0, 6.0, 9.0, 12.0),
    "bearings_per_range": 2,
    "min_points": 3,
    "skip_occluded": True,
    "cluster_cell_m": 0.05,
    "min_ring_points": 500,
    "seed": 7,
}


def load_rings(
    datasets_dir: Path, cell: float = 0.05, min_ring_points: int = 500
) -> tuple[np.ndarray, np.ndarray, list[dict[str, float]]]:
    """Points (N, 2), trunk index per point (-1 = not a trunk) and the ring reference per trunk
    of the FORTLS slice (:func:`stemmap.eval.real_slices.load_slice`, shared with
    benchmarks/real_geometry.py; every trunk there is a full ring).

    ``cell`` and ``min_ring_points`` are those of the slice's spec (5 cm, 500 points): they
    are checked, not passed on.
    """
    spec = SLICES["fortls_slice"]
    if (cell, min_ring_points) != (spec.cell, spec.min_ring_points):
        raise InputError(
            f"load_rings: cell / min_ring_points are fixed by SLICES['fortls_slice'] "
            f"({spec.cell}, {spec.min_ring_points}); got ({cell}, {min_ring_points})."
        )
    sl = load_slice(datasets_dir, "fortls_slice")
    return sl.xy, sl.labels, sl.refs


def virtual_scan(
    xy: np.ndarray,
    labels: np.ndarray,
    vantage: np.ndarray,
    target: int,
    bin_rad: float,
    noise: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, tuple[bool, bool]] | None:
    """Visible arc of ``target`` from ``vantage``: nearest return per angular bin of width
    ``bin_rad`` over the whole slice, plus N(0, noise) range noise.

    Returns the arc points (in a frame with the sensor at the origin) and whether each side is a
    true silhouette edge (the neighbouring bin is empty or farther), or None when the target is
    not visible as one contiguous run of bins.
    """
    q = xy - vantage
    rho = np.hypot(q[:, 0], q[:, 1])
    # bins relative to the target's direction so the arc never straddles +-pi
    tgt = q[labels == target].mean(axis=0)
    ref = math.atan2(tgt[1], tgt[0])
    c, s = math.cos(ref), math.sin(ref)
    th = np.arctan2(-s * q[:, 0] + c * q[:, 1], c * q[:, 0] + s * q[:, 1])
    b = np.floor(th / bin_rad).astype(np.int64)
    order = np.lexsort((rho, b))
    bs = b[order]
    first = np.ones(bs.shape[0], dtype=bool)
    first[1:] = bs[1:] != bs[:-1]
    nearest = order[first]  # index of the nearest point per non-empty bin
    nb = b[nearest]
    hit = labels[nearest] == target
    if not hit.any():
        return None
    k = np.flatnonzero(hit)
    if np.any(np.diff(nb[k]) != 1) or np.any(np.diff(k) != 1):
        return None  # split by an occluder
    idx = nearest[k]
    # edges: the bin just outside each side is empty or its nearest return is farther
    lo_ok = k[0] == 0 or nb[k[0] - 1] != nb[k[0]] - 1 or rho[nearest[k[0] - 1]] > rho[idx[0]]
    hi_ok = (
        k[-1] == nb.shape[0] - 1
        or nb[k[-1] + 1] != nb[k[-1]] + 1
        or rho[nearest[k[-1] + 1]] > rho[idx[-1]]
    )
    r = rho[idx] + rng.normal(0.0, noise, idx.shape[0]) if noise > 0 else rho[idx]
    ang = np.arctan2(q[idx, 1], q[idx, 0])
    pts = np.column_stack((r * np.cos(ang), r * np.sin(ang)))
    return pts, (bool(lo_ok), bool(hi_ok))


def _stats(err_cm: np.ndarray) -> dict[str, float]:
    e = err_cm[np.isfinite(err_cm)]
    if e.size == 0:
        return {"n": 0, "rmse_cm": math.nan, "bias_cm": math.nan, "mae_cm": math.nan}
    return {
        "n": int(e.size),
        "rmse_cm": round(float(np.sqrt(np.mean(e * e))), 3),
        "bias_cm": round(float(np.mean(e)), 3),
        "median_abs_cm": round(float(np.median(np.abs(e))), 3),
    }


def run_real_geometry(
    datasets_dir: Path | str,
    *,
    bin_deg: float = DEFAULTS["bin_deg"],
    range_noise_m: float = DEFAULTS["range_noise_m"],
    ranges_m: tuple[float, ...] = DEFAULTS["ranges_m"],
    bearings_per_range: int = DEFAULTS["bearings_per_range"],
    min_points: int = DEFAULTS["min_points"],
    skip_occluded: bool = DEFAULTS["skip_occluded"],
    seed: int = DEFAULTS["seed"],
    methods: tuple[str, ...] | None = None,
    _cache: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Arc-based diameter error of every fit method against the full-ring reference.

    Parameters
    ----------
    datasets_dir : path of the shared datasets folder (holding ``fortls_slice/``)
    bin_deg : angular bin of the virtual scanner, degrees
    range_noise_m : std of the Gaussian range noise added to each virtual return, metres
    ranges_m : distances of the vantage points from each trunk centre, metres
    bearings_per_range : random bearings per distance (seeded)
    min_points : arcs with fewer returns are skipped (not fitted by any method)
    skip_occluded : skip arcs with an edge hidden by a nearer trunk (a detector flags these as
        partial trunks); when False they are fitted with that edge marked
    seed : RNG seed (vantage bearings and noise)
    methods : fit methods to run (default: all registered)

    Returns
    -------
    dict
        ``scenario`` (every parameter), ``trees`` (reference per trunk), ``arcs`` (count,
        points per arc) and ``methods`` -> overall and per-range ``rmse_cm``/``bias_cm``,
        failures and fits/s.
    """
    rng = np.random.default_rng(seed)
    cache = _cache if _cache is not None else {}
    if "rings" not in cache:
        cache["rings"] = load_rings(Path(datasets_dir))
    xy, labels, refs = cache["rings"]
    bin_rad = math.radians(bin_deg)
    arcs: list[np.ndarray] = []
    edges: list[tuple[bool, bool]] = []
    truth: list[float] = []
    dist: list[float] = []
    n_occluded = 0
    for t, ref in enumerate(refs):
        centre = np.array([ref["x"], ref["y"]])
        for d in ranges_m:
            for bearing in rng.uniform(-math.pi, math.pi, bearings_per_range):
                vantage = centre + d * np.array([math.cos(bearing), math.sin(bearing)])
                got = virtual_scan(xy, labels, vantage, t, bin_rad, range_noise_m, rng)
                if got is None or got[0].shape[0] < min_points:
                    continue
                if skip_occluded and not all(got[1]):
                    n_occluded += 1
                    continue
                arcs.append(got[0])
                edges.append(got[1])
                truth.append(ref["diameter"])
                dist.append(d)
    if not arcs:
        raise InputError("no trunk arc was visible from any vantage point.")
    pts = np.vstack(arcs)
    seg = np.repeat(np.arange(len(arcs)), [a.shape[0] for a in arcs])
    truth_a = np.asarray(truth)
    dist_a = np.asarray(dist)
    n_pts = np.array([a.shape[0] for a in arcs])
    out_methods: dict[str, Any] = {}
    for m in methods or tuple(FIT_METHODS):
        t0 = time.perf_counter()
        fits = fit_circles_batch(
            pts,
            seg,
            m,
            sigma=range_noise_m if range_noise_m > 0 else None,
            angle_increment=bin_rad,
            edges=np.asarray(edges),
        )
        dt = time.perf_counter() - t0
        err = (fits.diameters - truth_a) * 100.0
        by_range = {f"{d:g}m": _stats(err[dist_a == d]) for d in ranges_m}
        out_methods[m] = {
            **_stats(err),
            "failed": int((~fits.ok).sum()),
            "by_range": by_range,
            "fits_per_s": round(len(arcs) / dt, 1),
        }
    return {
        "benchmark": "scan_fits_real",
        "dataset": str(SLICE),
        "scenario": {
            "bin_deg": bin_deg,
            "range_noise_m": range_noise_m,
            "ranges_m": list(ranges_m),
            "bearings_per_range": bearings_per_range,
            "min_points": min_points,
            "skip_occluded": skip_occluded,
            "seed": seed,
            "clustering": "8-connected occupancy grid",
            "cluster_cell_m": DEFAULTS["cluster_cell_m"],
            "min_ring_points": DEFAULTS["min_ring_points"],
            "reference": "geometric fit of the full ring",
            "sigma_passed_to_fits": range_noise_m if range_noise_m > 0 else None,
            "angle_increment_passed_to_fits_rad": bin_rad,
        },
        "trees": {
            "n": len(refs),
            "diameter_cm_min": round(min(r["diameter"] for r in refs) * 100, 1),
            "diameter_cm_max": round(max(r["diameter"] for r in refs) * 100, 1),
            "ring_rms_mm_max": round(max(r["ring_rms_m"] for r in refs) * 1000, 2),
        },
        "arcs": {
            "n": len(arcs),
            "points_per_arc_mean": round(float(n_pts.mean()), 1),
            "points_per_arc_min": int(n_pts.min()),
            "points_per_arc_max": int(n_pts.max()),
            "occluded_edges_fitted": int(np.sum(~np.asarray(edges))),
            "skipped_partly_occluded": n_occluded,
        },
        "methods": out_methods,
    }


def simulated_arcs(
    dist: float,
    n_arcs: int,
    *,
    bin_deg: float,
    noise: float,
    rng: np.random.Generator,
    r_range: tuple[float, float] = (0.05, 0.4),
    min_points: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact ray casting of one circle per arc from a scanner at (0, 0): beams every
    ``bin_deg`` with a random phase, Gaussian range noise. Returns points, segment ids, radii."""
    dth = math.radians(bin_deg)
    pts: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    radii: list[float] = []
    while len(radii) < n_arcs:
        r = float(rng.uniform(*r_range))
        bearing = float(rng.uniform(-1.5, 1.5))
        c = dist * np.array([math.cos(bearing), math.sin(bearing)])
        half = math.asin(r / dist)
        ang = np.arange(bearing - half + rng.uniform(0.0, dth), bearing + half, dth)
        u = np.column_stack((np.cos(ang), np.sin(ang)))
        b = u @ c
        rr = b - np.sqrt(np.maximum(b * b - (c @ c - r * r), 0.0))
        rr = rr + rng.normal(0.0, noise, rr.shape)
        if rr.shape[0] < min_points:
            continue
        pts.append(u * rr[:, None])
        ids.append(np.full(rr.shape[0], len(radii)))
        radii.append(r)
    return np.vstack(pts), np.concatenate(ids), np.asarray(radii)


def run_simulated(
    *,
    ranges_m: tuple[float, ...] = (1.0, 3.0, 5.0, 8.0, 12.0),
    n_arcs: int = 1000,
    bin_deg: float = 0.5,
    range_noise_m: float = 0.01,
    seed: int = 1,
) -> dict[str, Any]:
    """Diameter error per method on simulated one-sided arcs (trunk radius 5-40 cm)."""
    rng = np.random.default_rng(seed)
    res: dict[str, Any] = {m: {} for m in FIT_METHODS}
    pts_per_arc: dict[str, float] = {}
    for d in ranges_m:
        pts, ids, radii = simulated_arcs(d, n_arcs, bin_deg=bin_deg, noise=range_noise_m, rng=rng)
        pts_per_arc[f"{d:g}m"] = round(pts.shape[0] / n_arcs, 1)
        for m in FIT_METHODS:
            fits = fit_circles_batch(
                pts, ids, m, sigma=range_noise_m, angle_increment=math.radians(bin_deg)
            )
            err = (fits.diameters - 2.0 * radii) * 100.0
            res[m][f"{d:g}m"] = {**_stats(err), "failed": int((~fits.ok).sum())}
    return {
        "scenario": {
            "ranges_m": list(ranges_m),
            "arcs_per_range": n_arcs,
            "bin_deg": bin_deg,
            "range_noise_m": range_noise_m,
            "radius_m": [0.05, 0.4],
            "min_points": 3,
            "seed": seed,
            "points_per_arc_mean": pts_per_arc,
        },
        "methods": res,
    }


def run_project_simulator(
    *,
    ranges_m: tuple[float, ...] = (2.0, 4.0, 7.0, 10.0),
    n_scans: int = 200,
    preset: str = "sick_lms",
    seed: int = 0,
) -> dict[str, Any]:
    """Diameter error per method on the project's own 2D scanner simulator.

    Trees (DBH 10-60 cm) on an arc of radius ``d`` around the sensor, >= 1.2 m apart (no
    occlusion); ``n_scans`` scans from the origin with a random heading jitter of +-0.01 rad
    (random beam phase). The preset models beam divergence, mixed pixels at trunk edges and
    range noise (``sick_lms``: 0.5 deg, 1 cm, 0.25 deg divergence). Each tree's returns are
    taken from the simulator's per-beam ground-truth ids (segmentation is not tested here).
    """
    from stemmap.sim.forest import Stand
    from stemmap.sim.scanner import scanner_preset, simulate_scans

    model = scanner_preset(preset)
    rng = np.random.default_rng(seed)
    res: dict[str, Any] = {m: {} for m in FIT_METHODS}
    for d in ranges_m:
        n = max(3, int(2.4 * d / 1.2))
        ang = np.linspace(-1.2, 1.2, n)
        dbh = rng.uniform(0.1, 0.6, n)
        stand = Stand(
            trees_xy=np.column_stack((d * np.cos(ang), d * np.sin(ang))),
            diameters=dbh,
            bounds=(-d - 1, -d - 1, d + 1, d + 1),
        )
        poses = np.zeros((n_scans, 3))
        poses[:, 2] = rng.uniform(-0.01, 0.01, n_scans)
        batch, hit, _ = simulate_scans(stand, poses, model, rng=rng)
        valid = np.isfinite(batch.ranges) & (hit >= 0)
        scan_i, beam_i = np.nonzero(valid)
        a = batch.angles[beam_i]
        r = batch.ranges[scan_i, beam_i]
        pts = np.column_stack((r * np.cos(a), r * np.sin(a)))
        tree = hit[scan_i, beam_i]
        seg = scan_i * n + tree  # one segment per (scan, tree)
        for m in FIT_METHODS:
            # ours models the footprint of the edge returns (the preset's beam divergence)
            fits = fit_circles_batch(
                pts,
                seg,
                m,
                sigma=model.range_noise,
                angle_increment=model.angle_increment,
                beam_divergence=model.beam_divergence,
            )
            keep = fits.ok & (fits.n_points >= 3)
            err = (fits.diameters - dbh[fits.segment_ids % n])[keep] * 100.0
            failed = int((~fits.ok & (fits.n_points >= 3)).sum())
            res[m][f"{d:g}m"] = {**_stats(err), "failed_with_3_or_more_returns": failed}
    return {
        "scenario": {
            "preset": preset,
            "angle_increment_deg": math.degrees(model.angle_increment),
            "range_noise_m": model.range_noise,
            "beam_divergence_deg": math.degrees(model.beam_divergence),
            "ranges_m": list(ranges_m),
            "n_scans": n_scans,
            "dbh_m": [0.1, 0.6],
            "seed": seed,
        },
        "methods": res,
    }


def run_speed(
    *, n_arcs: int = 2000, n_points: int = 10, seed: int = 2, repeats: int = 3
) -> dict[str, Any]:
    """Fits per second per method on ``n_points``-return arcs at 5 m: single calls (Python
    dispatch per segment) and one batched call. One process, one thread (noisy: the machine is
    shared)."""
    rng = np.random.default_rng(seed)
    arcs: list[np.ndarray] = []
    # whole visible arcs with exactly n_points returns (not truncated ones: a cut arc has a
    # false silhouette edge): at 5 m with 0.5 deg beams, 10 returns need r ~ 0.2-0.24 m
    r_mid = 5.0 * math.sin(math.radians(0.25 * n_points))
    while len(arcs) < n_arcs:
        pts, _, _ = simulated_arcs(
            5.0, 1, bin_deg=0.5, noise=0.01, rng=rng, r_range=(0.9 * r_mid, 1.1 * r_mid)
        )
        if pts.shape[0] == n_points:
            arcs.append(pts)
    allp = np.vstack(arcs)
    ids = np.repeat(np.arange(n_arcs), n_points)
    out: dict[str, Any] = {}
    inc = math.radians(0.5)
    for m, fn in FIT_METHODS.items():
        fn(arcs[0], sigma=0.01)  # warm-up (numba cache load)
        single, batch = math.inf, math.inf
        for _ in range(repeats):  # best of `repeats`: the machine is shared and noisy
            t0 = time.perf_counter()
            for a in arcs:
                fn(a, sigma=0.01, angle_increment=inc)
            t1 = time.perf_counter()
            fit_circles_batch(allp, ids, m, sigma=0.01, angle_increment=inc)
            t2 = time.perf_counter()
            single, batch = min(single, t1 - t0), min(batch, t2 - t1)
        out[m] = {
            "single_fits_per_s": round(n_arcs / single),
            "batch_fits_per_s": round(n_arcs / batch),
        }
    return {
        "scenario": {
            "n_arcs": n_arcs,
            "n_points": n_points,
            "range_m": 5.0,
            "repeats_best_of": repeats,
            "threads": 1,
        },
        "methods": out,
    }


def _range_jacobian(c: np.ndarray, r: float, th: np.ndarray) -> np.ndarray:
    """d rho_i / d(cx, cy, r) of thin-beam returns at bearings ``th`` (first hit of a circle)."""
    u = np.column_stack((np.cos(th), np.sin(th)))
    b = u @ c
    q = np.sqrt(np.maximum(b * b - (c @ c - r * r), 1e-30))
    dc = u - (b[:, None] * u - c[None, :]) / q[:, None]
    return np.column_stack((dc, -r / q))


def _orthogonal_jacobian(c: np.ndarray, r: float, th: np.ndarray) -> np.ndarray:
    """d(|p_i - c| - r) / d(cx, cy, r) with the returns p_i on the circle (the fit's former
    orthogonal-distance model, isotropic noise)."""
    u = np.column_stack((np.cos(th), np.sin(th)))
    b = u @ c
    rho = b - np.sqrt(np.maximum(b * b - (c @ c - r * r), 0.0))
    n = (u * rho[:, None] - c) / r
    return np.column_stack((-n, -np.ones(th.shape[0])))


def _tangent_jacobian(c: np.ndarray, r: float) -> np.ndarray:
    """d(beta -+ asin(r / D)) / d(cx, cy, r): the two tangent bearings (rows lo, hi)."""
    d2 = float(c @ c)
    q = math.sqrt(d2 - r * r)
    b = np.array([-c[1] / d2, c[0] / d2, 0.0])
    a = np.array([-r * c[0] / (d2 * q), -r * c[1] / (d2 * q), 1.0 / q])
    return np.vstack((b - a, b + a))


def _footprint_edge_jacobian(c: np.ndarray, r: float, th: float, footprint: float) -> np.ndarray:
    """d rho / d(cx, cy, r) of an edge return whose range is the mean over the part of a beam
    footprint of ``footprint`` rad that hits the circle (the ours fit's edge model,
    scan-fits.md "Edge model"; the kernel's own prediction and partials)."""
    ux, uy = math.cos(th), math.sin(th)
    out = np.zeros(4)
    b = ux * c[0] + uy * c[1]
    s0 = ux * c[1] - uy * c[0]
    if not _footprint_range(b, s0, r, footprint, out):
        return _range_jacobian(c, r, np.array([th]))[0]
    return np.array([out[1] * ux - out[2] * uy, out[1] * uy + out[2] * ux, out[3]])


def crlb_diameter_var(
    c: np.ndarray,
    r: float,
    th: np.ndarray,
    sigma: float,
    tangent_std: np.ndarray | None,
    model: str = "range",
    footprint: float = 0.0,
) -> float:
    """Cramer-Rao bound on var(2 r) for returns at bearings ``th`` (range or orthogonal noise
    ``sigma``) plus Gaussian tangent observations with the given stds (rows lo, hi; None or
    inf = no silhouette on that side). Fisher information J = sum_i g_i g_i^T / sigma^2 +
    sum_edge t_e t_e^T / s_e^2; bound = 4 [J^-1]_rr. ``footprint`` > 0 (range model): the
    lowest / highest-bearing return of a side with a tangent term is footprint-averaged (an
    averaging scanner, the ours fit's edge model) instead of a thin ray: its range changes
    less steeply with the tangent's position than a grazing thin ray's, so it carries less
    information (the thin-ray bound is optimistic there)."""
    jac = _range_jacobian(c, r, th) if model == "range" else _orthogonal_jacobian(c, r, th)
    if footprint > 0 and model == "range" and tangent_std is not None and th.shape[0] >= 2:
        for side, i in enumerate((int(np.argmin(th)), int(np.argmax(th)))):
            if np.isfinite(tangent_std[side]):
                jac[i] = _footprint_edge_jacobian(c, r, float(th[i]), footprint)
    fisher = jac.T @ jac / sigma**2
    if tangent_std is not None:
        t = _tangent_jacobian(c, r)
        for k in range(2):
            if np.isfinite(tangent_std[k]):
                fisher += np.outer(t[k], t[k]) / tangent_std[k] ** 2
    try:
        return float(4.0 * np.linalg.inv(fisher)[2, 2])
    except np.linalg.LinAlgError:
        return math.inf


def linearised_mmse_diameter_var(
    c: np.ndarray,
    r: float,
    th: np.ndarray,
    sigma: float,
    width: float,
    rng: np.random.Generator,
    n_draw: int = 150,
    n_post: int = 4000,
) -> float:
    """Bayesian minimum MSE of 2 r when each tangent bearing is only known to lie in an interval
    of ``width`` (uniform beam phase, the silhouette's true likelihood) and the returns carry
    Gaussian range noise, in the linearised model: posterior = Gaussian (returns) restricted to
    the two slabs; its mean by rejection sampling, averaged over ``n_draw`` realisations."""
    jac = _range_jacobian(c, r, th)
    cov = np.linalg.inv(jac.T @ jac / sigma**2)
    chol = np.linalg.cholesky(cov)
    t = _tangent_jacobian(c, r)
    errs = []
    for _ in range(n_draw):
        theta_p = chol @ rng.standard_normal(3)
        obs = rng.uniform(-0.5, 0.5, 2) * width
        samp = theta_p + rng.standard_normal((n_post, 3)) @ chol.T
        ok = np.all(np.abs(obs - samp @ t.T) < width / 2, axis=1)
        if ok.sum() < 50:
            samp = theta_p + rng.standard_normal((20 * n_post, 3)) @ chol.T
            ok = np.all(np.abs(obs - samp @ t.T) < width / 2, axis=1)
        if ok.any():
            errs.append(2.0 * float(samp[ok, 2].mean()))
    return float(np.mean(np.square(errs)))


def run_crlb(
    *,
    ranges_m: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0, 7.0, 10.0),
    radius_m: float = 0.15,
    bin_deg: float = 0.5,
    range_noise_m: float = 0.01,
    n_phase: int = 24,
    seed: int = 3,
) -> dict[str, Any]:
    """How well can any fit do? Diameter error bounds for one trunk seen whole (both edges),
    RMS over ``n_phase`` beam phases, cm (docs/algorithms/scan-fits.md, "Cramer-Rao bound")."""
    dth = math.radians(bin_deg)
    s = dth / math.sqrt(12.0)
    rng = np.random.default_rng(seed)
    out: dict[str, Any] = {}
    for d in ranges_m:
        c = np.array([d, 0.0])
        half = math.asin(radius_m / d)
        rows = []
        for ph in (np.arange(n_phase) + 0.5) / n_phase:
            th = np.arange(-half + ph * dth, half, dth)
            rows.append(
                (
                    th.shape[0],
                    crlb_diameter_var(c, radius_m, th, range_noise_m, np.full(2, s), "orth"),
                    crlb_diameter_var(c, radius_m, th, range_noise_m, np.full(2, s)),
                    crlb_diameter_var(c, radius_m, th, range_noise_m, None),
                    linearised_mmse_diameter_var(c, radius_m, th, range_noise_m, dth, rng)
                    if ph * n_phase % 2 < 1
                    else math.nan,
                )
            )
        a = np.asarray(rows)

        def rms_cm(v: np.ndarray) -> float:
            return round(100.0 * math.sqrt(float(np.nanmean(v))), 3)

        out[f"{d:g}m"] = {
            "returns_mean": round(float(a[:, 0].mean()), 1),
            "crlb_orthogonal_gauss_silhouette_cm": rms_cm(a[:, 1]),
            "crlb_range_gauss_silhouette_cm": rms_cm(a[:, 2]),
            "crlb_range_no_silhouette_cm": rms_cm(a[:, 3]),
            "mmse_range_uniform_silhouette_cm": rms_cm(a[:, 4]),
            "silhouette_only_cm": round(100.0 * math.sqrt(2.0) * d * math.cos(half) * s, 3),
        }
    return {
        "scenario": {
            "radius_m": radius_m,
            "bin_deg": bin_deg,
            "range_noise_m": range_noise_m,
            "beam_phases": n_phase,
            "seed": seed,
        },
        "bounds": out,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--bin-deg", type=float, default=DEFAULTS["bin_deg"])
    ap.add_argument("--noise", type=float, default=DEFAULTS["range_noise_m"])
    ap.add_argument("--bearings", type=int, default=DEFAULTS["bearings_per_range"])
    ap.add_argument("--seed", type=int, default=DEFAULTS["seed"])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument(
        "--with-sim", action="store_true", help="add simulated arcs by range and fit speed"
    )
    ap.add_argument(
        "--crlb", action="store_true", help="only the diameter error bounds (Cramer-Rao, MMSE)"
    )
    args = ap.parse_args(argv)
    if args.crlb:
        res_b = run_crlb(bin_deg=args.bin_deg, range_noise_m=args.noise)
        print(json.dumps(res_b) if args.json else json.dumps(res_b, indent=2))
        return 0
    ddir = args.datasets or find_datasets_dir(Path(__file__).resolve().parent)
    if ddir is None:
        print("shared datasets folder not found (set STEMMAP_DATASETS)", file=sys.stderr)
        return 2
    res = run_real_geometry(
        ddir,
        bin_deg=args.bin_deg,
        range_noise_m=args.noise,
        bearings_per_range=args.bearings,
        seed=args.seed,
    )
    if args.with_sim:
        res["simulated"] = run_simulated(bin_deg=args.bin_deg, range_noise_m=args.noise)
        res["project_simulator"] = run_project_simulator()
        res["speed"] = run_speed()
    if args.json:
        print(json.dumps(res))
    else:
        print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
