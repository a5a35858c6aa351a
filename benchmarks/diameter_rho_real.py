"""The intra-trunk correlation ``rho`` of per-scan DBH errors, measured on REAL trunk geometry.

:func:`stemmap.slam.uncertainty.diameter_standard_errors` gives a mapped tree's DBH the
standard error ``s / sqrt(n) * sqrt(1 + (n - 1) rho)`` (Kish's design effect): the ``n`` scans
of one trunk share part of their error (same side seen, same bark). ``rho`` = 0.03 was set on
the simulator (benchmarks/uncertainty_calibration.py), whose trunks are smooth cylinders. Here
the trunks are the real breast-height slices of every cloud in the shared datasets
(:mod:`stemmap.eval.real_slices`, ring references as the truth): for every reference trunk, a
machine drives straight past it (lateral distance 4 and 8 m, on two opposite sides, a scan
every 0.5 m from 15 m before to 15 m after; the whole slice occludes), virtual 2D scans
(0.5 deg, nearest-return or SICK-class averaging, optional range noise), the default detector,
and the detections matched to the trunk give per pass ``n``, the mean DBH error ``e`` and the
per-scan spread ``s``. ``rho`` is the value that makes the median of
``|e| / (s / sqrt(n) * sqrt(1 + (n - 1) rho))`` equal 0.6745 (the median |z| of a calibrated
standard error), solved over all passes, and leave-one-dataset-out (solved without a dataset,
scored on it).

``bias``: the same passes for the per-trunk bias scale ``b`` of
``sqrt(s^2 (1 + (n - 1) rho) / n + b^2)`` (:data:`stemmap.slam.uncertainty.DIAMETER_BIAS`):
per form of ``b`` (:data:`BIAS_FORMS`) and rho in (1, 0.03), ``k`` solved for median |z| =
0.6745 on all passes and leave-one-dataset-out (median |z| and share |z| < 1 held out).

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage: python benchmarks/diameter_rho_real.py [--noise 0 0.01] [--skip fortls_slice]
[--rows-out rows.json | --rows-in rows.json] [--preset stemmap|none] [--scans]
Prints JSON. The machine is shared; times are not reported.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.optimize import brentq

from _datasets import require_datasets_dir
from _real_scanning import ANY_HIT, ReturnRule, add_hit_fraction, matched  # real_geometry.py's
from stemmap.eval.real_slices import SLICES, load_slice, noisy_batch, virtual_scans
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

MEDIAN_ABS_Z = 0.6745
OFFSETS_M = (4.0, 8.0)
ALONG_M = np.arange(-15.0, 15.01, 0.5)


def passes(center: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Vantage points (K, 2) of straight drives past ``center``: two opposite sides x offsets,
    the drive direction drawn at random per trunk."""
    phi = rng.uniform(0.0, 2.0 * math.pi)
    u = np.array([math.cos(phi), math.sin(phi)])  # drive direction
    n = np.array([-u[1], u[0]])  # to the side
    out = []
    for side in (1.0, -1.0):
        for d in OFFSETS_M:
            out.append(center + side * d * n + ALONG_M[:, None] * u)
    return out


def pass_detector(model: str, preset: str | None = "stemmap") -> DetectorConfig:
    """The detector of the passes: the default detector (``ScanTrunkDetector()``, the
    ``stemmap`` preset that ``map`` and ``demo`` run) set up for the scanner as
    ``real_geometry.py`` does (:func:`_real_scanning.matched`: a first-echo scanner's
    footprint is one beam step, ``stemmap detect --footprint``). ``preset=None``: a bare
    ``DetectorConfig()`` (Kasa fit, no plausibility tests), what this benchmark ran before
    Dec 5 by mistake (``--preset none``, kept to reproduce those rows)."""
    cfg = DetectorConfig() if preset is None else DetectorConfig.preset(preset)
    return matched(cfg, model, 0.5)


def run_slice(
    name: str,
    model: str,
    noise: float,
    seed: int,
    preset: str | None = "stemmap",
    scans: list[dict[str, Any]] | None = None,
    *,
    return_rule: ReturnRule,
) -> list[dict[str, Any]]:
    """One row per (trunk, pass) with >= 2 matched detections: n, mean error e, spread s (m).
    ``scans``: when given, one record per matched scan is appended to it (range to the trunk
    centre, the trunk's returns in the noise-free scan, the detection's points and arc, the
    error; m / deg) for the per-scan breakdown. ``return_rule``: the averaging scanner's."""
    where = require_datasets_dir()
    sl = load_slice(where, name)
    rng = np.random.default_rng(seed)
    det = ScanTrunkDetector(pass_detector(model, preset))
    rows: list[dict[str, Any]] = []
    for t, (c, d) in enumerate(zip(sl.centers, sl.diameters, strict=True)):
        if not 0.1 <= d <= 1.0:
            continue
        for p, vp in enumerate(passes(c, rng)):
            ranges0, hit = virtual_scans(
                sl.xy, sl.labels, vp, resolution_deg=0.5, model=model,  # type: ignore[arg-type]
                centers=sl.centers, **return_rule.kwargs(),
            )  # fmt: skip
            obs = det.detect_batch(noisy_batch(ranges0, 0.5, noise, rng))
            errs, arcs = [], []
            for s in range(vp.shape[0]):
                m = obs.index == s
                if not m.any():
                    continue
                dist = np.hypot(*(obs.centers[m] - (c - vp[s])).T)
                k = int(np.argmin(dist))
                if dist[k] <= d / 2.0 + 0.05:
                    errs.append(2.0 * float(obs.radii[m][k]) - d)
                    arcs.append(float(obs.arc_deg[m][k]))
                    if scans is not None:
                        scans.append(
                            {
                                "dataset": name,
                                "trunk": t,
                                "pass": p,
                                "range_m": float(np.hypot(*(c - vp[s]))),
                                "returns": int((hit[s] == t).sum()),
                                "points": int(obs.n_points[m][k]),
                                "r_std": float(np.sqrt(max(obs.covs[m][k][2, 2], 0.0))),
                                "arc_deg": arcs[-1],
                                "err": errs[-1],
                                "dbh": float(d),
                            }
                        )
            if len(errs) >= 2:
                e = np.asarray(errs)
                rows.append(
                    {
                        "dataset": name,
                        "trunk": t,
                        "n": len(e),
                        "e": float(e.mean()),
                        "s": float(e.std(ddof=1)),
                        "dbh": float(d),
                        "offset_m": float(np.hypot(*(vp[vp.shape[0] // 2] - c))),
                        "arc_deg": float(np.nanmedian(arcs))
                        if np.isfinite(arcs).any()
                        else math.nan,
                    }
                )
    return rows


#: Bands of the per-scan breakdown (:func:`scan_breakdown`): range to the trunk centre (m),
#: the trunk's returns in the noise-free scan, the detection's arc (deg).
SCAN_BANDS: dict[str, tuple[tuple[float, float], ...]] = {
    "range_m": ((0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0)),
    "returns": ((0, 8), (8, 16), (16, 32), (32, 1000)),
    "arc_deg": ((0.0, 60.0), (60.0, 90.0), (90.0, 120.0), (120.0, 360.0)),
}


def scan_breakdown(scans: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-scan DBH errors (cm: count, bias, RMSE, median |error|) by dataset and by each band
    of :data:`SCAN_BANDS` (``lo <= value < hi``), overall and per dataset."""

    def stats(sel: list[dict[str, Any]]) -> dict[str, Any]:
        e = 100.0 * np.array([r["err"] for r in sel])
        if e.size == 0:
            return {"n": 0}
        return {
            "n": int(e.size),
            "bias_cm": round(float(e.mean()), 2),
            "rmse_cm": round(float(np.sqrt(np.mean(e**2))), 2),
            "median_abs_cm": round(float(np.median(np.abs(e))), 2),
        }

    def bands(sel: list[dict[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {"all": stats(sel)}
        for key, bs in SCAN_BANDS.items():
            out[key] = {
                f"{lo:g}-{hi:g}": stats([r for r in sel if lo <= r[key] < hi]) for lo, hi in bs
            }
        return out

    res = bands(scans)
    for name in sorted({r["dataset"] for r in scans}):
        res[name] = bands([r for r in scans if r["dataset"] == name])
    return res


def median_abs_z(rows: list[dict[str, Any]], rho: float) -> float:
    n = np.array([r["n"] for r in rows], dtype=float)
    e = np.array([r["e"] for r in rows])
    s = np.array([r["s"] for r in rows])
    ok = s > 0
    se = s[ok] / np.sqrt(n[ok]) * np.sqrt(1.0 + (n[ok] - 1.0) * rho)
    return float(np.median(np.abs(e[ok]) / se))


def solve_rho(rows: list[dict[str, Any]]) -> float:
    if median_abs_z(rows, 0.0) <= MEDIAN_ABS_Z:
        return 0.0
    if median_abs_z(rows, 1.0) > MEDIAN_ABS_Z:
        return 1.0
    return float(brentq(lambda r: median_abs_z(rows, r) - MEDIAN_ABS_Z, 0.0, 1.0))


#: Forms of the per-trunk bias scale ``b`` tried (``k`` is fitted): a constant (m), a share of
#: the measured DBH, or ``k`` times 180 deg over the scan's median arc of the trunk (a one-sided
#: arc's edge-model bias grows as less of the circle is seen).
BIAS_FORMS = ("constant", "dbh", "inverse_arc")


def bias_scale(rows: list[dict[str, Any]], form: str, k: float) -> np.ndarray:
    """``b`` (m) per row for the bias ``form`` with scale ``k``."""
    if form == "constant":
        return np.full(len(rows), k)
    if form == "dbh":  # the measured DBH, as a map has it (not the reference)
        return k * np.array([r["dbh"] + r["e"] for r in rows])
    if form == "inverse_arc":
        arc = np.array([r.get("arc_deg", math.nan) for r in rows])
        return k * 180.0 / np.where(np.isfinite(arc) & (arc > 1.0), arc, 180.0)
    raise ValueError(form)


def abs_z_bias(rows: list[dict[str, Any]], rho: float, form: str, k: float) -> np.ndarray:
    """|mean error| / sqrt(s^2 (1 + (n - 1) rho) / n + b^2) of the rows with s > 0."""
    n = np.array([r["n"] for r in rows], dtype=float)
    e = np.array([r["e"] for r in rows])
    s = np.array([r["s"] for r in rows])
    ok = s > 0
    b = bias_scale(rows, form, k)[ok]
    se = np.sqrt(s[ok] ** 2 * (1.0 + (n[ok] - 1.0) * rho) / n[ok] + b**2)
    return np.abs(e[ok]) / se


def solve_scale(abs_z: Callable[[float], np.ndarray], upper: float = 100.0) -> float:
    """The scale ``k`` >= 0 making the median of ``abs_z(k)`` (decreasing in ``k``) 0.6745
    (0 if already at or below; bracket doubled from 0.01 up to ``upper``)."""

    def f(k: float) -> float:
        return float(np.median(abs_z(k))) - MEDIAN_ABS_Z

    if f(0.0) <= 0:
        return 0.0
    hi = 0.01
    while f(hi) > 0 and hi < upper:
        hi *= 2.0
    return float(brentq(f, 0.0, hi))


def solve_bias(rows: list[dict[str, Any]], rho: float, form: str) -> float:
    """The ``k`` making the median |z| of ``rows`` 0.6745 (0 if already at or below)."""
    return solve_scale(lambda k: abs_z_bias(rows, rho, form, k))


def bias_loo(rows: list[dict[str, Any]], rhos: tuple[float, ...]) -> dict[str, Any]:
    """Per bias form and rho: ``k`` on all passes, and leave-one-dataset-out (``k`` solved
    without a dataset; median |z| and share |z| < 1 on it)."""
    out: dict[str, Any] = {}
    names = sorted({r["dataset"] for r in rows})
    for form in BIAS_FORMS:
        for rho in rhos:
            res: dict[str, Any] = {"k_all": solve_bias(rows, rho, form)}
            for name in names:
                train = [r for r in rows if r["dataset"] != name]
                test = [r for r in rows if r["dataset"] == name]
                k = solve_bias(train, rho, form)
                z = abs_z_bias(test, rho, form, k)
                res[name] = {
                    "k_without": k,
                    "held_out_median_abs_z": float(np.median(z)),
                    "held_out_share_abs_z_below_1": float(np.mean(z < 1.0)),
                }
            out[f"{form}_rho{rho:g}"] = res
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.01], help="range noise, m")
    ap.add_argument("--models", nargs="+", default=["nearest", "averaging"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--skip", nargs="*", default=["fortls_slice"],
        help="datasets left out (default: fortls_slice, synthetic perfect circles)",
    )  # fmt: skip
    ap.add_argument("--rows-out", help="write the per-pass rows to this JSON file")
    ap.add_argument("--rows-in", help="read the per-pass rows from this JSON file (no scans)")
    ap.add_argument(
        "--scans-out", help="write the per-scan records (per scanner configuration) to this JSON"
    )
    ap.add_argument(
        "--preset", default="stemmap",
        help="detector preset (default stemmap, the default detector; 'none': a bare"
        " DetectorConfig(), Kasa without plausibility tests, what ran before Dec 5)",
    )  # fmt: skip
    ap.add_argument(
        "--scans", action="store_true",
        help="also print the per-scan errors by range, returns and arc (scan_breakdown)",
    )  # fmt: skip
    add_hit_fraction(ap, ANY_HIT)
    a = ap.parse_args()
    rule = ReturnRule(a.hit_fraction)
    preset = None if a.preset == "none" else a.preset
    rows: list[dict[str, Any]] = []
    scans: dict[str, list[dict[str, Any]]] = {}
    if a.rows_in:
        with open(a.rows_in) as f:
            rows = json.load(f)
    else:
        for i, name in enumerate(SLICES):
            if name in a.skip:
                continue
            for model in a.models:
                for noise in a.noise:
                    sc = scans.setdefault(f"{model}_noise{100 * noise:g}cm", [])
                    for r in run_slice(
                        name, model, noise, a.seed + i, preset, sc, return_rule=rule
                    ):
                        rows.append({**r, "model": model, "noise_m": noise})
    if a.rows_out:
        with open(a.rows_out, "w") as f:
            json.dump(rows, f)
    if a.scans_out and scans:
        with open(a.scans_out, "w") as f:
            json.dump(scans, f)
    out: dict[str, Any] = {"preset": a.preset, "n_passes": len(rows), "rho_all": solve_rho(rows)}
    out["median_abs_z_at_rho_all"] = median_abs_z(rows, out["rho_all"])
    out["median_abs_z_at_0.03"] = median_abs_z(rows, 0.03)
    out["median_abs_err_cm"] = 100 * float(np.median([abs(r["e"]) for r in rows]))
    out["median_spread_cm"] = 100 * float(np.median([r["s"] for r in rows]))
    loo = {}
    for name in sorted({r["dataset"] for r in rows}):
        train = [r for r in rows if r["dataset"] != name]
        test = [r for r in rows if r["dataset"] == name]
        rho = solve_rho(train)
        loo[name] = {
            "passes": len(test),
            "rho_without": rho,
            "held_out_median_abs_z": median_abs_z(test, rho),
            "held_out_median_abs_z_at_0.03": median_abs_z(test, 0.03),
            "rho_alone": solve_rho(test),
            "median_n": float(np.median([r["n"] for r in test])),
            "median_abs_err_cm": 100 * float(np.median([abs(r["e"]) for r in test])),
            "median_spread_cm": 100 * float(np.median([r["s"] for r in test])),
        }
    out["leave_one_dataset_out"] = loo
    by = {}
    for model in a.models:
        for noise in a.noise:
            sel = [r for r in rows if r["model"] == model and r["noise_m"] == noise]
            if sel:
                by[f"{model}_noise{100 * noise:g}cm"] = {
                    "passes": len(sel),
                    "rho": solve_rho(sel),
                    "median_abs_z_at_rho_1": median_abs_z(sel, 1.0),
                    "median_abs_err_cm": 100 * float(np.median([abs(r["e"]) for r in sel])),
                    "median_spread_cm": 100 * float(np.median([r["s"] for r in sel])),
                }
    out["by_scanner"] = by
    out["bias"] = bias_loo(rows, (1.0, 0.03))
    if a.scans and scans:
        out["per_scan"] = {k: scan_breakdown(v) for k, v in scans.items()}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
