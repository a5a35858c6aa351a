"""Diagnostic: what a sparse cell's lost stems hold, and whether they can be measured at all.

For each cell (cloud x transform x seed, the draws of ``cloud_robustness.py`` / ``cloud_loo.py``)
the transformed file goes through ``detect_stems_file`` with the per-stem step traced, as
``cloud_lost_stems.py`` does (its ``stage``: where the per-stem step stopped, or ``no slice
fit`` when no call of it fitted a circle near the stem). For every checked baseline stem the
cell misses it reports what the data hold and what one fit over a taller band makes of them:

* ``axis``: the stem's axis on the *shipped* cloud (:func:`stemmap.cloud.axisfit._fit_axes`, a
  leaning ring stack with a taper prior, on the shipped returns within r + 5 cm of the
  baseline stem at 0.8-2.0 m): where to look, not what to find;
* ``counts_10cm`` / ``_20cm`` / ``_40cm``: the transformed cloud's returns within r + 5 cm of
  that axis per 0.1 / 0.2 / 0.4 m slice over 0.8-2.0 m (heights from the baseline's ground
  model), and ``arc_deg`` per 0.4 m slice and over the band, about the axis;
* ``fit_band`` / ``fit_tall``: the same ring-stack fit on the transformed cloud's returns
  within r + 10 cm of the axis over 0.8-2.0 m and over 0.5-3.0 m (start: a Kasa circle of
  those returns; Huber weights and trimming as the detector's): DBH, RMS, inliers, arc, and
  the DBH standard error (the larger of the posterior's and the delete-one-bin jackknife's,
  0.4 m bins), with ``minus_shipped_cm`` (against the baseline's DBH) and ``minus_ring_cm``
  (against the fixed ring reference; ``ring_full`` says whether it is a full ring).

The selection knows where the stem is (the shipped cloud's axis), so the fits are an upper
bound of what a detector that must find the stem first could measure; what they cannot
reproduce is not measurable from these returns. ``--set key=value`` as in
``cloud_robustness.py`` (the detection only).

    PYTHONPATH=src:benchmarks python benchmarks/cloud_sparse_stems.py --cloud treels_pine_plot \\
        --transforms subsample_20,subsample_10 --seeds 0,1,2,3,4
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

import cloud_robustness as cr
from _cloud_refs import CLOUDS, reference_of_each
from cloud_lost_stems import cell_args, lost_report, traced
from stemmap.cloud.axisfit import _fit_axes, _jackknife_var_r
from stemmap.cloud.slicefit import _segment_arcs
from stemmap.cloud.stems import detect_stems_file

BAND = (0.8, 2.0)
TALL = (0.5, 3.0)
BIN = 0.4


def _arc(p: np.ndarray, c: np.ndarray) -> float:
    if p.shape[0] < 2:
        return 0.0
    return float(_segment_arcs(p, np.zeros(p.shape[0], np.int64), 1, c[None, :])[0])


def _axis_at(ax: np.ndarray, h: np.ndarray, bh: float) -> np.ndarray:
    return np.column_stack((ax[0] + ax[2] * (h - bh), ax[1] + ax[3] * (h - bh)))


def shipped_axis(
    xyz: np.ndarray, hgt: np.ndarray, xy: np.ndarray, r: float, floor: float, bh: float
) -> np.ndarray:
    """(cx, cy, lean x, lean y) of the stem on the shipped cloud (band returns within r + 5
    cm of the baseline centre); the baseline's centre, vertical, if the fit fails."""
    m = (hgt >= BAND[0]) & (hgt <= BAND[1]) & (np.hypot(*(xyz[:, :2] - xy).T) <= r + 0.05)
    if m.sum() < 20:
        return np.array([xy[0], xy[1], 0.0, 0.0])
    s = np.clip(((hgt[m] - BAND[0]) // BIN).astype(np.int64), 0, 2)
    f = _fit_axes(xyz[m, :2], hgt[m] - bh, np.zeros(int(m.sum()), np.int64), s, 3, floor)
    t = f.params[0]
    if not f.alive[0] or not np.all(np.isfinite(t)) or abs(t[4] - r) > 0.3 * r:
        return np.array([xy[0], xy[1], 0.0, 0.0])
    return np.asarray(t[:4], dtype=np.float64)


def ring_fit(
    xyz: np.ndarray,
    hgt: np.ndarray,
    ax: np.ndarray,
    r: float,
    rng: tuple[float, float],
    floor: float,
    bh: float,
) -> dict[str, Any] | None:
    """The ring-stack fit of the returns within r + 10 cm of the axis over ``rng``."""
    m = (hgt >= rng[0]) & (hgt <= rng[1])
    d = np.hypot(*(xyz[:, :2] - _axis_at(ax, hgt, bh)).T)
    m &= d <= r + 0.10
    n = int(m.sum())
    nb = max(3, round((rng[1] - rng[0]) / BIN))
    if n < 8:
        return {"n": n}
    s = np.clip(((hgt[m] - rng[0]) / ((rng[1] - rng[0]) / nb)).astype(np.int64), 0, nb - 1)
    f = _fit_axes(xyz[m, :2], hgt[m] - bh, np.zeros(n, np.int64), s, nb, floor)
    if not f.alive[0] or not np.isfinite(f.params[0, 4]):
        return {"n": n}
    var = max(float(f.cov[0, 4, 4]), _jackknife_var_r(f, 0, floor))
    return {
        "n": n,
        "dbh_cm": round(200 * float(f.params[0, 4]), 2),
        "rms_mm": round(1000 * float(f.rms[0]), 1),
        "inliers": int(f.n_in[0]),
        "arc_deg": round(float(f.arcs[0])),
        "lean_deg": round(math.degrees(math.atan(math.hypot(*f.params[0, 2:4]))), 1),
        "dbh_se_cm": round(200 * math.sqrt(var), 2) if math.isfinite(var) else None,
        "bins_with_3": int((f.slice_inliers[0] >= 3).sum()),
        "bins": nb,
    }


def stem_data(
    xyz: np.ndarray, hgt: np.ndarray, ax: np.ndarray, r: float, floor: float, bh: float
) -> dict[str, Any]:
    """Counts per 10 / 20 / 40 cm slice and arcs of the returns within r + 5 cm of the axis."""
    inb = (hgt >= BAND[0]) & (hgt < BAND[1])
    c = _axis_at(ax, hgt, bh)
    near = inb & (np.hypot(*(xyz[:, :2] - c).T) <= r + 0.05)
    out: dict[str, Any] = {}
    for th in (0.1, 0.2, 0.4):
        k = round((BAND[1] - BAND[0]) / th)
        s = np.clip(((hgt[near] - BAND[0]) // th).astype(np.int64), 0, k - 1)
        out[f"counts_{round(100 * th)}cm"] = " ".join(
            str(int(v)) for v in np.bincount(s, minlength=k)
        )
    rel = xyz[near, :2] - c[near]
    s4 = np.clip(((hgt[near] - BAND[0]) // 0.4).astype(np.int64), 0, 2)
    out["arc_deg_40cm"] = " ".join(str(round(_arc(rel[s4 == s], np.zeros(2)))) for s in range(3))
    out["arc_deg_band"] = round(_arc(rel, np.zeros(2)))
    return out


def main() -> None:
    args, root, cfg = cell_args(__doc__ or "", "treels_pine_plot")
    bl = cr.run_baseline(args.cloud, root / CLOUDS[args.cloud])
    if bl.ground is None:
        raise SystemExit("error: the baseline has no ground model")
    bh = cfg.breast_height
    floor = float(bl.det.noise_floor)
    h_ship = bl.ground.height_of(bl.xyz)
    refs = reference_of_each(bl.refs, bl.det.xy)
    axes = {
        i: shipped_axis(bl.xyz, h_ship, bl.det.xy[i], bl.det.diameter[i] / 2, floor, bh)
        for i in bl.checked
    }
    cells = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            for name, prep, f in cr.transformed_files(
                bl, args.transforms.split(","), Path(tmp), seed
            ):
                with traced() as calls:
                    det = detect_stems_file(f, cfg)
                row = cr.score_run(name, bl, det, prep)
                pairs = cr._match(bl.det.xy, bl.det.diameter, det.xy)
                found = {i for i, _ in pairs}
                hgt = bl.ground.height_of(prep.xyz)
                lost = []
                for i in sorted(i for i in bl.checked if i not in found):
                    r = float(bl.det.diameter[i] / 2)
                    rep = lost_report(bl, i, calls)
                    ring = refs[i][1] if refs[i] is not None else None
                    item: dict[str, Any] = {
                        "stem": i,
                        "shipped_dbh_cm": round(200 * r, 2),
                        "ring_cm": None if ring is None else round(100 * ring.diameter, 2),
                        "ring_full": None if ring is None else ring.full,
                        "stage": ", ".join(sorted({c["stage"] for c in rep["calls"]}))
                        or "no slice fit",
                        **stem_data(prep.xyz, hgt, axes[i], r, floor, bh),
                    }
                    for key, rng in (("fit_band", BAND), ("fit_tall", TALL)):
                        fr = ring_fit(prep.xyz, hgt, axes[i], r, rng, floor, bh)
                        if fr is not None and "dbh_cm" in fr:
                            fr["minus_shipped_cm"] = round(fr["dbh_cm"] - 200 * r, 2)
                            if ring is not None:
                                fr["minus_ring_cm"] = round(fr["dbh_cm"] - 100 * ring.diameter, 2)
                        item[key] = fr
                    lost.append(item)
                cells.append({"cell": f"{name}/{seed}", "fails": row["fails"], "lost": lost})
    print(json.dumps({"cloud": args.cloud, "set": args.set, "cells": cells}, indent=1))


if __name__ == "__main__":
    main()
