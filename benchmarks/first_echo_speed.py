"""Speed of the numpy first-echo path: the ``stemmap`` preset against another setting on the
real-geometry benchmark's nearest-return scans, in one process (issue 11's speed rule: ratios
within one run, never a single wall-clock number).

A first-echo scanner (``beam_footprint_deg`` > 0, ``stemmap detect --footprint``) always runs
the numpy path (``ScanTrunkDetector._compiled``), so its speed is not what
``scan_detection.py --speed-set`` measures (the compiled path of an averaging scanner). The
batches are ``real_geometry.py --vantage V``'s own nearest-return scans
(``_real_scanning.scene_batches``: every slice with reference trunks, 0.25 / 0.5 / 1 deg,
0 / 1 / 3 cm of range noise, the same vantage points and noise draws; 360 deg scans, 1440 /
720 / 360 beams), each detector set up as the benchmark sets it up for a first-echo scanner
(footprint = the angular step, ``_real_scanning.matched``).

``--rounds`` rounds of best-of-3 process-CPU times over all the batches, the two detectors
alternating in each round; reports scans per CPU second per round and the ratio of the other
setting to the preset per round, with the detections of each (count and digest, bit for bit:
``scan_detection.detections_digest`` over the batches in order).

``--ref CHECKOUT`` compares code instead of settings: the same setting (the preset with
``--grid`` / ``--set``) in this checkout against another checkout of stemmap (e.g. main's
worktree), both imported in one process as ``scan_speed_vs_ref.py`` imports them, alternating;
reports the ratio of this checkout to the reference per round and both digests (equal digests:
the same detections bit for bit).

Return rule: nearest-return scans only. The averaging (SICK-class) scans ``scene_batches``
draws besides are skipped; their rule is passed by name, ``_real_scanning.ANY_HIT`` (any
sub-ray), and changes no draw here (the noise is drawn by the scans' shape).

Usage::

    PYTHONPATH=src:benchmarks python benchmarks/first_echo_speed.py --grid 67
    PYTHONPATH=src:benchmarks python benchmarks/first_echo_speed.py --set '{"cut_ends": false}'
    PYTHONPATH=src:benchmarks python benchmarks/first_echo_speed.py --grid 85 --ref ../../main

One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from _datasets import require_datasets_dir
from _loo_grid import LOO_GRID
from _real_scanning import ANY_HIT, matched, scene_batches
from scan_detection import detections_digest, timed_both
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.types import ScanBatch


def nearest_batches(
    ddir: Path, n_vantage: int, seed: int, background: str
) -> list[tuple[str, float, ScanBatch]]:
    """(configuration name, step deg, scans) of every nearest-return configuration of
    ``real_geometry.py`` (slice name prefixed)."""
    return [
        (f"{sc.sl.name}:{sc.config}", sc.res, sc.batch)
        for sc in scene_batches(ddir, n_vantage, seed, background, return_rule=ANY_HIT)
        if sc.model == "nearest"
    ]


def compare(
    batches: list[tuple[str, float, ScanBatch]], overrides: dict[str, Any], rounds: int
) -> dict[str, Any]:
    """The preset against the preset with ``overrides`` on ``batches``, alternating, ``rounds``
    rounds of best-of-3 process-CPU times over all the batches."""
    steps = sorted({res for _, res, _ in batches})
    configs = {
        "default": DetectorConfig.preset("stemmap"),
        "other": DetectorConfig.preset("stemmap", **overrides),
    }
    dets = {
        name: {res: ScanTrunkDetector(matched(cfg, "nearest", res)) for res in steps}
        for name, cfg in configs.items()
    }
    n_scans = sum(len(b) for _, _, b in batches)
    out: dict[str, Any] = {
        "overrides": overrides,
        "batches": len(batches),
        "scans": n_scans,
        "rounds": rounds,
        "same_config": configs["default"] == configs["other"],
    }
    differ: list[str] = []
    for name, by_res in dets.items():
        h = hashlib.sha256()
        count = 0
        for _, res, b in batches:
            obs = by_res[res].detect_batch(b)
            count += len(obs)
            h.update(detections_digest(obs).encode())
        out[f"{name}_detections"] = count
        out[f"{name}_digest"] = h.hexdigest()
    for label, res, b in batches:
        a, o = (detections_digest(dets[n][res].detect_batch(b)) for n in ("default", "other"))
        if a != o:
            differ.append(label)
    out["configurations_that_differ"] = differ
    load_before = os.getloadavg()[0]
    sps: dict[str, list[int]] = {name: [] for name in dets}
    for _ in range(rounds):
        for name, by_res in dets.items():

            def run(by_res: dict[float, ScanTrunkDetector] = by_res) -> None:
                for _, res, b in batches:
                    by_res[res].detect_batch(b)

            _, cpu = timed_both(run, 3)
            sps[name].append(round(n_scans / cpu))
    ratio = [round(o / d, 4) for o, d in zip(sps["other"], sps["default"], strict=True)]
    out.update(
        {
            "default_scans_per_cpu_second": sps["default"],
            "other_scans_per_cpu_second": sps["other"],
            "ratio_other_to_default": ratio,
            "median_ratio": float(np.median(ratio)),
            "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
    )
    return out


def _ours(name: str) -> bool:
    return name == "stemmap" or name.startswith("stemmap.")


def _use(modules: dict[str, Any]) -> None:
    """Put one checkout's ``stemmap`` modules into ``sys.modules`` (the other's out)."""
    for name in [k for k in sys.modules if _ours(k)]:
        del sys.modules[name]
    sys.modules.update(modules)


def compare_ref(
    batches: list[tuple[str, float, ScanBatch]], overrides: dict[str, Any], rounds: int, ref: Path
) -> dict[str, Any]:
    """The preset with ``overrides`` in this checkout (``branch``) against the same in the
    checkout ``ref``, alternating, ``rounds`` rounds of best-of-3 process-CPU times over all
    the batches; the digest of each one's detections. Each checkout runs with its own
    ``stemmap`` modules in ``sys.modules`` (:func:`_use`): a function that imports inside its
    body (``_inner_runs.inner_runs``) would otherwise find the other checkout's."""
    from scan_speed_vs_ref import _import_from

    steps = sorted({res for _, res, _ in batches})
    runs: dict[str, tuple[dict[float, Any], list[tuple[float, Any]]]] = {}
    modules: dict[str, dict[str, Any]] = {}
    for name, src in (
        ("branch", Path(__file__).resolve().parent.parent / "src"),
        ("ref", ref / "src"),
    ):
        detect, types = _import_from(src)
        cfg = detect.DetectorConfig.preset("stemmap", **overrides)
        dets = {res: detect.ScanTrunkDetector(matched(cfg, "nearest", res)) for res in steps}
        own = [
            (
                res,
                types.ScanBatch(
                    np.array(b.ranges),
                    np.array(b.times),
                    b.angle_min,
                    b.angle_increment,
                    b.range_min,
                    b.range_max,
                    b.frame,
                ),
            )
            for _, res, b in batches
        ]
        runs[name] = (dets, own)
        modules[name] = {k: v for k, v in sys.modules.items() if _ours(k)}
    n_scans = sum(len(b) for _, _, b in batches)
    out: dict[str, Any] = {
        "overrides": overrides,
        "ref": str(ref),
        "batches": len(batches),
        "scans": n_scans,
        "rounds": rounds,
    }
    for name, (dets, own) in runs.items():
        _use(modules[name])
        h = hashlib.sha256()
        count = 0
        for res, b in own:
            obs = dets[res].detect_batch(b)
            count += len(obs)
            h.update(detections_digest(obs).encode())
        out[f"{name}_detections"] = count
        out[f"{name}_digest"] = h.hexdigest()
    load_before = os.getloadavg()[0]
    sps: dict[str, list[int]] = {name: [] for name in runs}
    for _ in range(rounds):
        for name, (dets, own) in runs.items():
            _use(modules[name])

            def run(dets: dict[float, Any] = dets, own: list[tuple[float, Any]] = own) -> None:
                for res, b in own:
                    dets[res].detect_batch(b)

            _, cpu = timed_both(run, 3)
            sps[name].append(round(n_scans / cpu))
    ratio = [round(b / r, 4) for b, r in zip(sps["branch"], sps["ref"], strict=True)]
    out.update(
        {
            "branch_scans_per_cpu_second": sps["branch"],
            "ref_scans_per_cpu_second": sps["ref"],
            "ratio_branch_to_ref": ratio,
            "median_ratio": float(np.median(ratio)),
            "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        }
    )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--set", help="the other setting: overrides of the stemmap preset (JSON)")
    what.add_argument(
        "--grid", type=int, help="the other setting: LOO grid point N (benchmarks/_loo_grid.py)"
    )
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--vantage", type=int, default=20, help="vantage points per dataset")
    ap.add_argument("--seed", type=int, default=11, help="real_geometry.py's --seed")
    ap.add_argument("--background", choices=("none", "ground"), default="none")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument(
        "--ref", type=Path, default=None, help="another checkout: compare code, same setting"
    )
    args = ap.parse_args(argv)
    overrides = json.loads(args.set) if args.set is not None else dict(LOO_GRID[args.grid])
    ddir = require_datasets_dir(args.datasets)
    batches = nearest_batches(ddir, args.vantage, args.seed, args.background)
    out = {
        "benchmark": "first_echo_speed",
        "other": {"grid": args.grid} if args.grid is not None else {"set": args.set},
        "vantage": args.vantage,
        "seed": args.seed,
        "background": args.background,
        **(
            compare(batches, overrides, args.rounds)
            if args.ref is None
            else compare_ref(batches, overrides, args.rounds, args.ref)
        ),
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
