"""Calibration of the detections' CENTRE (position) covariance on the real-geometry views
(issue 11, Dec 6, "First-echo centre covariance" in docs/algorithms/scan-detection.md); the
sibling of ``first_echo_dbh_z.py`` (the DBH std).

Replays ``real_geometry.py --vantage V``'s scans exactly (:func:`_real_scanning.scene_batches`:
every slice with reference trunks, nearest-return and averaging scanners, 0.25 / 0.5 / 1 deg,
0 / 1 / 3 cm of added range noise, the same vantage points and noise draws), runs the
``stemmap`` preset set up for the scanner (:func:`_real_scanning.matched`; ``--set``: overrides
on top of it), matches the detections to the reference trunks as the benchmark does (visible:
>= 4 returns of the noise-free scan, <= 15 m, DBH 10-100 cm; greedy within radius + 5 cm) and
records for every matched view the centre error against the reference centre (the slice's
full-ring fit), the reported covariance over (x, y, r) and, for the first-echo fits, the fit's
own covariance (``--own``; a wrapper of ``_output_columns``, detections unchanged).

Scores (:func:`cstats`): the centre error split along the line of sight (sensor -> centre,
"along") and across it, each over its stated std (median |z|: 0.674 calibrated; 90th
percentile: 1.645), the Mahalanobis distance ``d = sqrt(e' C^-1 e)`` of the 2D error (median
1.177, 90th percentile 2.146 for a calibrated Gaussian) and the coverage of the 1-sigma and
2-sigma ellipses (0.393 and 0.865), the RMS centre error and the RMS the covariance states
(``sqrt(mean(trace C))``), and the correlation of the along error with the radius error. The
radius entries (:func:`rstats`; Dec 6, "Averaging DBH standard error"): the DBH error over the
stated DBH std ``2 sqrt(C_rr)`` (``dbh_med_z``, ``dbh_p90_z``), the median Mahalanobis distance
of the (x, y, r) error (``med_d3``, 1.538 calibrated) and the along-radius correlation the
covariance states. ``--loo --averaging`` also chooses ``dbh_sd_footprint`` (the pooled median
|z| of the DBH error 0.674 on the training rows) and scores each ``--rows-in`` file apart.

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published without ``--hit-fraction``
(its Dec 6 averaging rows were published at 0 and at 0.3: the commands in
docs/algorithms/scan-detection.md say which). ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/centre_cov_z.py --rows-out /tmp/c.json
    PYTHONPATH=src:benchmarks python benchmarks/centre_cov_z.py --rows-in /tmp/c.json
    PYTHONPATH=src:benchmarks python benchmarks/centre_cov_z.py --models averaging \
        --hit-fraction 0.3 --rows-out /tmp/a3.json                  # the q = 0.3 virtual SICK
    PYTHONPATH=src:benchmarks python benchmarks/centre_cov_z.py --loo --averaging \
        --rows-in /tmp/a0.json /tmp/a3.json                # averaging terms, both models pooled

One JSON object on stdout; a table on stderr.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _real_scanning import ANY_HIT, add_hit_fraction, matched, scene_batches
from first_echo_dbh_z import SHORT, geometry_digest, matched_views, zstats
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

#: Calibrated values of the scores (a 2D Gaussian error with the stated covariance).
CALIBRATED = {
    "med_z": 0.674,
    "p90_z": 1.645,
    "med_d": math.sqrt(2.0 * math.log(2.0)),
    "p90_d": math.sqrt(2.0 * math.log(10.0)),
    "cov1": 1.0 - math.exp(-0.5),
    "cov2": 1.0 - math.exp(-2.0),
    "med_d3": 1.5382,  # sqrt of the chi-square (3 dof) median, 2.366: (x, y, r) together
}


class _Own:
    """``--own``: the fit's own covariance of every output candidate of the numpy path
    (before ``dbh_sd_noise`` and the centre options), looked up by (scan, centre)."""

    def __init__(self) -> None:
        self.table: dict[tuple[int, float, float], list[float]] = {}

    def install(self) -> None:
        import stemmap.scan._pieces as pieces
        import stemmap.scan.detect as detect
        from stemmap.scan._segment_fits import _output_columns

        def wrapped(segs: Any, fitted: Any, ok: Any, cfg: Any = None) -> dict[str, np.ndarray]:
            cols = _output_columns(segs, fitted, ok, cfg)
            if fitted.cov_out is not None:
                own = _output_columns(segs, fitted._replace(cov_out=None), ok)["covs"]
                for c, cv, s in zip(cols["centers"], own, cols["index"], strict=True):
                    self.table[(int(s), float(c[0]), float(c[1]))] = [float(v) for v in cv.ravel()]
            return cols

        detect._output_columns = wrapped  # type: ignore[attr-defined]
        pieces._output_columns = wrapped  # type: ignore[attr-defined]


OWN = _Own()


def view_rows(sc: Any, cfg: DetectorConfig, obs: Any, min_returns: int = 4) -> list[dict]:
    """One row per matched visible view of ``sc`` (a :class:`_real_scanning.SceneBatch`)."""
    sl = sc.sl
    diam = sl.diameters
    rows = []
    for s, t, k, rng_t, rel in matched_views(sc, cfg, obs, min_returns):
        c = obs.centers[k]
        row = {
            "dataset": sl.name,
            "model": sc.model,
            "step": sc.res,
            "noise": sc.noise,
            "scan": s,
            "trunk": int(t),
            "range": float(rng_t[t]),
            "dbh": float(diam[t]),
            "ex": float(c[0] - rel[t, 0]),
            "ey": float(c[1] - rel[t, 1]),
            "er": float(obs.radii[k] - diam[t] / 2.0),
            "cx": float(c[0]),
            "cy": float(c[1]),
            "cov": [float(v) for v in obs.covs[k].ravel()],
            "n": int(obs.n_points[k]),
            "arc": float(obs.arc_deg[k]),
        }
        own = OWN.table.get((s, float(c[0]), float(c[1])))
        if own is not None:
            row["own"] = own
        rows.append(row)
    return rows


def collect(
    ddir: Path,
    n_vantage: int,
    seed: int,
    overrides: dict[str, Any],
    models: tuple[str, ...],
    hit_fraction: float = 0.0,
) -> tuple[list[dict], dict[str, Any]]:
    """Every matched view of every configuration of ``models``, and per model the detections'
    count, digest without the covariances (:func:`first_echo_dbh_z.geometry_digest`) and
    with them (``scan_detection.detections_digest``). ``hit_fraction``: the virtual averaging
    scanner's return threshold (``real_geometry.py --hit-fraction``; 0: any sub-ray)."""
    from _real_scanning import ReturnRule
    from scan_detection import detections_digest

    base = DetectorConfig.preset("stemmap", **overrides)
    rows: list[dict] = []
    digests = {m: hashlib.sha256() for m in models}
    full = {m: hashlib.sha256() for m in models}
    counts = dict.fromkeys(models, 0)
    rule = ReturnRule(min_hit_fraction=hit_fraction)  # 0: ANY_HIT, virtual_scans' default
    for sc in scene_batches(ddir, n_vantage, seed, return_rule=rule):
        if sc.model not in models:
            continue
        cfg = matched(base, sc.model, sc.res)
        OWN.table.clear()
        obs = ScanTrunkDetector(cfg).detect_batch(sc.batch)
        counts[sc.model] += len(obs)
        digests[sc.model].update(geometry_digest(obs).encode())
        full[sc.model].update(detections_digest(obs).encode())
        rows.extend({**r, "hit_fraction": hit_fraction} for r in view_rows(sc, cfg, obs))
    return rows, {
        m: {
            "detections": counts[m],
            "geometry_digest": digests[m].hexdigest()[:16],
            "full_digest": full[m].hexdigest()[:16],
        }
        for m in models
    }


def centre_parts(rows: list[dict], key: str = "cov") -> dict[str, np.ndarray]:
    """Arrays of the rows: error (K, 2), radius error (K,), the line of sight u (K, 2) (sensor
    -> detected centre), and the (K, 3, 3) covariance under ``key``."""
    e = np.array([[r["ex"], r["ey"]] for r in rows]).reshape(-1, 2)
    c = np.array([[r["cx"], r["cy"]] for r in rows]).reshape(-1, 2)
    u = c / np.maximum(np.hypot(c[:, 0], c[:, 1]), 1e-9)[:, None]
    cov = np.array([r.get(key, r["cov"]) for r in rows]).reshape(-1, 3, 3)
    return {"e": e, "er": np.array([r["er"] for r in rows]), "u": u, "cov": cov}


def cstats(e: np.ndarray, u: np.ndarray, cxy: np.ndarray, er: np.ndarray) -> dict[str, Any]:
    """Scores of centre errors ``e`` (K, 2) against the stated 2x2 covariances ``cxy``."""
    if e.shape[0] == 0:
        return {"n": 0}
    v = np.column_stack((-u[:, 1], u[:, 0]))
    ea = np.sum(e * u, axis=1)
    et = np.sum(e * v, axis=1)
    sa = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", u, cxy, u), 1e-18))
    st = np.sqrt(np.maximum(np.einsum("ki,kij,kj->k", v, cxy, v), 1e-18))
    det = cxy[:, 0, 0] * cxy[:, 1, 1] - cxy[:, 0, 1] ** 2
    inv = np.empty_like(cxy)
    inv[:, 0, 0], inv[:, 1, 1] = cxy[:, 1, 1], cxy[:, 0, 0]
    inv[:, 0, 1] = inv[:, 1, 0] = -cxy[:, 0, 1]
    inv /= np.where(det > 0, det, np.nan)[:, None, None]
    d = np.sqrt(np.einsum("ki,kij,kj->k", e, inv, e))
    d = np.where(np.isfinite(d), d, np.inf)
    za, zt = np.abs(ea) / sa, np.abs(et) / st
    corr = float(np.corrcoef(ea, er)[0, 1]) if e.shape[0] > 2 else math.nan
    return {
        "n": int(e.shape[0]),
        "med_z_along": round(float(np.median(za)), 3),
        "p90_z_along": round(float(np.quantile(za, 0.9)), 3),
        "med_z_across": round(float(np.median(zt)), 3),
        "p90_z_across": round(float(np.quantile(zt, 0.9)), 3),
        "med_d": round(float(np.median(d)), 3),
        "p90_d": round(float(np.quantile(d, 0.9)), 3),
        "cov1": round(float(np.mean(d <= 1.0)), 3),
        "cov2": round(float(np.mean(d <= 2.0)), 3),
        "rms_cm": round(100.0 * float(np.sqrt(np.mean(np.sum(e * e, axis=1)))), 2),
        "stated_rms_cm": round(100.0 * float(np.sqrt(np.mean(cxy[:, 0, 0] + cxy[:, 1, 1]))), 2),
        "rms_along_cm": round(100.0 * float(np.sqrt(np.mean(ea * ea))), 2),
        "rms_across_cm": round(100.0 * float(np.sqrt(np.mean(et * et))), 2),
        "med_sd_along_cm": round(100.0 * float(np.median(sa)), 2),
        "med_sd_across_cm": round(100.0 * float(np.median(st)), 2),
        "corr_along_r": round(corr, 3),
    }


def group_key(r: dict, step: bool) -> str:
    name = SHORT.get(r["dataset"], r["dataset"])
    tail = f"{r['step']:g} deg" if step else "all"
    return f"{r['model']} | {name} | {100 * r['noise']:g} cm | {tail}"


def table(rows: list[dict], key: str = "cov", steps: bool = True) -> dict[str, Any]:
    """:func:`cstats` per model x dataset x noise (x step)."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        groups[group_key(r, False)].append(r)
        if steps:
            groups[group_key(r, True)].append(r)
    out = {}
    for k in sorted(groups):
        p = centre_parts(groups[k], key)
        out[k] = {**cstats(p["e"], p["u"], p["cov"][:, :2, :2], p["er"]), **rstats(p)}
    return out


def rstats(p: dict[str, np.ndarray]) -> dict[str, Any]:
    """Scores of the radius entries of :func:`centre_parts` ``p``: the DBH error over the
    stated DBH std ``2 sqrt(C_rr)`` (:func:`first_echo_dbh_z.zstats`, prefixed ``dbh_``), the
    median Mahalanobis distance of the (x, y, r) error over the full covariance (1.538
    calibrated) and the median correlation of the along-sight centre and the radius that the
    covariance states (against ``corr_along_r``, the errors' own)."""
    if p["er"].size == 0:
        return {}
    cov, u = p["cov"], p["u"]
    z = zstats(2.0 * p["er"], 2.0 * np.sqrt(np.maximum(cov[:, 2, 2], 0.0)))
    e3 = np.column_stack((p["e"], p["er"]))
    try:
        d3 = np.sqrt(np.einsum("ki,ki->k", e3, np.linalg.solve(cov, e3[:, :, None])[:, :, 0]))
        med_d3 = round(float(np.median(np.where(np.isfinite(d3), d3, np.inf))), 3)
    except np.linalg.LinAlgError:
        med_d3 = math.nan
    saa = np.einsum("ki,kij,kj->k", u, cov[:, :2, :2], u)
    sar = np.einsum("ki,ki->k", u, cov[:, :2, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = sar / np.sqrt(saa * cov[:, 2, 2])
    return {
        **{f"dbh_{k}": v for k, v in z.items() if k != "n"},
        "med_d3": med_d3,
        "stated_corr_along_r": round(float(np.nanmedian(rho)), 3),
    }


#: The real-bark slices the centre terms are chosen on, leave one out (FORTLS: synthetic
#: circles, no outline to learn from; aRchi: an untrusted reference; both reported).
BARK = ("treels_pine_plot", "treels_pine", "lidr_dbh")


def candidate_covs(rows: list[dict], b: float, along: float, across: float) -> np.ndarray:
    """The covariance :func:`stemmap.scan._centre_cov.centre_covs` would report for every
    nearest-return row (``--own`` rows, run with the DBH outline ``b``): the noise factor
    ``k`` from the reported and own ``C_rr`` (``k^2 = (C_rr - b^2 / 4) / own C_rr``)."""
    from stemmap.scan._centre_cov import centre_covs

    rep = np.array([r["cov"] for r in rows]).reshape(-1, 3, 3)
    own = np.array([r.get("own", r["cov"]) for r in rows]).reshape(-1, 3, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.sqrt(np.maximum(rep[:, 2, 2] - 0.25 * b * b, 0.0) / own[:, 2, 2])
    k = np.where(np.isfinite(k), np.maximum(k, 1.0), 1.0)  # k >= 1 by construction
    c = np.array([[r["cx"], r["cy"]] for r in rows]).reshape(-1, 2)
    return centre_covs(rep, k, c, b, along, across)


def _median_z(rows: list[dict], cov: np.ndarray, axis: str) -> float:
    p = centre_parts(rows)
    u = p["u"] if axis == "along" else np.column_stack((-p["u"][:, 1], p["u"][:, 0]))
    e = np.sum(p["e"] * u, axis=1)
    sd = np.sqrt(np.einsum("ki,kij,kj->k", u, cov[:, :2, :2], u))
    return float(np.median(np.abs(e) / sd))


def _solve(f: Any, hi: float) -> float:
    """The root of the decreasing ``f(x) - 0.674`` in [0, hi] (bisection; 0 if f(0) <= 0.674)."""
    lo = 0.0
    if f(lo) <= CALIBRATED["med_z"]:
        return 0.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) > CALIBRATED["med_z"] else (lo, mid)
    return 0.5 * (lo + hi)


def choose(rows: list[dict], b: float) -> tuple[float, float]:
    """``centre_sd_along`` (gain) then ``centre_sd_across`` (m) so that the pooled median |z|
    along, then across, the line of sight of ``rows`` is 0.674 (the rule of ``b``)."""
    g = _solve(lambda x: _median_z(rows, candidate_covs(rows, b, x, 0.0), "along"), 10.0)
    c = _solve(lambda x: _median_z(rows, candidate_covs(rows, b, g, x), "across"), 0.2)
    return g, c


def averaging_candidate_covs(
    rows: list[dict], cfg: DetectorConfig, f: float, c: float, h: float = 0.0
) -> np.ndarray:
    """The covariance :func:`stemmap.scan._centre_cov.averaging_centre_covs` would report for
    every averaging row (run with the averaging terms off: ``cov`` is the fit's own), with the
    outline term of ``cfg`` (``centre_sd_along`` times ``dbh_sd_outline / 2``), the footprint
    share ``f`` and the across std ``c`` (m); ``h`` > 0: the radius terms too
    (``dbh_sd_footprint`` = ``h``, the radius outline ``dbh_sd_outline / 2``)."""
    from stemmap.scan._centre_cov import averaging_centre_covs

    own = np.array([r["cov"] for r in rows]).reshape(-1, 3, 3)
    xy = np.array([[r["cx"], r["cy"]] for r in rows]).reshape(-1, 2)
    outline = 0.5 * cfg.centre_sd_along * cfg.dbh_sd_outline
    ro = 0.5 * cfg.dbh_sd_outline if h > 0 else 0.0
    theta = math.radians(cfg.beam_divergence_deg)
    return averaging_centre_covs(own, xy, outline, f, theta, c, ro, h)


def _median_z_dbh(rows: list[dict], cov: np.ndarray) -> float:
    er = np.array([r["er"] for r in rows])
    return float(np.median(np.abs(er) / np.sqrt(cov[:, 2, 2])))


def choose_averaging_radius(rows: list[dict], cfg: DetectorConfig) -> float:
    """``dbh_sd_footprint`` so that the pooled median |z| of the DBH error of ``rows`` (the
    fit's own covariance) is 0.674 with the outline's ``dbh_sd_outline / 2`` on the radius
    (the rule of ``b``; the radius entries do not depend on the centre terms)."""
    return _solve(
        lambda x: _median_z_dbh(rows, averaging_candidate_covs(rows, cfg, 0.0, 0.0, x)), 10.0
    )


def choose_averaging(rows: list[dict], cfg: DetectorConfig) -> tuple[float, float]:
    """``centre_sd_footprint`` then ``centre_sd_across_averaging`` (m) by the rule of
    :func:`choose`: the pooled median |z| along, then across, the line of sight is 0.674."""
    f = _solve(
        lambda x: _median_z(rows, averaging_candidate_covs(rows, cfg, x, 0.0), "along"), 10.0
    )
    c = _solve(lambda x: _median_z(rows, averaging_candidate_covs(rows, cfg, f, x), "across"), 0.2)
    return f, c


def loo(rows: list[dict], b: float, cfg: DetectorConfig | None = None) -> dict[str, Any]:
    """Leave one real-bark dataset out: the terms chosen on the other two (:func:`choose`;
    with ``cfg``, the averaging rows and :func:`choose_averaging`), scored on the held-out one
    per noise level; FORTLS and aRchi with the terms of all three."""
    model = "nearest" if cfg is None else "averaging"
    sub_rows = [r for r in rows if r["model"] == model]
    out: dict[str, Any] = {}
    for held in (*BARK, "fortls_slice", "archi_tree1"):
        train = [r for r in sub_rows if r["dataset"] in BARK and r["dataset"] != held]
        test = [r for r in sub_rows if r["dataset"] == held]
        if not test:
            continue
        if cfg is None:
            g, c = choose(train, b)
            cov = candidate_covs(test, b, g, c)
            terms = {"along": round(g, 3), "across_cm": round(100 * c, 3)}
        else:
            g, c = choose_averaging(train, cfg)
            h = choose_averaging_radius(train, cfg)
            cov = averaging_candidate_covs(test, cfg, g, c, h)
            terms = {"footprint": round(g, 3), "across_cm": round(100 * c, 3)}
            terms["dbh_footprint"] = round(h, 3)
        for r, cv in zip(test, cov, strict=True):
            r["_cand"] = [float(v) for v in cv.ravel()]
        cells = {}
        sources = sorted({_source(r) for r in test})
        for src, noise in ((s, n) for s in sources for n in (0.0, 0.01, 0.03)):
            sub = [r for r in test if r["noise"] == noise and _source(r) == src]
            if sub:
                p = centre_parts(sub, "_cand")
                head = f"{src} | " if len(sources) > 1 else ""
                cells[f"{head}{100 * noise:g} cm"] = {
                    **cstats(p["e"], p["u"], p["cov"][:, :2, :2], p["er"]),
                    **(rstats(p) if cfg is not None else {}),
                }
        out[SHORT.get(held, held)] = {**terms, **cells}
    return out


def _source(r: dict) -> str:
    """The rows' scanner model within a family: the averaging scanner's return threshold
    (rows of :func:`collect`), else the ``--rows-in`` file's name."""
    if "hit_fraction" in r:
        return f"q {r['hit_fraction']:g}"
    return str(r.get("source", ""))


def sim_rows(seed: int, overrides: dict[str, Any]) -> list[dict]:
    """The simulator's averaging rows (a check of the code; nothing is chosen on it): every
    matched eligible (tree, detection) pair of ``scan_detection.py``'s 400-scan drive and the
    ``stemmap demo`` drive of ``seed`` (:func:`_scan_sim._runs`; the scoring of
    :func:`_scan_sim.tree_errors`: its gate, returns, range and diameter) with the centre
    error in the sensor frame and the reported covariance of the ``stemmap`` preset with
    ``overrides``."""
    from _scan_sim import SCENARIO, _runs, scan_truth
    from stemmap.eval.matching import match_points

    sc = SCENARIO["scoring"]
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides))
    rows: list[dict] = []
    for drive, run in zip(("benchmark", "demo"), _runs(int(seed)), strict=True):
        obs = det.detect_batch(run.scans)
        tdiam = run.stand.diameters
        for k in range(run.true_poses.poses.shape[0]):
            sel = np.flatnonzero(obs.index == k)
            local, rng_k, elig = scan_truth(
                run,
                k,
                min_returns=sc["min_returns"],
                max_range=sc["max_range_m"],
                min_dbh=sc["min_dbh_m"],
            )
            m = match_points(obs.centers[sel], local, sc["gate_m"])
            for i, j in m.pairs:
                if not elig[j]:
                    continue
                q = sel[i]
                cen = obs.centers[q]
                rows.append(
                    {
                        "dataset": f"sim_{drive}",
                        "model": "averaging",
                        "step": float(math.degrees(abs(run.scans.angle_increment))),
                        "noise": 0.0,
                        "scan": k,
                        "trunk": int(j),
                        "range": float(rng_k[j]),
                        "dbh": float(tdiam[j]),
                        "ex": float(cen[0] - local[j, 0]),
                        "ey": float(cen[1] - local[j, 1]),
                        "er": float(obs.radii[q] - tdiam[j] / 2.0),
                        "cx": float(cen[0]),
                        "cy": float(cen[1]),
                        "cov": [float(v) for v in obs.covs[q].ravel()],
                    }
                )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--vantage", type=int, default=20, help="vantage points per dataset")
    ap.add_argument("--seed", type=int, default=11, help="real_geometry.py's --seed")
    ap.add_argument("--set", default="{}", help="JSON overrides of the stemmap preset")
    ap.add_argument("--models", default="nearest,averaging", help="scanner models, comma separated")
    add_hit_fraction(ap, ANY_HIT)
    ap.add_argument("--own", action="store_true", help="also record the fit's own covariance")
    ap.add_argument("--no-steps", action="store_true", help="no per-step rows in the table")
    ap.add_argument("--rows-out", type=Path, default=None)
    ap.add_argument(
        "--rows-in", type=Path, nargs="+", default=None, help="rows of earlier runs (pooled)"
    )
    ap.add_argument("--loo", action="store_true", help="choose the centre terms (--own rows)")
    ap.add_argument(
        "--sim", type=int, nargs="+", default=None, help="the simulator's rows of these seeds"
    )
    ap.add_argument(
        "--averaging",
        action="store_true",
        help="with --loo: the averaging terms on the averaging rows (run with them off)",
    )
    args = ap.parse_args(argv)
    if args.own:
        OWN.install()
    digest: dict[str, Any] = {}
    if args.sim is not None:
        rows = [r for seed in args.sim for r in sim_rows(seed, json.loads(args.set))]
        if args.rows_out is not None:
            args.rows_out.write_text(json.dumps(rows))
    elif args.rows_in is not None:
        rows = [
            {"source": path.stem, **r}
            for path in args.rows_in
            for r in json.loads(path.read_text())
        ]
    else:
        ddir = require_datasets_dir(args.datasets)
        models = tuple(args.models.split(","))
        rows, digest = collect(
            ddir, args.vantage, args.seed, json.loads(args.set), models, args.hit_fraction
        )
        if args.rows_out is not None:
            args.rows_out.write_text(json.dumps(rows))
    if args.loo:
        cfg = DetectorConfig.preset("stemmap", **json.loads(args.set))
        res = loo(rows, cfg.dbh_sd_outline, cfg if args.averaging else None)
        for key, v in res.items():
            print(f"{key:14s} {json.dumps(v)}", file=sys.stderr)
        head = {"benchmark": "centre_cov_z", "loo": True, "b": cfg.dbh_sd_outline}
        print(json.dumps({**head, "averaging": args.averaging, **res}))
        return 0
    tab = table(rows, steps=not args.no_steps)
    for key, v in tab.items():
        print(f"{key:44s} {json.dumps(v)}", file=sys.stderr)
    out = {"benchmark": "centre_cov_z", "set": args.set, "calibrated": CALIBRATED}
    print(json.dumps({**out, "digests": digest, "table": tab}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
