"""Diagnostic: what the thin re-measure (``StemConfig.thin_remeasure``) sees on a real cloud.

For each cell (cloud x ``cloud_robustness`` transform x seed, the same draws as
``cloud_robustness.py`` / ``cloud_loo.py``) the cloud is detected with the thin re-measure off
and on, and every call of :func:`stemmap.cloud.slicestem._thin_slice_stem` is traced: the
thick slices of the stem (height, radius, inliers, RMS, arc), and per thin slice the band
points in the annulus about the predicted circle and the annulus fit (radius, RMS, inliers,
arc; none when it failed its tests). ``--shape`` adds the shipped cloud's stems' sections:
per thin slice (0.2 m, 0.8-2.0 m) a circle fitted to the points within 5 cm of it and the
median residual in each 30 degree sector (a lobed or fluted section shows the same pattern
at every height; bark noise does not). docs/algorithms/cloud.md, "Why the thin re-measure
moves archi Tree_1". ``--set key=value`` (as in ``cloud_robustness.py``) configures the
traced run; with the default ``thin_remeasure_by = "error"`` every re-measure is traced twice
(its DBH std with the section term is a second call), ``--set thin_remeasure_by=slices``
traces the count rule of the section above once per stem.

    python benchmarks/cloud_thin_trace.py --cloud archi_tree_1 --transforms subsample_20 --seeds 2
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

import cloud_robustness as cr
import stemmap.cloud.measure as measure
import stemmap.cloud.slicestem as slicestem
from _cloud_refs import CLOUDS
from _datasets import require_datasets_dir
from stemmap.cloud.stems import StemConfig, detect_stems_file


def _r(v: float, scale: float = 100.0) -> float:
    return round(float(v) * scale, 2)


@contextmanager
def traced() -> Iterator[list[dict[str, Any]]]:
    """Record every thin re-measure while the block runs (the wrapped functions are
    restored afterwards)."""
    calls: list[dict[str, Any]] = []
    fits: list[dict[str, Any]] = []
    thin0: Callable[..., Any] = measure._thin_slice_stem
    ann0: Callable[..., Any] = slicestem._annulus_fit

    def ann(
        ctx: Any,
        s: int,
        center: Any,
        radius: float,
        tol: float,
        slack: float,
        cfg: Any,
        noise: float | None = None,
    ) -> Any:
        fit = ann0(ctx, s, center, radius, tol, slack, cfg, noise)
        nf = ctx.noise_floor if noise is None else noise
        width = max(0.3 * radius, 3.0 * nf) + slack
        idx = np.asarray(ctx.tree.query_ball_point(center, radius + width), dtype=np.int64)
        q = ctx.band.xy[idx[ctx.band_sl[idx] == s]]
        n = int((np.abs(np.hypot(*(q - center).T) - radius) <= width).sum())
        fits.append(
            {
                "h": round(float(ctx.centers_h[s]), 2),
                "annulus_points": n,
                "fit": None
                if fit is None
                else {
                    "r_cm": _r(fit.radius),
                    "rms_mm": _r(fit.rms, 1000),
                    "n_in": fit.n_in,
                    "arc": round(fit.arc),
                },
            }
        )
        return fit

    def thin(f: Any, c: int, ctx: Any, ctx0: Any, cfg_thin: Any) -> Any:
        fits.clear()
        out = thin0(f, c, ctx, ctx0, cfg_thin)
        ps = f.passed[c]
        calls.append(
            {
                "noise_floor_mm": _r(ctx.noise_floor, 1000),
                "thick": {
                    "h": [round(float(h), 2) for h in ctx.centers_h[ps]],
                    "r_cm": [_r(v) for v in f.radii[c, ps]],
                    "n_in": [int(v) for v in f.n_in[c, ps]],
                    "rms_mm": [_r(v, 1000) for v in f.rms[c, ps]],
                    "arc": [round(float(v)) for v in f.arcs[c, ps]],
                },
                "thin": list(fits),
                "thin_stem": None
                if out is None
                else {"dbh_cm": _r(out[0][2]), "n_slices": out[0][7], "dbh_std_cm": _r(out[0][9])},
            }
        )
        return out

    measure._thin_slice_stem = thin  # type: ignore[assignment]
    slicestem._annulus_fit = ann  # type: ignore[assignment]
    try:
        yield calls
    finally:
        measure._thin_slice_stem = thin0  # type: ignore[assignment]
        slicestem._annulus_fit = ann0  # type: ignore[assignment]


def _kasa(p: np.ndarray) -> tuple[np.ndarray, float]:
    a = np.column_stack((2 * p[:, 0], 2 * p[:, 1], np.ones(len(p))))
    s = np.linalg.lstsq(a, (p**2).sum(axis=1), rcond=None)[0]
    return s[:2], float(np.sqrt(s[2] + s[0] ** 2 + s[1] ** 2))


def section_shape(bl: cr.Baseline) -> list[dict[str, Any]]:
    """Per shipped stem and thin slice: circle (points within 5 cm, trimmed twice) and the
    median residual (mm) per 30 degree sector with > 5 points (None otherwise)."""
    xyz = bl.xyz
    h = xyz[:, 2] - bl.ground.ground_at(xyz[:, :2]) if bl.ground is not None else xyz[:, 2]
    out = []
    for i in range(len(bl.det)):
        c, r0 = bl.det.xy[i], bl.det.diameter[i] / 2
        rows = []
        for lo in np.arange(0.8, 2.0, 0.2):
            p = xyz[(h >= lo) & (h < lo + 0.2), :2]
            p = p[np.abs(np.hypot(*(p - c).T) - r0) < 0.08]
            if p.shape[0] < 8:
                continue
            cc, rr = _kasa(p)
            for _ in range(2):
                p = p[np.abs(np.hypot(*(p - cc).T) - rr) < 0.05]
                cc, rr = _kasa(p)
            d = np.hypot(*(p - cc).T) - rr
            ang = np.degrees(np.arctan2(p[:, 1] - cc[1], p[:, 0] - cc[0])) % 360
            sec = [
                _r(np.median(d[s]), 1000) if s.sum() > 5 else None
                for s in ((ang >= a) & (ang < a + 30) for a in range(0, 360, 30))
            ]
            rows.append(
                {
                    "h": round(float(lo + 0.1), 1),
                    "n": int(p.shape[0]),
                    "r_cm": _r(rr),
                    "rms_mm": _r(d.std(), 1000),
                    "sector_median_mm": sec,
                }
            )
        out.append({"stem": i, "dbh_cm": _r(bl.det.diameter[i]), "slices": rows})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cloud", default="archi_tree_1", choices=list(CLOUDS))
    ap.add_argument("--transforms", default="subsample_50,subsample_20")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--shape", action="store_true", help="the shipped stems' sections")
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value (traced run)")
    args = ap.parse_args()
    overrides = cr.set_overrides(args.set)
    root = require_datasets_dir()
    bl = cr.run_baseline(args.cloud, root / CLOUDS[args.cloud])
    out: dict[str, Any] = {
        "cloud": args.cloud,
        "set": overrides,
        "shipped_dbh_cm": [_r(d) for d in bl.det.diameter],
    }
    if args.shape:
        out["shape"] = section_shape(bl)
    cells = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            for name, _, f in cr.transformed_files(bl, args.transforms.split(","), Path(tmp), seed):
                off = detect_stems_file(f, StemConfig(thin_remeasure=False))
                with traced() as calls:
                    on = detect_stems_file(f, StemConfig(**overrides))
                cells.append(
                    {
                        "cell": f"{name}/{seed}",
                        "dbh_cm_off": [_r(d) for d in off.diameter],
                        "dbh_cm_on": [_r(d) for d in on.diameter],
                        "remeasures": calls,
                    }
                )
    out["cells"] = cells
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
