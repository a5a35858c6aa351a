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

Each visible trunk also gets one *cause* (``causes``, the per-trunk table of issue 11's tenth
round), the first that applies:

- found: ``ok`` (|DBH error| <= 3 cm), else ``merge_bias`` (the detection holds a return beyond
  the trunk's own and its error is > 1 cm farther from zero than the same detector's on the
  trunk's own beams alone), else ``fit_bias:bark`` (the ring's own points on the side seen lie
  > 1 cm RMS off the reference circle: a non-circular outline) or
  ``fit_bias:partial_arc`` (they lie on it, the fit of the one-sided arc is off);
- missed: ``beams`` (fewer own returns than ``min_points_partial`` and no candidate, or one
  dropped by a count test: range / beam count), ``merge:<reason>`` / ``split:<reasons>`` as
  above, ``reject:<reason>`` (the trunk's own candidate dropped by that plausibility test),
  ``no_candidate``.

Per cause: how many, and for the found ones the DBH error at <= 10 m (n, RMSE, bias, and the
cause's share of the total bias: sum of its errors / number of found trunks). Per reference
trunk: ring-fit diameter next to the girth-tape diameter (convex-hull perimeter / pi, which
for a convex outline is also its mean caliper width, Cauchy's formula) and the
area-equivalent diameter of the ring's own points (``reference_check``).

"Over the trunk": the candidate's mean return lies within its half width (plus the trunk's
angular radius) of the trunk's bearing and within the trunk diameter plus the candidate's
width of its range. Next to it, *perfect segmentation*: the same detector (and the textbook
Kasa detector) on scans that keep only the trunk's own beams (every other beam masked):
what is left when nothing is merged. And per reference trunk its quality: ring RMS, coverage,
sectors filled (the outline joined across them), and the spread of the reference diameter
when each 30-degree sector of the ring is left out in turn (jackknife).

Return rule: the virtual averaging (SICK-class) scanner's is ``--hit-fraction`` (the share of
the footprint that must hit, as ``real_geometry.py``'s), default 0: any sub-ray
(``_real_scanning.ANY_HIT``, ``virtual_scans``' own default; of 25 sub-rays since Dec 5, of
5 before), the rule of every number this script has published. ``real_geometry.py``'s
virtual SICK has used 0.3, the real LMS200's, since Dec 6.

Usage::

    python benchmarks/real_geometry_diagnose.py                    # 0.5 deg nearest, no noise
    python benchmarks/real_geometry_diagnose.py --model averaging --noise 0.01
    python benchmarks/real_geometry_diagnose.py --set '{"arc_refit": true}'
    python benchmarks/real_geometry_diagnose.py --only lidr_dbh archi_tree1 --no-misses

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _real_scanning import (  # shared with real_geometry.py
    ANY_HIT,
    TEXTBOOK,
    ReturnRule,
    add_hit_fraction,
    matched,
    vantage_points,
)
from _real_scanning import error_stats as _stats
from _real_scanning import greedy_match as _match
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


def miss_class(
    rej: dict[str, Any],
    rej_scan: np.ndarray,
    reasons: np.ndarray,
    s: int,
    rel: np.ndarray,
    diam: float,
    own: int,
) -> tuple[np.ndarray, str]:
    """The rejected candidates of scan ``s`` over a missed trunk (at ``rel``, ``own`` own
    returns) and the miss's class: ``no_candidate``, ``split:<reasons>``, or the reason of
    the one candidate (``merge:`` when it holds more than one return beyond the trunk's)."""
    near = _over(rej, np.flatnonzero(rej_scan == s), rel, diam)
    if near.size == 0:
        return near, "no_candidate"
    if near.size > 1:
        return near, "split:" + "/".join(sorted(set(reasons[near].tolist())))
    j = int(near[0])
    return near, ("merge:" if int(rej["n_points"][j]) > own + 1 else "") + str(reasons[j])


def visible_views(
    sl: RealSlice, vp: np.ndarray, hit: np.ndarray, obs: Any, min_returns: int
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]]:
    """Every visible trunk view (>= ``min_returns`` own returns, <= 15 m, DBH 10-100 cm) of
    the scans from ``vp``: scan, trunk, the trunks relative to the scanner and their ranges,
    the scan's detections (mask into ``obs``) and their greedy match, the own returns."""
    diam = sl.diameters
    for s in range(vp.shape[0]):
        rel = sl.centers - vp[s]
        rng_t = np.hypot(rel[:, 0], rel[:, 1])
        m = obs.index == s
        match = _match(obs.centers[m], rel, diam / 2.0 + 0.05)
        for t in range(len(sl.refs)):
            own = int((hit[s] == t).sum())
            if own >= min_returns and rng_t[t] <= 15.0 and 0.1 <= diam[t] <= 1.0:
                yield s, t, rel, rng_t, m, match, own


def view_row(s: int, t: int, diam: float, rng_t: float, own: int, c: str) -> dict[str, Any]:
    """The identity of one trunk view (scan ``s``, trunk ``t``) in a per-view listing."""
    return {
        "scan": s,
        "trunk": t,
        "diameter_cm": round(100.0 * diam, 1),
        "range_m": round(rng_t, 2),
        "own_returns": own,
        "class": c,
    }


def own_beams_only(batch: ScanBatch, hit: np.ndarray, s: int, t: int) -> ScanBatch:
    """Scan ``s`` of ``batch`` with only trunk ``t``'s own beams (``hit``, every other beam
    masked): what the detector gives under perfect segmentation."""
    return ScanBatch(
        ranges=np.where(hit[s] == t, batch.ranges[s], np.inf)[None, :],
        times=batch.times[s : s + 1],
        angle_min=batch.angle_min,
        angle_increment=batch.angle_increment,
        range_min=batch.range_min,
        range_max=batch.range_max,
    )


def diagnose(
    sl: RealSlice,
    cfg: DetectorConfig,
    model: str,
    res: float,
    noise: float,
    seed: int,
    n_vantage: int,
    min_returns: int,
    return_rule: ReturnRule,
) -> dict[str, Any]:
    """Classify every visible trunk of one slice (module docstring; ``return_rule``: the
    averaging scanner's)."""
    rng = np.random.default_rng(seed)
    vp = vantage_points(sl, n_vantage, rng)
    ranges0, hit = virtual_scans(
        sl.xy,
        sl.labels,
        vp,
        resolution_deg=res,
        model=model,
        centers=sl.centers,  # type: ignore[arg-type]
        **return_rule.kwargs(),
    )
    batch = noisy_batch(ranges0, res, noise, rng)
    det = ScanTrunkDetector(matched(cfg, model, res))
    obs = det.detect_batch(batch)
    rej = det.rejected(batch)
    rej_scan = np.asarray(rej["scan_index"])
    reasons = np.asarray(rej["reason"], dtype=object)
    dets = {"stemmap": det, "textbook_kasa": ScanTrunkDetector(TEXTBOOK)}
    classes: Counter[str] = Counter()
    causes: list[tuple[str, float, float]] = []  # (cause, range m, DBH error cm or NaN)
    err: list[float] = []
    alone: dict[str, list[tuple[float, float]]] = {k: [] for k in dets}
    misses: list[dict[str, Any]] = []
    diam = sl.diameters
    for s, t, rel, rng_t, m, match, own in visible_views(sl, vp, hit, obs, min_returns):
        solo = own_beams_only(batch, hit, s, t)  # perfect segmentation
        solo_err = math.nan
        for name, d in dets.items():
            o = d.detect_batch(solo)
            k = _match(o.centers, rel[t : t + 1], diam[t : t + 1] / 2.0 + 0.05)[0]
            e = (2.0 * o.radii[k] - diam[t]) * 100.0 if k >= 0 else math.nan
            alone[name].append((float(rng_t[t]), e))
            if name == "stemmap":
                solo_err = e
        if match[t] >= 0:
            n = int(obs.n_points[m][match[t]])
            classes["found_extra" if n > own + 1 else "found"] += 1
            e_det = (2.0 * obs.radii[m][match[t]] - diam[t]) * 100.0
            if rng_t[t] <= 10.0:
                err.append(e_det)
            causes.append(
                (
                    _found_cause(
                        e_det,
                        solo_err,
                        n > own,
                        _outline_rms(sl, t, vp[s]),
                    ),
                    float(rng_t[t]),
                    e_det,
                )
            )
            continue
        near, c = miss_class(rej, rej_scan, reasons, s, rel[t], float(diam[t]), own)
        classes[c] += 1
        cause = c
        if own < cfg.min_points_partial and (
            c == "no_candidate" or c in ("min_points", "min_points_partial")
        ):
            cause = "beams"
        elif ":" not in c and c != "no_candidate":
            cause = "reject:" + c
        causes.append((cause, float(rng_t[t]), math.nan))
        misses.append(
            {
                **view_row(s, t, float(diam[t]), float(rng_t[t]), own, c),
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
        "causes": cause_table(causes),
        "perfect_segmentation": {k: summary(v) for k, v in alone.items()},
        "misses": misses,
        "references": [
            {**reference_jackknife(sl, t), **reference_check(sl, t)} for t in range(len(sl.refs))
        ],
    }


#: A found trunk's DBH error counts as ``ok`` within this many cm (the issue's RMSE target).
OK_CM = 3.0
#: ... and as ``merge_bias`` when the merged detection is this much (cm) farther from zero
#: than the fit of the trunk's own beams alone.
MERGE_EXCESS_CM = 1.0
#: The ring's points on the side seen farther than this RMS (m) from the reference circle: a
#: non-circular outline (``fit_bias:bark``), else ``fit_bias:partial_arc``.
OUTLINE_RMS_M = 0.01


def _found_cause(e_det: float, e_solo: float, merged: bool, outline_rms: float) -> str:
    """Cause of a found trunk's DBH error (module docstring)."""
    if abs(e_det) <= OK_CM:
        return "ok"
    if merged and not abs(e_det) <= abs(e_solo) + MERGE_EXCESS_CM:  # (NaN solo: merge)
        return "merge_bias"
    return "fit_bias:bark" if outline_rms > OUTLINE_RMS_M else "fit_bias:partial_arc"


def _outline_rms(sl: RealSlice, t: int, vantage: np.ndarray) -> float:
    """RMS (m) off the reference circle of the ring's own points on the side of trunk ``t``
    seen from ``vantage`` (angle from the sensor direction below acos(r / d)): the outline the
    scan samples, without the first-echo footprint effect of the virtual beams."""
    ref = sl.refs[t]
    c = np.array([ref["x"], ref["y"]])
    r = 0.5 * ref["diameter"]
    q = sl.xy[sl.labels == t][: int(ref["n_points"])] - c
    u = vantage - c
    d = float(np.hypot(*u))
    rad = np.hypot(*q.T)
    seen = (q @ u) / np.maximum(rad * d, 1e-12) > r / d
    res = rad[seen] - r
    return float(np.sqrt(np.mean(res * res))) if res.size else math.nan


def cause_table(rows: list[tuple[str, float, float]]) -> dict[str, Any]:
    """Count per cause; for the found causes the DBH error at <= 10 m (n, RMSE, bias) and the
    cause's share of the bias of all found trunks at <= 10 m (sum of its errors / their
    number, cm: the shares add up to the bias)."""
    found10 = [e for _, r, e in rows if math.isfinite(e) and r <= 10.0]
    out: dict[str, Any] = {}
    for cause in sorted({c for c, _, _ in rows}):
        mine = [(r, e) for c, r, e in rows if c == cause]
        entry: dict[str, Any] = {"n": len(mine)}
        e10 = np.array([e for r, e in mine if math.isfinite(e) and r <= 10.0])
        if any(math.isfinite(e) for _, e in mine):
            entry["within_10m"] = _stats(e10)
            entry["bias_share_cm"] = round(float(e10.sum()) / len(found10), 2) if found10 else None
        out[cause] = entry
    return out


def reference_check(sl: RealSlice, t: int, sector_deg: float = 10.0) -> dict[str, Any]:
    """The reference trunk ``t``'s ring-fit diameter next to the outline's girth-tape diameter
    (perimeter / pi; for a convex outline also its mean caliper width over all directions,
    Cauchy's formula) and area-equivalent diameter, cm. The outline is the polygon of the
    median radius of the ring's own points per ``sector_deg`` sector (robust to the cloud's
    range noise, which would inflate a convex hull); sectors without points take the radius
    interpolated between their seen neighbours. A circle gives the same three; a lobed or
    flattened outline does not, and a 2D scan from one side measures one caliper width of it.
    Also the largest and smallest sector radius off the ring's (cm)."""
    ref = sl.refs[t]
    c = np.array([ref["x"], ref["y"]])
    q = sl.xy[sl.labels == t][: int(ref["n_points"])] - c  # the ring's inliers, not the fill
    n_sec = round(360.0 / sector_deg)
    sec = np.floor((np.degrees(np.arctan2(q[:, 1], q[:, 0])) + 180.0) / sector_deg).astype(int)
    sec %= n_sec
    rad = np.hypot(*q.T)
    mid = np.radians(-180.0 + sector_deg * (np.arange(n_sec) + 0.5))
    seen = np.unique(sec)
    med = np.array([np.median(rad[sec == k]) for k in seen])
    # circular interpolation over the unseen sectors
    r = np.interp(
        np.arange(n_sec), np.concatenate((seen - n_sec, seen, seen + n_sec)), np.tile(med, 3)
    )
    x, y = r * np.cos(mid), r * np.sin(mid)
    perim = float(np.sum(np.hypot(np.diff(x, append=x[0]), np.diff(y, append=y[0]))))
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    dev = 100.0 * (med - 0.5 * ref["diameter"])
    return {
        "ring_diameter_cm": round(100.0 * ref["diameter"], 2),
        "girth_diameter_cm": round(100.0 * perim / math.pi, 2),
        "area_diameter_cm": round(100.0 * 2.0 * math.sqrt(area / math.pi), 2),
        "sector_radius_off_ring_cm": [round(float(dev.min()), 2), round(float(dev.max()), 2)],
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
    ap.add_argument("--no-misses", action="store_true", help="leave out the per-miss list")
    add_hit_fraction(ap, ANY_HIT)
    args = ap.parse_args(argv)
    ddir = require_datasets_dir(args.datasets)
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
            ReturnRule(args.hit_fraction),
        )
        if args.no_misses:
            del out["datasets"][name]["misses"]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
