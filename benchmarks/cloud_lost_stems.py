"""Diagnostic: the stage that loses each baseline stem a ``cloud_robustness`` cell misses.

For each cell (cloud x transform x seed: the draws of ``cloud_robustness.py`` /
``cloud_loo.py``) the transformed file goes through ``detect_stems_file`` with the per-stem
step (:func:`stemmap.cloud.slicestem._slice_stem`, as :mod:`stemmap.cloud.measure` calls it)
and the slice fits (``_ladder._fit_slices``) traced. For every checked baseline stem the
detection misses, per call of the per-stem step whose cluster fitted a circle near the stem
(a fitted centre within the baseline radius + 10 cm; thick band, tighter refits, thin
ladder -- the slice count tells which):

* ``band``: the band's returns (before the vertical filter) within r + 5 cm of the baseline
  stem per slice of that call -- what the data hold;
* ``fits``: each slice's circle (r cm / RMS mm / inliers / arc deg), passed or not (per-slice
  tests, step 7), the consensus weight (inliers / RMS^2, cm^-2) and the radius standard
  error from the fit's covariance (``se``, mm; ``slicestem._radius_se``);
* ``stage``: where the per-stem step stops -- ``consensus`` (fewer than ``min_slices``
  agreeing slices and no guided refit passes), ``guided refits`` (refits passed but still too
  few), ``vertical extent``, ``ends in band``, ``taper``, or ``stem`` (it gave a stem that a
  later step dropped: duplicate suppression, or another tolerance's stem won);
* ``guided_refits``: the guided refits that passed (height: r cm / RMS mm / inliers);
* ``agree``: the radius the slices agree on and the agreeing slices' heights (m).

A stem with no such call was lost before the per-stem step (too few returns for a slice fit,
or its cluster fitted nothing near it): ``band`` then counts its returns in the first
round's slices. ``--set key=value`` as in ``cloud_robustness.py``.

    PYTHONPATH=src:benchmarks python benchmarks/cloud_lost_stems.py --cloud treels_pine_plot \\
        --transforms subsample_20,subsample_10 --seeds 0,1,2,3,4
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

import cloud_robustness as cr
import stemmap.cloud.measure as measure
import stemmap.cloud.slicestem as ss
from _cloud_refs import CLOUDS
from _datasets import require_datasets_dir
from stemmap.cloud.config import StemConfig
from stemmap.cloud.stems import detect_stems_file


def _c(v: float) -> float:
    return round(float(v) * 100, 2)


def stage_of(fits: Any, c: int, ctx: Any, cfg: StemConfig) -> tuple[str, Any, str]:
    """Where :func:`~stemmap.cloud.slicestem._slice_stem` stops for cluster ``c`` (its tests
    in its order, through the same functions), the agreement it reached, and the guided
    refits that passed ("h: r cm / RMS mm / inliers", or "")."""
    agree = ss._consistent_slices(
        fits, c, ctx.centers_h, ss._consensus_floor(ctx, cfg), ss._se_floor(ctx, cfg)
    )
    done = ""
    if agree.kept.sum() < cfg.min_slices:
        refit = ss._guided_refits(fits, c, agree, ctx, cfg)
        if refit is None:
            return "consensus", agree, ""
        m = agree.kept | refit[1]
        done = ", ".join(
            f"{ctx.centers_h[s]:.1f}: {_c(refit[0].radii[0, s])}/"
            f"{1000 * refit[0].rms[0, s]:.1f}/{int(refit[0].n_in[0, s])}"
            for s in np.flatnonzero(refit[1])
        )
        if m.sum() < cfg.min_slices:
            return "guided refits", agree, done
        fits, c = refit[0], 0
        pred = ss._centre_line(ctx.centers_h[m], fits.centers[0, m], ctx.centers_h)
        agree = ss._Agreement(m, float(np.median(fits.radii[0, m])), agree.tol, pred)
    m = agree.kept
    if not ctx.slice_cloud and np.ptp(ctx.centers_h[m]) < cfg.min_vertical_extent - 1e-9:
        return "vertical extent", agree, done
    if cfg.continues_above and not ctx.slice_cloud and ss._ends_in_band(agree, ctx, cfg):
        return "ends in band", agree, done
    h_meas, _ = ss._measurement_height(fits, c, agree, ctx, cfg)
    at = ss._stem_at(fits, c, m, ctx.centers_h[m] - h_meas, cfg, ctx.few_thick)
    return ("taper" if at is None else "stem"), agree, done


@contextmanager
def traced() -> Iterator[list[tuple[Any, int, Any, StemConfig]]]:
    """Record every call of the per-stem step (fits as copies) while the block runs."""
    calls: list[tuple[Any, int, Any, StemConfig]] = []
    orig = measure._slice_stem

    def wrap(fits: Any, c: int, ctx: Any, cfg: StemConfig) -> Any:
        calls.append((ss._row(fits, c), 0, ctx, cfg))
        return orig(fits, c, ctx, cfg)

    measure._slice_stem = wrap  # type: ignore[assignment]
    try:
        yield calls
    finally:
        measure._slice_stem = orig  # type: ignore[assignment]


def band_counts(ctx: Any, xy: np.ndarray, r: float) -> str:
    """The band's returns within ``r`` + 5 cm of ``xy`` per slice of ``ctx`` ("a / b / c")."""
    near = np.hypot(*(ctx.band.xy - xy).T) <= r + 0.05
    return " / ".join(
        str(int((near & (ctx.band_sl == s)).sum())) for s in range(ctx.centers_h.shape[0])
    )


def lost_report(bl: cr.Baseline, i: int, calls: list[Any]) -> dict[str, Any]:
    """What the per-stem calls near baseline stem ``i`` saw, and where each stopped."""
    xy, r = bl.det.xy[i], bl.det.diameter[i] / 2
    out: dict[str, Any] = {"stem": i, "baseline_dbh_cm": _c(2 * r), "calls": []}
    seen: set[tuple[Any, ...]] = set()
    for fits, c, ctx, cfg in calls:
        ok = fits.fitted[c] & np.isfinite(fits.radii[c])
        d = np.hypot(*(fits.centers[c] - xy).T)
        if not np.any(ok & (d <= r + 0.10)):
            continue
        key = (ctx.centers_h.shape[0], tuple(np.round(fits.radii[c][ok], 4)))
        if key in seen:
            continue
        seen.add(key)
        stage, agree, refits = stage_of(fits, c, ctx, cfg)
        out["calls"].append(
            {
                "slices": ctx.centers_h.shape[0],
                "band": band_counts(ctx, xy, r),
                "floor_mm": round(1000 * ctx.noise_floor, 1),
                "fits": " | ".join(
                    "-"
                    if not ok[s]
                    else f"{_c(fits.radii[c, s])}/{1000 * fits.rms[c, s]:.1f}/"
                    f"{int(fits.n_in[c, s])}/{fits.arcs[c, s]:.0f}"
                    + ("" if fits.passed[c, s] else " x")
                    + f" w{fits.weights[c, s] * 1e-4:.0f}"
                    + f" se{1000 * float(ss._radius_se(fits, c)[s]):.1f}"
                    for s in range(ctx.centers_h.shape[0])
                ),
                "stage": stage,
                "guided_refits": refits,
                "agree": f"{_c(agree.radius)} cm at "
                + ", ".join(f"{h:.1f}" for h in ctx.centers_h[agree.kept]),
            }
        )
    if not out["calls"] and calls:
        out["band_first_round"] = band_counts(calls[0][2], xy, r)
    return out


def cell_args(doc: str, cloud: str) -> tuple[argparse.Namespace, Path, StemConfig]:
    """The command line of a per-cell diagnostic (``--cloud``, default ``cloud``;
    ``--transforms``, ``--seeds``, ``--set``): the arguments, the datasets directory and the
    configuration."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--cloud", default=cloud, choices=list(CLOUDS))
    ap.add_argument("--transforms", default="subsample_20,subsample_10")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    args = ap.parse_args()
    root = require_datasets_dir()
    return args, root, replace(StemConfig(), **cr.set_overrides(args.set))


def main() -> None:
    args, root, cfg = cell_args(__doc__ or "", "treels_pine_plot")
    bl = cr.run_baseline(args.cloud, root / CLOUDS[args.cloud])
    cells = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            for name, prep, f in cr.transformed_files(
                bl, args.transforms.split(","), Path(tmp), seed
            ):
                with traced() as calls:
                    det = detect_stems_file(f, cfg)
                row = cr.score_run(name, bl, det, prep)
                pairs = cr._match(
                    bl.det.xy,
                    bl.det.diameter,
                    prep.back(np.column_stack((det.xy, np.nan_to_num(det.z))))[:, :2],
                )
                found = {i for i, _ in pairs}
                lost = [i for i in sorted(bl.checked) if i not in found]
                cells.append(
                    {
                        "cell": f"{name}/{seed}",
                        "fails": row["fails"],
                        "lost": [lost_report(bl, i, calls) for i in lost],
                    }
                )
    print(json.dumps({"cloud": args.cloud, "set": args.set, "cells": cells}, indent=1))


if __name__ == "__main__":
    main()
