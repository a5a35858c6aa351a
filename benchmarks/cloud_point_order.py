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

Preset ``munjer2025`` (EB-LiDAR, ``--munjer``): the real clouds under 1 m tall (the lidR and
FORTLS slices) with the pass-through box opened, as ``cloud_stems.py`` runs them, and virtual
VLP-16 frames of ``treels/pine_plot.laz`` (``munjer2025_real_frames.virtual_frame``, sensor
every 2 m on the three lines between the rows, 39 frames) with the published box, as given
and rounded to a 2 mm grid (equal z in a cell: the ground-relative box's tie-break), each
with ``ground_relative`` off (the default) and on. Per case: whether every order gave
bit-identical voxel points, DBSCAN labels and stems, the stems' count, and the CPU time of
``munjer_clusters`` with the share of it spent on the voxel grid's canonical sort.

``--subsample F`` first keeps a random fraction F of every cloud's points (the draw of
``cloud_robustness.py``'s ``subsample_*``, seed 0: a sparse cloud's thickened band), and
``--set key=value`` overrides a :class:`StemConfig` option (true / false / a number), e.g.
``--set thin_refit_points=true``.

Prints ONE JSON object. Usage: python benchmarks/cloud_point_order.py [--perms 10]
[--clouds a,b] [--repeat 3] [--munjer] [--no-ours] [--subsample F] [--set key=value ...]
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
from _datasets import require_datasets_dir
from cloud_robustness import set_overrides, write_las
from munjer2025_real_frames import LINES_X, virtual_frame
from stemmap.cloud.canonical import canonical_order
from stemmap.cloud.filters import pass_through
from stemmap.cloud.munjer import MunjerClusters, MunjerConfig, level_to_ground, munjer_clusters
from stemmap.cloud.stems import CloudStems, StemConfig, detect_stems, detect_stems_file
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


def _same_clusters(a: MunjerClusters, b: MunjerClusters) -> bool:
    """Voxel points, labels and accepted stems bit-identical."""
    sa, sb = a.stems(), b.stems()
    return (
        np.array_equal(a.points, b.points)
        and np.array_equal(a.labels, b.labels)
        and len(sa) == len(sb)
        and np.array_equal(sa.xy, sb.xy)
        and np.array_equal(sa.diameter, sb.diameter)
    )


def _munjer_case(clouds: list[np.ndarray], cfg: MunjerConfig, perms: int, repeat: int) -> dict:
    """EB-LiDAR on each cloud in its order and ``perms`` permutations; CPU time of the
    pipeline and of the voxel grid's canonical sort (on the pass-through points)."""
    identical, stems, differ, stems_differ, counts = True, 0, 0, 0, set()
    cpu, sort_cpu = 0.0, 0.0
    for xyz in clouds:
        base = munjer_clusters(xyz, cfg)
        stems += len(base.stems())
        runs = [
            munjer_clusters(xyz[np.random.default_rng(s).permutation(len(xyz))], cfg)
            for s in range(perms)
        ]
        same = all(_same_clusters(r, base) for r in runs)
        identical &= same
        differ += not same
        b = base.stems()
        stems_differ += not all(
            len(r.stems()) == len(b) and np.array_equal(r.stems().diameter, b.diameter)
            for r in runs
        )
        counts |= {len(r.stems()) - len(b) for r in runs}
        zb = level_to_ground(xyz) if cfg.ground_relative else xyz
        p = xyz[pass_through(zb, x=cfg.box_x, y=cfg.box_y, z=cfg.box_z)]
        t_all, t_sort = [], []
        for _ in range(repeat):
            t0 = time.process_time()
            munjer_clusters(xyz, cfg)
            t1 = time.process_time()
            canonical_order(p[:, 0], p[:, 1], p[:, 2])
            t_all.append(t1 - t0)
            t_sort.append(time.process_time() - t1)
        cpu += float(np.median(t_all))
        sort_cpu += float(np.median(t_sort))
    return {
        "clouds": len(clouds),
        "stems_file_order": stems,
        "bit_identical_over_orders": identical,
        "clouds_differing": differ,
        "clouds_with_other_stems": stems_differ,
        "stem_count_change_over_orders": sorted(counts),
        "cpu_s": round(cpu, 4),
        "sort_cpu_s": round(sort_cpu, 4),
        "sort_share": round(sort_cpu / cpu, 4) if cpu > 0 else None,
    }


def run_munjer(root: Path, perms: int, repeat: int) -> dict[str, Any]:
    """EB-LiDAR's order check (module docstring)."""
    out: dict[str, Any] = {}
    opened = MunjerConfig(box_x=None, box_y=None, box_z=None)
    for k in ("lidr_dbh", "fortls_slice"):
        xyz = read_cloud(str(root / CLOUDS[k])).xyz
        out[f"{k}_box_opened"] = _munjer_case([xyz], opened, perms, repeat)
    plot = read_cloud(str(root / "treels" / "pine_plot.laz")).xyz
    frames = [
        virtual_frame(plot, np.array([x, y, np.pi / 2]))
        for x in LINES_X
        for y in np.arange(-8.0, 18.0, 2.0)
    ]
    gridded = [np.round(f / 0.002) * 0.002 for f in frames]
    for name, fs in (("frames", frames), ("frames_2mm", gridded)):
        for gr in (False, True):
            cfg = MunjerConfig(ground_relative=gr)
            key = f"pine_plot_{name}" + ("_ground_relative" if gr else "")
            out[key] = _munjer_case(fs, cfg, perms, repeat)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--perms", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--clouds", default=",".join(CLOUDS))
    ap.add_argument("--munjer", action="store_true", help="also the munjer2025 preset")
    ap.add_argument("--no-ours", action="store_true", help="skip preset ours")
    ap.add_argument("--subsample", type=float, default=None, help="keep this fraction")
    ap.add_argument("--set", action="append", default=[], help="StemConfig key=value")
    a = ap.parse_args()
    overrides = set_overrides(a.set)
    root = require_datasets_dir()
    res = {
        k: run_cloud(str(root / CLOUDS[k]), a.perms, a.repeat, a.subsample, overrides)
        for k in a.clouds.split(",")
        if k in CLOUDS and not a.no_ours
    }
    out: dict[str, Any] = {
        "perms": a.perms,
        "subsample": a.subsample,
        "set": overrides,
        "clouds": res,
    }
    if a.munjer:
        out["munjer2025"] = run_munjer(root, a.perms, a.repeat)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
