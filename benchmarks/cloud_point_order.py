"""Benchmark: do the real clouds give the same stems whatever the order of their points?

A user who re-exports a cloud (another tool, a merge of tiles, a COPC conversion) gets the
same points in another order. Every cloud of ``cloud_real.py`` goes through ``detect_stems``
(preset ours, heights on, as ``stemmap stems``) in file order and in ``--perms`` random
permutations of its points (``numpy.random.default_rng(seed).permutation``, seeds 0, 1, ...),
and through ``detect_stems_file`` on a LAS written in one permuted order (the streaming
path: ground pass, then band pass). Per cloud: the stems' count in each order, and over the
orders the largest spread (max - min, per stem matched to the file-order result within
half its diameter + 10 cm) of DBH, position (largest distance from the file order's), point
count and slice count, plus the spacing and noise floor spread, and whether every order
gave bit-identical positions, diameters and point counts. CPU time (``time.process_time``)
of the file-order run (median of ``--repeat`` runs) is printed too.

``--subsample F`` first keeps a random fraction F of every cloud's points (the draw of
``cloud_robustness.py``'s ``subsample_*``, seed 0: a sparse cloud's thickened band), and
``--set key=value`` overrides a :class:`StemConfig` option (true / false / a number), e.g.
``--set thin_refit_points=true``.

Prints ONE JSON object. Usage: python benchmarks/cloud_point_order.py [--perms 10]
[--clouds a,b] [--repeat 3] [--subsample F] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from _cloud_refs import CLOUDS, match_stems
from cloud_robustness import set_value, write_las
from stemmap.cloud.stems import CloudStems, StemConfig, detect_stems, detect_stems_file
from stemmap.datasets import find_datasets_dir
from stemmap.io.clouds import read_cloud


def _spread(runs: list[CloudStems], base: CloudStems) -> dict[str, Any]:
    """Largest max - min over the runs of each matched stem's values (base included)."""
    out = {"dbh_mm": 0.0, "position_mm": 0.0, "n_points": 0, "n_slices": 0, "unmatched": 0}
    for i in range(len(base)):
        dbh, xy, npt, nsl = [base.diameter[i]], [base.xy[i]], [base.n_points[i]], [base.n_slices[i]]
        for r in runs:
            pairs = dict(match_stems(base.xy, base.diameter, r.xy))
            if i not in pairs:
                out["unmatched"] += 1
                continue
            j = pairs[i]
            dbh.append(r.diameter[j])
            xy.append(r.xy[j])
            npt.append(r.n_points[j])
            nsl.append(r.n_slices[j])
        p = np.asarray(xy)
        out["dbh_mm"] = max(out["dbh_mm"], 1000 * float(np.ptp(dbh)))
        out["position_mm"] = max(out["position_mm"], 1000 * float(np.max(np.hypot(*(p - p[0]).T))))
        out["n_points"] = max(out["n_points"], int(np.ptp(npt)))
        out["n_slices"] = max(out["n_slices"], int(np.ptp(nsl)))
    out["dbh_mm"] = round(out["dbh_mm"], 4)
    out["position_mm"] = round(out["position_mm"], 4)
    return out


def _write_las(path: Path, src: str, perm: np.ndarray) -> None:
    """The file's points (header, scales, offsets, every field) in the order ``perm``."""
    las = laspy.read(src)
    out = laspy.LasData(las.header)
    out.points = las.points[perm]
    out.write(str(path))


def run_cloud(
    path: str,
    perms: int,
    repeat: int,
    subsample: float | None = None,
    overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    cfg = replace(StemConfig(), estimate_height=True, **(overrides or {}))
    xyz = read_cloud(path).xyz
    if subsample is not None:
        n = xyz.shape[0]
        keep = np.random.default_rng(0).choice(n, int(subsample * n), replace=False)
        xyz = xyz[np.sort(keep)]
    cpu = []
    for _ in range(repeat):
        t0 = time.process_time()
        base = detect_stems(xyz, cfg)
        cpu.append(time.process_time() - t0)
    runs = []
    for s in range(perms):
        perm = np.random.default_rng(s).permutation(xyz.shape[0])
        runs.append(detect_stems(xyz[perm], cfg))
    with tempfile.TemporaryDirectory() as tmp:
        las = Path(tmp) / "permuted.las"
        src = path
        if subsample is not None:  # the subsample in file order, as the file to compare with
            src = str(Path(tmp) / "subsample.las")
            write_las(Path(src), xyz, 1e-4, 1.0)
        _write_las(las, src, np.random.default_rng(1000).permutation(xyz.shape[0]))
        streamed = detect_stems_file(las, cfg)
        file_order = detect_stems_file(src, cfg)
    same = all(
        len(r) == len(base)
        and np.array_equal(r.xy, base.xy)
        and np.array_equal(r.diameter, base.diameter)
        and np.array_equal(r.n_points, base.n_points)
        for r in runs
    )
    spacing = [r.spacing for r in [base, *runs]]
    floor = [r.noise_floor for r in [base, *runs]]
    return {
        "n_points": int(xyz.shape[0]),
        "stems_file_order": len(base),
        "stems_per_order": sorted({len(r) for r in runs}),
        "dbh_cm_file_order": [round(100 * float(d), 3) for d in base.diameter],
        "bit_identical_over_orders": same,
        "spread_over_orders": _spread(runs, base),
        "spacing_spread_mm": round(1000 * float(np.ptp(spacing)), 6),
        "noise_floor_spread_mm": round(1000 * float(np.ptp(floor)), 6),
        "streamed_permuted_las_vs_file": _spread([streamed], file_order),
        "streamed_stems": [len(file_order), len(streamed)],
        "cpu_s_file_order": round(float(np.median(cpu)), 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--perms", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--subsample", type=float, default=None, help="keep this fraction")
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    a = ap.parse_args()
    overrides = {k: set_value(v) for k, v in (kv.split("=", 1) for kv in a.set)}
    root = find_datasets_dir()
    if root is None:
        raise SystemExit("error: ../shared/datasets not found (set STEMMAP_DATASETS).")
    res = {
        k: run_cloud(str(root / CLOUDS[k]), a.perms, a.repeat, a.subsample, overrides)
        for k in a.clouds.split(",")
        if k in CLOUDS
    }
    out = {"perms": a.perms, "subsample": a.subsample, "set": overrides, "clouds": res}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
