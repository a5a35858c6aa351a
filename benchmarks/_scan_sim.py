"""The simulated 2D laser scenario of ``scan_detection.py`` (a stand with clutter, a SICK
LMS-like scanner, a lawnmower drive) and its per-scan scoring, shared with ``real_geometry.py``
(the simulated precision its grid is admitted on). A helper module, not a script; each
benchmark imports it explicitly (the script's own folder is on ``sys.path`` when it runs, from
any working directory)."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from stemmap.eval.detection import detectable_trees, scan_detection_metrics
from stemmap.eval.matching import match_points
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.sim.forest import stand_from_spec
from stemmap.sim.scanner import scanner_preset
from stemmap.sim.trajectory import lawnmower_path, simulate_run
from stemmap.types import StemObservations

__all__ = [
    "SCENARIO",
    "SIM_DBH_RMSE_LE5_MAX_CM",
    "SIM_PRECISION_MIN",
    "SIM_RECALL_MIN",
    "SIM_SEEDS",
    "admitted_over_seeds",
    "benchmark_drive",
    "edge_status",
    "make_run",
    "score",
    "set_sim_hit_fraction",
    "simulated_precision",
    "simulated_precision_seeds",
    "tree_errors",
    "worst_trees",
]


SCENARIO: dict[str, Any] = {
    "stand": {
        "layout": "random",
        "n_trees": 90,
        "size_m": [50.0, 50.0],
        "dbh_mean_m": 0.30,
        "dbh_std_m": 0.10,
        "dbh_min_m": 0.08,
        "min_spacing_m": 1.5,
    },
    "clutter": {"n_bushes": 10, "n_branches": 10, "n_walls": 1, "n_fences": 1, "n_rocks": 6},
    "scanner": {
        "preset": "sick_lms",
        "angle_min_deg": -90.0,
        "angle_max_deg": 90.0,
        "angle_increment_deg": 0.5,
        "range_max_m": 30.0,
        "range_noise_m": 0.01,
        "beam_divergence_deg": 0.25,
        "sub_beams": 25,
        "mixed_pixels": True,
        "dropout": 0.0,
    },
    "drive": {
        "path": "lawnmower",
        "strip_spacing_m": 8.0,
        "margin_m": 5.0,
        "speed_m_s": 1.0,
        "scan_rate_hz": 5.0,
        "corridor_half_width_m": 1.0,
    },
    "scoring": {
        "gate_m": 0.5,
        "min_returns": 5,
        "min_dbh_m": 0.10,
        "max_range_m": 15.0,
        # = max_range + gate, the domain score_scan_detections itself scores since Dec 5;
        # kept for tree_errors, which lists pairs without the scorer
        "detections_scored_within_m": 15.5,
        "range_bins_m": [0.0, 5.0, 10.0, 15.0],
    },
}


#: The simulated SICK's return threshold (``ScannerModel.min_hit_fraction``, the share of the
#: footprint that must hit for a beam to return) on both drives; ``None``: the scanner preset's
#: own. Set by :func:`set_sim_hit_fraction` (``scan_detection.py`` / ``real_geometry.py``
#: ``--sim-hit-fraction``, Dec 6).
_SIM_HIT_FRACTION: list[float | None] = [None]


def set_sim_hit_fraction(q: float | None) -> None:
    """Simulate both drives (:func:`make_run`, the demo drive of :func:`simulated_precision`)
    with a scanner that returns when ``q`` of its footprint hits (``None``: the ``sick_lms``
    preset's own threshold); drops the drives already drawn."""
    _SIM_HIT_FRACTION[0] = None if q is None else float(q)
    _runs.cache_clear()


def _scanner(preset: str, **overrides: float) -> Any:
    """The scanner preset with ``overrides`` and, when set, :data:`_SIM_HIT_FRACTION`."""
    q = _SIM_HIT_FRACTION[0]
    extra = {} if q is None else {"min_hit_fraction": q}
    return scanner_preset(preset, **overrides, **extra)


def make_run(n_scans: int, seed: int) -> Any:
    s = SCENARIO
    rng = np.random.default_rng(seed)
    stand = stand_from_spec(s["stand"], s["clutter"], rng=rng)
    sc = s["scanner"]
    model = _scanner(sc["preset"], range_max=sc["range_max_m"])
    dr = s["drive"]
    path = lawnmower_path(stand.bounds, dr["strip_spacing_m"], margin=dr["margin_m"])
    return simulate_run(
        stand,
        path,
        scanner=model,
        speed=dr["speed_m_s"],
        rate_hz=dr["scan_rate_hz"],
        corridor_half_width=dr["corridor_half_width_m"],
        max_scans=n_scans,
        rng=rng,
    )


def score(obs: StemObservations, run: Any) -> dict[str, Any]:
    sc = SCENARIO["scoring"]
    keep = np.hypot(obs.centers[:, 0], obs.centers[:, 1]) <= sc["detections_scored_within_m"]
    m = scan_detection_metrics(
        obs.select(keep),
        run,
        gate=sc["gate_m"],
        min_returns=sc["min_returns"],
        max_range=sc["max_range_m"],
        min_diameter=sc["min_dbh_m"],
        range_bins=sc["range_bins_m"],
    )

    def cm(v: float) -> float | None:
        return None if not math.isfinite(v) else round(100.0 * v, 3)

    def rate(v: float) -> float | None:
        return None if not math.isfinite(v) else round(v, 4)

    out: dict[str, Any] = {
        "recall": rate(m.recall),
        "precision": rate(m.precision),
        "f1": rate(m.f1),
        "ta": m.ta,
        "fa": m.fa,
        "fr": m.fr,
        "dbh_rmse_cm": cm(m.diameter_rmse),
        "dbh_bias_cm": cm(m.diameter_bias),
        "center_rmse_cm": cm(m.center_rmse),
    }
    for b in m.by_range:
        key = f"{b.range_lo:g}_{b.range_hi:g}"
        out[f"dbh_rmse_cm_{key}"] = cm(b.diameter_rmse)
        out[f"dbh_bias_cm_{key}"] = cm(b.diameter_bias)
        out[f"recall_{key}"] = rate(b.recall)
        out[f"n_{key}"] = b.ta
    # the names the issue asks for
    out["dbh_rmse_cm_le5"] = out.get("dbh_rmse_cm_0_5")
    out["dbh_bias_cm_le5"] = out.get("dbh_bias_cm_0_5")
    out["dbh_rmse_cm_5_10"] = out.get("dbh_rmse_cm_5_10")
    out["dbh_bias_cm_5_10"] = out.get("dbh_bias_cm_5_10")
    return out


#: The issue's simulated precision target, which every ``real_geometry.py`` grid setting must keep.
SIM_PRECISION_MIN = 0.95
#: Issue 11's simulated recall target (both drives) and DBH target (benchmark drive, <= 5 m, cm).
SIM_RECALL_MIN = 0.95
SIM_DBH_RMSE_LE5_MAX_CM = 1.2
#: The range bands of :func:`score` whose DBH error :func:`simulated_precision` reports.
BANDS = ("0_5", "5_10")
BAND_KEYS = ("dbh_rmse_cm", "dbh_bias_cm", "n")

#: The seeds a setting is admitted on: its mean precision over them, per drive (sixteenth
#: round, "admission over seeds"). One drive's precision per seed has an sd of 0.020-0.027
#: (benchmark) / 0.013-0.015 (demo) over seeds 1-10 for every grid setting (one clutter object
#: seen in tens of scans is worth 0.02-0.04), so one seed decides a setting within 0.02-0.03
#: of the target by chance; the mean of ten has a standard error of about 0.008 / 0.0045 and
#: one object moves it by at most 0.004. Five seeds (0.011 / 0.006) still decided bark 5 %
#: by 0.0001 (demo mean 0.9501 over seeds 1-5, 0.9478 over 1-10). Ten seeds cost ten times
#: one seed's detection passes (the drives are drawn once per seed, :func:`_runs`).
#: Since Dec 6 seeds 1-20: the admission asks what the issue-11 target is read on (the mean
#: over seeds 1-20, docs/algorithms.md "Decisions taken where issue 11 is silent"), not a
#: noisier copy of it on half the seeds.
SIM_SEEDS: tuple[int, ...] = tuple(range(1, 21))


# The cache must hold every seed of a check: the LOO asks for SIM_SEEDS (1-20) per setting in turn,
# and a least-recently-used cache smaller than that misses on every call of such a cycle.
@functools.lru_cache(maxsize=32)
def _runs(seed: int) -> tuple[Any, Any]:
    """The two simulated drives of ``seed`` (``scan_detection.py``'s 400 scans, the ``stemmap
    demo`` drive of 120 trees), drawn once per process: every setting is scored on the same
    scans, and drawing them costs more than the compiled detector's pass over them."""
    from stemmap.cli._demo import DEMO_SCENARIO, _stand_and_run

    demo_scanner = _scanner(str(DEMO_SCENARIO["scanner"]))
    return make_run(400, seed), _stand_and_run(seed, 120, scanner=demo_scanner)


def benchmark_drive(seed: int) -> Any:
    """``scan_detection.py``'s 400-scan drive of ``seed``, the one :func:`simulated_precision`
    scores (drawn once per process)."""
    return _runs(int(seed))[0]


def demo_score(obs: StemObservations, run: Any) -> dict[str, float]:
    """Detection recall and precision of ``obs`` on the ``stemmap demo`` drive ``run``, scored
    as the demo scores them (``cli._demo.demo_detection_metrics``: its ``DEMO_SCENARIO`` gate,
    returns, range and diameter)."""
    from stemmap.cli._demo import demo_detection_metrics

    m = demo_detection_metrics(obs, run)
    return {"recall": round(m.recall, 4), "precision": round(m.precision, 4)}


def simulated_precision(overrides: dict[str, Any], seed: int = 1) -> dict[str, Any]:
    """Detection recall / precision of the ``stemmap`` preset with ``overrides`` on the two
    simulated drives the ``real_geometry.py`` grid is admitted on: ``scan_detection.py``'s
    (400 scans, its scoring) and the ``stemmap demo`` drive (120 trees, the demo's scoring),
    seed ``seed``; ``admitted`` when both precisions are >= :data:`SIM_PRECISION_MIN`."""
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides))
    run, demo_run = _runs(int(seed))
    bench = score(det.detect_batch(run.scans), run)
    demo = demo_score(det.detect_batch(demo_run.scans), demo_run)
    keys = ("recall", "precision", *(f"{k}_{b}" for b in BANDS for k in BAND_KEYS))
    return {
        "benchmark": {k: bench[k] for k in keys},
        "demo": demo,
        "admitted": min(bench["precision"], demo["precision"]) >= SIM_PRECISION_MIN,
    }


def admitted_over_seeds(rows: Sequence[dict[str, Any]]) -> bool:
    """The admission rule of the ``real_geometry.py`` grid: issue 11's simulated targets, each
    on the mean over the seeds' ``rows`` (:func:`simulated_precision` results), the rule the
    docs state the default against since Dec 3:

    - precision >= :data:`SIM_PRECISION_MIN` on each drive (sixteenth round);
    - recall >= :data:`SIM_RECALL_MIN` on each drive, and the benchmark drive's DBH RMSE at
      <= 5 m <= :data:`SIM_DBH_RMSE_LE5_MAX_CM` (Dec 5: the precision alone admitted every
      "edge any" grid point, whose simulated DBH RMSE is 1.37-1.84 cm on all of seeds 1-20,
      scan-detection.md "The fit's measured noise, the default"). Rows without recall or a
      DBH key (a drive with no pair at <= 5 m) fail.

    With one row it is that seed's own test."""
    if not rows:
        raise ValueError("no seeds")

    def mean(drive: str, key: str) -> float:
        v = [r[drive].get(key) for r in rows]
        return math.nan if any(x is None for x in v) else float(np.mean(np.asarray(v, float)))

    drives = ("benchmark", "demo")
    return (
        all(mean(d, "precision") >= SIM_PRECISION_MIN for d in drives)
        and all(mean(d, "recall") >= SIM_RECALL_MIN for d in drives)
        and mean("benchmark", "dbh_rmse_cm_0_5") <= SIM_DBH_RMSE_LE5_MAX_CM
    )


def simulated_precision_seeds(overrides: dict[str, Any], seeds: Sequence[int]) -> dict[str, Any]:
    """:func:`simulated_precision` on each of ``seeds`` (each seed draws a new stand, clutter
    and drive): the rows per seed, the mean, smallest and largest precision and recall of each
    drive, the seeds below the precision target (``failing_seeds``), and ``admitted`` by
    :func:`admitted_over_seeds` (the mean over seeds; ``every_seed`` says whether each seed
    keeps it too: the default kept the target on seed 1 but not on seeds 2 and 7,
    scan-detection-history.md, sixteenth round).

    Also issue 11's other simulated targets on the benchmark drive: the DBH RMSE and bias (cm)
    at 0-5 m (the target's band) and 5-10 m per seed, their mean / smallest / largest over
    seeds and pooled over every matched pair of every seed (``_pooled``: weighted by each
    seed's pair count ``n_0_5`` / ``n_5_10``);
    ``recall_failing_seeds`` (recall < :data:`SIM_RECALL_MIN` on either drive) and
    ``dbh_failing_seeds`` (RMSE > :data:`SIM_DBH_RMSE_LE5_MAX_CM` or no pair)."""
    rows = [{"seed": int(s), **simulated_precision(overrides, int(s))} for s in seeds]
    summary: dict[str, Any] = {}
    for drive in ("benchmark", "demo"):
        for key in ("precision", "recall"):
            v = [float(r[drive][key]) for r in rows]
            summary[f"{drive}_{key}_mean"] = round(float(np.mean(v)), 4)
            summary[f"{drive}_{key}_min"] = round(min(v), 4)
            summary[f"{drive}_{key}_max"] = round(max(v), 4)
    for band in BANDS:
        bench = [
            r["benchmark"] for r in rows if r["benchmark"].get(f"dbh_rmse_cm_{band}") is not None
        ]
        if not bench:
            continue
        n = np.array([float(b[f"n_{band}"]) for b in bench])
        rmse = np.array([float(b[f"dbh_rmse_cm_{band}"]) for b in bench])
        bias = np.array([float(b[f"dbh_bias_cm_{band}"]) for b in bench])
        for key, v in ((f"dbh_rmse_cm_{band}", rmse), (f"dbh_bias_cm_{band}", bias)):
            summary[f"benchmark_{key}_mean"] = round(float(np.mean(v)), 3)
            summary[f"benchmark_{key}_min"] = round(float(np.min(v)), 3)
            summary[f"benchmark_{key}_max"] = round(float(np.max(v)), 3)
        summary[f"benchmark_dbh_rmse_cm_{band}_pooled"] = round(
            float(np.sqrt(np.sum(n * rmse**2) / np.sum(n))), 3
        )
        summary[f"benchmark_dbh_bias_cm_{band}_pooled"] = round(
            float(np.sum(n * bias) / np.sum(n)), 3
        )
    return {
        "seeds": [int(s) for s in seeds],
        "per_seed": rows,
        **summary,
        "recall_failing_seeds": [
            r["seed"]
            for r in rows
            if min(float(r["benchmark"]["recall"]), float(r["demo"]["recall"])) < SIM_RECALL_MIN
        ],
        "dbh_failing_seeds": [
            r["seed"]
            for r in rows
            if r["benchmark"].get("dbh_rmse_cm_0_5") is None
            or float(r["benchmark"]["dbh_rmse_cm_0_5"]) > SIM_DBH_RMSE_LE5_MAX_CM
        ],
        "failing_seeds": [r["seed"] for r in rows if not r["admitted"]],
        "every_seed": all(r["admitted"] for r in rows),
        "admitted": admitted_over_seeds(rows),
    }


def edge_status(ranges: np.ndarray, beams: np.ndarray, dist: float, dbh: float) -> tuple[str, str]:
    """What lies beyond each silhouette edge of a trunk in one scan (first, last beam of
    ``beams``, its returns in the scan ``ranges``; trunk centre at ``dist``, diameter ``dbh``,
    metres): ``"fov"`` (the edge is the field of view's end), ``"occluded"`` (the next beam
    returns from nearer than the trunk's front: the edge is hidden), ``"background"`` (it
    returns from behind: a mixed pixel's background) or ``"open"`` (no return). A trunk is
    *whole* in that scan when neither edge is ``fov`` / ``occluded`` (the Cramér-Rao bound's
    edge model, scan-fits.md)."""
    out: list[str] = []
    for b_edge, step in ((int(beams[0]), -1), (int(beams[-1]), 1)):
        nb = b_edge + step
        if not 0 <= nb < ranges.shape[0]:
            out.append("fov")
            continue
        rn = ranges[nb]
        if not np.isfinite(rn):
            out.append("open")
        elif rn < dist - dbh / 2:
            out.append("occluded")
        else:
            out.append("background")
    return out[0], out[1]


def scan_truth(
    run: Any, k: int, *, min_returns: int, max_range: float, min_dbh: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trees of ``run`` in scan ``k``'s sensor frame (T, 2), their range (T,) and which of
    them the scoring counts (``detectable_trees``: at least ``min_returns`` of their own
    returns, within ``max_range``, at least ``min_dbh`` thick)."""
    pose = run.true_poses.poses[k]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = run.stand.trees_xy - pose[:2]
    local = np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))
    rng = np.hypot(local[:, 0], local[:, 1])
    elig = detectable_trees(
        run.hit_ids[k],
        run.stand.trees_xy.shape[0],
        min_returns=int(min_returns),
        truth_range=rng,
        max_range=float(max_range),
        diameters=run.stand.diameters,
        min_diameter=float(min_dbh),
    )
    return local, rng, elig


def tree_errors(obs: StemObservations, run: Any) -> dict[str, np.ndarray]:
    """Every matched (eligible tree, detection) pair of :func:`score` with the tree it is:
    scan, tree index, sensor range (m), true DBH (m), DBH error (m, detected - true), returns
    on the trunk, mixed-pixel returns among them, and ``whole`` (both edges seen,
    :func:`edge_status`). The same rules as :func:`score` (detections beyond
    ``detections_scored_within_m`` dropped, ``scan_detection_metrics``' eligibility and
    one-to-one matching per scan), so the RMSE of these errors per range band is the score's;
    a diagnostic of which trees make the DBH RMSE, not a second scorer."""
    sc = SCENARIO["scoring"]
    keep = np.hypot(obs.centers[:, 0], obs.centers[:, 1]) <= sc["detections_scored_within_m"]
    obs = obs.select(keep)
    poses = run.true_poses.poses
    tdiam = run.stand.diameters
    cols: dict[str, list[Any]] = {
        k: [] for k in ("scan", "tree", "range", "dbh", "error", "returns", "mixed", "whole")
    }
    for k in range(poses.shape[0]):
        sel = obs.index == k
        local, rng_k, elig = scan_truth(
            run,
            k,
            min_returns=sc["min_returns"],
            max_range=sc["max_range_m"],
            min_dbh=sc["min_dbh_m"],
        )
        hit = run.hit_ids[k]
        m = match_points(obs.centers[sel], local, sc["gate_m"])
        diam = obs.diameters[sel]
        for i, j in m.pairs:
            if not elig[j]:
                continue
            beams = np.flatnonzero(hit == j)
            sides = edge_status(run.scans.ranges[k], beams, float(rng_k[j]), float(tdiam[j]))
            for key, v in (
                ("scan", k),
                ("tree", j),
                ("range", rng_k[j]),
                ("dbh", tdiam[j]),
                ("error", diam[i] - tdiam[j]),
                ("returns", beams.shape[0]),
                ("mixed", int(np.sum(run.mixed[k, beams]))),
                ("whole", "fov" not in sides and "occluded" not in sides),
            ):
                cols[key].append(v)
    return {k: np.asarray(v) for k, v in cols.items()}


def worst_trees(err: dict[str, np.ndarray], max_range: float = 5.0, n: int = 5) -> dict[str, Any]:
    """The DBH RMSE at < ``max_range`` (the score's 0-5 m band) of :func:`tree_errors`
    ``err`` split into whole and partial trunks (cm), and the ``n`` trees with the largest
    share of its sum of squares: per tree its pairs, share, RMSE and mean error (cm), mean
    range (m), true DBH (cm), mean returns, the fraction of pairs seen partially and the mean
    mixed-pixel returns."""
    near = err["range"] < max_range
    e = 100.0 * err["error"][near]
    whole = err["whole"][near].astype(bool)

    def rms(v: np.ndarray) -> float | None:
        return round(float(np.sqrt(np.mean(v**2))), 3) if v.size else None

    out: dict[str, Any] = {
        "n": int(e.size),
        "dbh_rmse_cm": rms(e),
        "whole_n": int(whole.sum()),
        "whole_dbh_rmse_cm": rms(e[whole]),
        "partial_n": int((~whole).sum()),
        "partial_dbh_rmse_cm": rms(e[~whole]),
    }
    trees = err["tree"][near]
    sse_all = float(np.sum(e**2))
    rows = []
    for j in np.unique(trees):
        t = trees == j
        et = e[t]
        rows.append(
            {
                "tree": int(j),
                "pairs": int(t.sum()),
                "sse_share": round(float(np.sum(et**2)) / sse_all, 3) if sse_all > 0 else 0.0,
                "rmse_cm": rms(et),
                "mean_error_cm": round(float(np.mean(et)), 2),
                "range_m": round(float(np.mean(err["range"][near][t])), 2),
                "dbh_cm": round(100.0 * float(err["dbh"][near][t][0]), 1),
                "returns": round(float(np.mean(err["returns"][near][t])), 1),
                "partial_fraction": round(float(np.mean(~whole[t])), 2),
                "mixed_returns": round(float(np.mean(err["mixed"][near][t])), 2),
            }
        )
    rows.sort(key=lambda r: -float(r["sse_share"]))
    out["worst"] = rows[:n]
    return out
