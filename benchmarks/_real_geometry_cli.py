"""The command line of ``benchmarks/real_geometry.py``: its options (:func:`build_parser`), the
``--loo-rules`` return thresholds (:func:`parse_rule`) and the parts of its JSON output that
echo the options -- the scenario of a leave-one-dataset-out run (:func:`loo_scenario`) and of a
plain run (:func:`run_scenario`) -- and what it reports of each dataset's slice
(:func:`dataset_info`).

Split from ``real_geometry.py`` (which imports every name here): how the benchmark is asked
and how it echoes the question are one concept, the scoring and the leave-one-dataset-out
choice another.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from _loo_choice import LOO_PROTOCOL_BY_SCANNER, LOO_PROTOCOL_POOLED, TRUSTED_REFERENCE_CM
from _loo_greedy import GREEDY_EPS
from _loo_grid import LOO_EXTRA, LOO_GRID
from _real_scanning import BACKGROUNDS, ReturnRule, scene_note
from _scan_sim import (
    SIM_DBH_RMSE_LE5_MAX_CM,
    SIM_PRECISION_MIN,
    SIM_RECALL_MIN,
    SIM_SEEDS,
)
from stemmap.eval.real_slices import FILLS, SLICES, RealSlice

__all__ = ["build_parser", "dataset_info", "loo_scenario", "parse_rule", "run_scenario"]


def parse_rule(text: str) -> ReturnRule:
    """``FRACTION[:PROFILE[:SUB_RAYS]]`` as a :class:`ReturnRule` (``--loo-rules``)."""
    parts = text.split(":")
    return ReturnRule(
        float(parts[0]),
        parts[1] if len(parts) > 1 else "uniform",
        int(parts[2]) if len(parts) > 2 else 5,
    )


def build_parser(description: str, epilog: str | None = None) -> argparse.ArgumentParser:
    """The options of ``real_geometry.py`` (``description``: its first docstring line;
    ``epilog``: the LOO protocol's paragraph)."""
    ap = argparse.ArgumentParser(description=description, epilog=epilog)
    ap.add_argument("--datasets", type=Path, default=None, help="shared datasets folder")
    ap.add_argument("--quick", action="store_true", help="2 scanner configs, 3 detectors")
    ap.add_argument("--vantage", type=int, default=None, help="vantage points per dataset")
    ap.add_argument("--min-returns", type=int, default=4)
    ap.add_argument(
        "--only",
        nargs="*",
        choices=list(SLICES),
        default=None,
        help="datasets to run (default: all); each draws the vantage points and noise of a"
        " full run (its stream's seed is --seed + its position in the full list)",
    )
    ap.add_argument(
        "--seed",
        type=int,
        default=11,
        help="dataset k of the full list (0-based) draws from the stream --seed + k",
    )
    ap.add_argument(
        "--loo",
        action="store_true",
        help="leave-one-dataset-out choice of LOO_GRID (stemmap), by scanner family unless"
        " --pooled",
    )
    ap.add_argument(
        "--by-scanner",
        action="store_true",
        help="--loo --pooled: also report the choice made separately on the nearest-return rows"
        " and on the averaging rows, each held out on its own rows (without --pooled it is the"
        " protocol and always reported)",
    )
    ap.add_argument(
        "--pooled",
        action="store_true",
        help="--loo: choose one setting per fold on every training row, nearest-return and"
        " averaging pooled (the protocol of every LOO before Dec 6). Default: by scanner family"
        " -- the setting for first-echo scanners is chosen on the training sets' nearest-return"
        " rows, the one for averaging scanners on their averaging rows, and each held-out row is"
        " scored under its own family's choice (the detector knows its scanner model; the"
        " issue's nearest-return target row then does not depend on the benchmark's averaging"
        " model); the pooled choice is reported next to it under 'pooled'",
    )
    ap.add_argument(
        "--train-all",
        action="store_true",
        help="--loo: train on every dataset, also those whose reference is not trusted",
    )
    ap.add_argument(
        "--set",
        type=json.loads,
        default=None,
        help="also run the stemmap preset with these overrides, e.g. '{\"sigma_from_scan\": true}'"
        ' (detector "stemmap+set")',
    )
    ap.add_argument(
        "--no-sim-check",
        action="store_true",
        help="--loo: choose among every grid setting, also those below the simulated"
        " precision target (the rounds before the tenth)",
    )
    ap.add_argument(
        "--baseline-grid",
        type=int,
        default=None,
        help="--loo: also choose among the first N grid settings (before a round's additions)",
    )
    ap.add_argument(
        "--background",
        choices=BACKGROUNDS,
        default="none",
        help="what the virtual scans see besides the trunks: ground = the pitched scan plane"
        " meets the cloud's ground and understory (fifteenth round, a robustness view); none ="
        " the slice only (default: the issue's benchmark, every round's target row)",
    )
    ap.add_argument(
        "--grid-precision",
        action="store_true",
        help="only check every LOO_GRID setting's simulated precision (SIM_PRECISION_MIN)",
    )
    ap.add_argument(
        "--sim-precision",
        action="store_true",
        help="only check the stemmap preset's (with --set) simulated precision on --sim-seeds",
    )
    ap.add_argument(
        "--sim-seeds",
        type=int,
        nargs="+",
        default=list(SIM_SEEDS),
        help="--loo / --grid-precision / --sim-precision: simulator seeds, each a new stand and"
        " drive; a setting is admitted when, on the mean over them, precision and recall are"
        " >= 0.95 on each drive and the DBH RMSE at <= 5 m is <= 1.2 cm"
        f" (default: {' '.join(map(str, SIM_SEEDS))}; `--sim-seeds 1` is the check of"
        " every round before the sixteenth)",
    )
    ap.add_argument(
        "--averaging",
        action="store_true",
        help="only the averaging scanner at 0.25 / 0.5 / 1 deg, noise 0 / 1 cm (the return"
        " threshold study, Dec 4; with --quick's 3 detectors)",
    )
    ap.add_argument(
        "--hit-fraction",
        type=float,
        default=ReturnRule().min_hit_fraction,
        help="averaging scanner's return threshold: share of the footprint that must hit"
        " (default 0.3: the real SICK LMS200's, measured on Victoria Park, and the simulator's;"
        " 0: any sub-ray, every round's benchmark before Dec 6; 0.5: half the footprint)",
    )
    ap.add_argument(
        "--loo-rules",
        nargs="*",
        default=[],
        help="--loo: the averaging configurations also under these return thresholds, each"
        " FRACTION[:PROFILE[:SUB_RAYS]] (e.g. 0:uniform:20 0.25:uniform:20 0.5:gaussian:20),"
        " each an extra scanner configuration of the objective and the held-out table",
    )
    ap.add_argument(
        "--beam-profile",
        choices=("uniform", "gaussian"),
        default="uniform",
        help="averaging scanner's beam: uniform sub-rays (default) or a Gaussian beam's energy"
        " (the threshold and the power-weighted mean range weighted by the energy too)",
    )
    ap.add_argument(
        "--sub-rays",
        type=int,
        default=25,
        help="averaging scanner's sub-rays per footprint (default 25 since Dec 5, 5 before; the"
        " threshold moves in steps of 1/sub-rays)",
    )
    ap.add_argument(
        "--fill",
        choices=FILLS,
        default="circle",
        help="what stands in a reference trunk's unseen sectors: the reference circle (default,"
        " every round's benchmark) or the outline joined across them from the seen sectors'"
        " median radii (Dec 5, 'aRchi tree 1: the reference settled')",
    )
    ap.add_argument(
        "--max-fill-returns",
        type=int,
        default=None,
        help="a trunk view counts only with at most this many returns from the points that"
        " fill its unseen sectors (default: every view, every round's benchmark; 1: views of"
        " the side no lidar saw do not count, Dec 5, 'aRchi tree 1: the reference settled')",
    )
    ap.add_argument(
        "--greedy",
        action="store_true",
        help="--loo: also the greedy forward selection from the preset over every option value"
        " a grid setting sets differently (_loo_greedy.py), per fold and on every training set",
    )
    ap.add_argument(
        "--greedy-eps",
        type=float,
        default=GREEDY_EPS,
        help=f"--greedy: stop when no ingredient raises the training score by more (default"
        f" {GREEDY_EPS})",
    )
    ap.add_argument(
        "--greedy-only",
        nargs="*",
        default=None,
        metavar="FOLD",
        help="--loo: only the greedy selection (the grid not run), for these folds (held-out"
        " dataset names and / or all_trusted; none given: every one)",
    )
    ap.add_argument(
        "--greedy-cache",
        type=Path,
        default=None,
        help="--greedy: also keep each setting's rows in this folder (shared by parallel runs)",
    )
    ap.add_argument(
        "--sim-hit-fraction",
        type=float,
        default=None,
        help="the admission's simulated SICK: share of its footprint that must hit for a beam"
        " to return, on both drives (default: the sick_lms preset's own)",
    )
    return ap


def loo_scenario(
    args: argparse.Namespace,
    scanners: tuple[tuple[str, float, float], ...],
    n_vantage: int,
    rule: ReturnRule,
) -> dict[str, Any]:
    """The ``scenario`` of a ``--loo`` run's output: every option it ran with."""
    return {
        "scanners_model_res_deg_noise_m": [list(s) for s in scanners],
        "averaging_return": rule.note(),
        "averaging_return_also": [parse_rule(r).note() for r in args.loo_rules],
        "background": scene_note(args.background),
        "unseen_sectors_filled_with": args.fill,
        "max_fill_returns_per_view": args.max_fill_returns,
        "vantage_points_per_dataset": n_vantage,
        "grid": list(LOO_GRID),
        "outside_grid": list(LOO_EXTRA),
        "objective": "mean over training datasets x scanners of F1(recall, precision)"
        " - RMSE(<=10 m)/3 cm (recall for F1 where the reference is incomplete)",
        "sim_hit_fraction": args.sim_hit_fraction,
        "choice": "among the settings admitted on the simulator (scan_detection.py and"
        f" stemmap demo drives, seeds {list(args.sim_seeds)}, on the mean: precision >="
        f" {SIM_PRECISION_MIN}, recall >= {SIM_RECALL_MIN}, DBH RMSE <= 5 m <="
        f" {SIM_DBH_RMSE_LE5_MAX_CM} cm; held_out's 'admission' has the rule)"
        if not args.no_sim_check
        else "among every grid setting",
        "training": "every dataset"
        if args.train_all
        else f"datasets whose reference jackknife is within {TRUSTED_REFERENCE_CM} cm",
        "seed": args.seed,
        "protocol": LOO_PROTOCOL_POOLED if args.pooled else LOO_PROTOCOL_BY_SCANNER,
        "by_scanner": "also chosen per scanner family (nearest, averaging), each on its own rows"
        if args.by_scanner and args.pooled
        else ("the protocol" if not args.pooled else "off"),
    }


def run_scenario(
    args: argparse.Namespace,
    scanners: tuple[tuple[str, float, float], ...],
    n_vantage: int,
    rule: ReturnRule,
    dets: dict[str, Any],
) -> dict[str, Any]:
    """The ``scenario`` of a plain run's output: every option and detector it ran with."""
    return {
        "mode": "quick" if args.quick else "full",
        "scanners_model_res_deg_noise_m": [list(s) for s in scanners],
        "averaging_footprint_deg": 0.25,
        "averaging_return": rule.note(),
        "background": scene_note(args.background),
        "unseen_sectors_filled_with": args.fill,
        "max_fill_returns_per_view": args.max_fill_returns,
        "vantage_points_per_dataset": n_vantage,
        "vantage_range_m": [1.0, 15.0],
        "min_returns_visible": args.min_returns,
        "visible": "centre <= 15 m, diameter 10-100 cm, inside the detector's gate/FOV",
        "match_gate": "reference radius + 5 cm",
        "slice_height_m": [1.2, 1.4],
        "seed": args.seed,
        "detectors": {k: v.to_dict() for k, v in dets.items()},
    }


def dataset_info(sl: RealSlice, name: str) -> dict[str, Any]:
    """What a plain run reports of dataset ``name``'s slice and its reference trunks (its
    ``results`` are added by the caller)."""
    return {
        "file": SLICES[name].path,
        "slice_points": int(sl.xy.shape[0]),
        "reference_trunks": len(sl.refs),
        "reference_diameters_cm": [round(100 * r["diameter"], 1) for r in sl.refs],
        "reference_ring_rms_mm_max": (
            round(1000 * max(r["ring_rms_m"] for r in sl.refs), 1) if sl.refs else None
        ),
        "reference_coverage_deg_min": (
            min(r["coverage_deg"] for r in sl.refs) if sl.refs else None
        ),
        "partial_rings_not_scored": [
            {"diameter_cm": round(100 * r["diameter"], 1), "coverage_deg": r["coverage_deg"]}
            for r in sl.partial
        ],
    }
