"""Diagnostic: how a single-tree cloud's DBH is chosen, stage by stage, in the shipped cloud
and in ``cloud_robustness`` cells (cloud x transform x seed).

Traces every call of the per-stem step (``slicestem._slice_stem``: first round, the thin
re-measure ``_thin_slice_stem`` and every rung of the single-tree ladder
``measure._single_tree_stem``) and prints, per call: each slice's circle
(height: r cm / RMS mm / inliers / arc deg; ``x`` failed the per-slice tests, ``*`` among
the agreeing slices), the agreed radius and tolerance, the guided refits that passed, and
the stem it gave (DBH, measurement height, kept slices, taper, support = inliers / RMS^2,
DBH standard deviation); per ladder rung its RANSAC tolerance, and the stem the ladder
chose. Then the cell's score (``cloud_robustness.score_run``).

    PYTHONPATH=src:benchmarks python benchmarks/cloud_single_tree_trace.py \\
        --cloud archi_tree_1 --transforms subsample_20,subsample_10 --seeds 0,1,2,3,4
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

import cloud_robustness as cr
import stemmap.cloud.measure as measure
import stemmap.cloud.slicestem as ss
from _cloud_refs import CLOUDS
from cloud_lost_stems import cell_args
from stemmap.cloud._ladder import _stem_weight
from stemmap.cloud.config import StemConfig
from stemmap.cloud.stems import detect_stems_file

LOG: list[str] = []


def _stem(r: Any) -> str:
    if r is None:
        return "None"
    row = r[0]
    return (
        f"D={100 * row[2]:.2f} h={row[13]:.2f} n={row[7]} taper={row[8]:.3f} "
        f"w={_stem_weight(row):.0f} rms={1000 * row[6]:.1f} std={100 * row[9]:.2f}"
    )


def _fits(fits: Any, c: int, ctx: Any, agree: Any) -> str:
    ok = fits.fitted[c] & np.isfinite(fits.radii[c])
    return " | ".join(
        "-"
        if not ok[s]
        else f"{ctx.centers_h[s]:.1f}:{100 * fits.radii[c, s]:.1f}/{1000 * fits.rms[c, s]:.0f}"
        f"/{int(fits.n_in[c, s])}/{fits.arcs[c, s]:.0f}"
        + ("" if fits.passed[c, s] else "x")
        + ("*" if agree.kept[s] else "")
        for s in range(ctx.centers_h.shape[0])
    )


def install() -> None:
    """Wrap the per-stem step, the thin re-measure and the single-tree ladder (this
    process only: a diagnostic)."""
    o_slice, o_single, o_thin = ss._slice_stem, measure._single_tree_stem, ss._thin_slice_stem

    def w_slice(fits: Any, c: int, ctx: Any, cfg: StemConfig) -> Any:
        r = o_slice(fits, c, ctx, cfg)
        agree = ss._consistent_slices(
            fits, c, ctx.centers_h, ss._consensus_floor(ctx, cfg), ss._se_floor(ctx, cfg)
        )
        ref = ""
        if agree.kept.sum() < cfg.min_slices:
            rf = ss._guided_refits(fits, c, agree, ctx, cfg)
            if rf is not None:
                ref = ", ".join(
                    f"{ctx.centers_h[s]:.1f}:{100 * rf[0].radii[0, s]:.1f}"
                    for s in np.flatnonzero(rf[1])
                )
        LOG.append(
            f"    slices {ctx.centers_h.shape[0]} [{_fits(fits, c, ctx, agree)}] agree "
            f"{100 * agree.radius:.1f} tol {100 * agree.tol:.1f} refits [{ref}] -> {_stem(r)}"
        )
        return r

    def w_thin(fits: Any, c: int, ctx: Any, ctx0: Any, cfg_thin: StemConfig) -> Any:
        LOG.append("  thin re-measure:")
        r = o_thin(fits, c, ctx, ctx0, cfg_thin)
        LOG.append(f"  thin re-measure -> {_stem(r)}")
        return r

    def w_single(first: Any, refit: Any, tol0: float, thick: bool, *rest: Any) -> Any:
        LOG.append(f"  ladder (tol0 {1000 * tol0:.1f} mm), incumbent {_stem(first)}")

        def rung(thin: bool, f: float, tol: float) -> Any:
            LOG.append(f"  rung {'thin' if thin else 'band'} slices, tol {1000 * tol:.1f} mm")
            g = refit(thin, f, tol)
            LOG.append(f"   -> {_stem(g)}")
            return g

        b = o_single(first, rung, tol0, thick, *rest)
        LOG.append(f"  ladder chose {_stem(b)}")
        return b

    ss._slice_stem = w_slice  # type: ignore[assignment]
    measure._slice_stem = w_slice  # type: ignore[assignment]
    ss._thin_slice_stem = w_thin  # type: ignore[assignment]
    measure._thin_slice_stem = w_thin  # type: ignore[assignment]
    measure._single_tree_stem = w_single  # type: ignore[assignment]


def main() -> None:
    args, root, cfg = cell_args(__doc__ or "", "archi_tree_1")
    install()
    bl = cr.run_baseline(args.cloud, root / CLOUDS[args.cloud], cfg)
    print(f"=== shipped: D={bl.det.diameter * 100} h={bl.det.dbh_height}")
    print("\n".join(LOG))
    LOG.clear()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            for name, prep, f in cr.transformed_files(
                bl, args.transforms.split(","), Path(tmp), seed
            ):
                det = detect_stems_file(f, cfg)
                row = cr.score_run(name, bl, det, prep)
                print(
                    f"=== {name}/{seed}: D={det.diameter * 100} h={det.dbh_height} "
                    f"fails={row['fails']}"
                )
                print("\n".join(LOG))
                LOG.clear()


if __name__ == "__main__":
    main()
