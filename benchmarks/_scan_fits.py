"""Shared by benchmarks/scan_fits_real.py and benchmarks/scan_detection.py: the FORTLS slice's
full-ring references (:func:`load_rings`), arc fits on virtual 2D scans of it against those
references (:func:`run_real_geometry`), and the Cramer-Rao bound on the diameter of a fit
from a trunk's returns and tangent bearings (:func:`crlb_diameter_var`, docs:
algorithms/scan-fits.md). Split out of scan_fits_real.py so scan_detection.py imports it by
name instead of loading that script by path.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

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


def stats_cm(err_cm: np.ndarray) -> dict[str, float]:
    e = err_cm[np.isfinite(err_cm)]
    if e.size == 0:
        return {"n": 0, "rmse_cm": math.nan, "bias_cm": math.nan, "median_abs_cm": math.nan}
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
        by_range = {f"{d:g}m": stats_cm(err[dist_a == d]) for d in ranges_m}
        out_methods[m] = {
            **stats_cm(err),
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
