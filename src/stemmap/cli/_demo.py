"""``stemmap demo``: the whole chain on the built-in simulated forest, no input needed.

simulated stand + drive (2D laser scans, wheel odometry, ground truth)
-> per-scan trunk detection (:class:`stemmap.scan.detect.ScanTrunkDetector`, default preset)
-> tree-landmark SLAM (default back-end iSAM2, ``--backend`` for the others) -> stem map + path
-> scored against the simulator's truth, written to ``--out``:

* ``detections.csv`` -- every trunk seen in every scan (the ``stemmap detect`` format, sensor
  frame);
* ``trees.csv``, ``trees.geojson`` -- the stem map (world frame, metres);
* ``trajectory.csv`` -- the estimated path (time_s,x,y,theta, pose covariance columns);
* ``truth_trees.csv`` -- the simulator's trees (id,x,y,diameter);
* ``metrics.json`` -- detection precision/recall and DBH error, map and path errors, scenario;
* ``demo.png`` -- the map over the truth, and the per-scan DBH error against range.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer

from stemmap.cli._common import (
    ProgressFlag,
    QuietFlag,
    clean_json,
    fail_on_stemmap_error,
    json_default,
    progress,
)
from stemmap.cli._geo import CrsOption, GpkgFlag, checked_crs
from stemmap.cli._map import Backend, sim_problem, slam_metrics
from stemmap.cli._summary import JsonFlag, announce_compile, fmt, print_summary
from stemmap.cli._validate import bounded

if TYPE_CHECKING:
    from stemmap.eval.detection import DetectionMetrics
    from stemmap.sim.trajectory import SimRun
    from stemmap.types import StemObservations

__all__ = ["DEMO_BACKEND", "DEMO_SCENARIO", "demo_detection_metrics", "register", "run_demo"]

#: Default SLAM back-end of the demo: ours, GTSAM iSAM2 with odometry self-calibration. On this
#: simulated loop, seeds 1-6, trajectory RMSE 0.03-0.18 m and loop-closure error <= 0.13 m (EKF
#: 0.12-0.32 m / <= 0.12 m; docs/algorithms/slam.md "Odometry self-calibration").
DEMO_BACKEND = "isam2"

#: The demo's stand, clutter, scanner and drive (every parameter declared, as the benchmarks do).
DEMO_SCENARIO: dict[str, Any] = {
    "stand": {
        "layout": "random",
        "size_m": 60.0,
        "dbh_mean_m": 0.30,
        "dbh_std_m": 0.10,
        "dbh_min_m": 0.10,
        "min_spacing_m": 2.0,
    },
    "clutter": {"n_bushes": 8, "n_branches": 8, "n_walls": 1, "n_fences": 1, "n_rocks": 4},
    "scanner": "sick_lms",
    "drive": {
        "path": "loop",
        "radii_fraction": 0.35,
        "laps": 1.0,
        "speed_m_s": 1.0,
        "scan_rate_hz": 5.0,
        "corridor_half_width_m": 2.0,
        "odometry_noise": "wheel",
    },
    "scoring": {
        "scan_gate_m": 0.5,
        "min_returns": 5,
        "min_dbh_m": 0.10,
        "max_range_m": 15.0,
        "map_gate_m": 1.0,
        "map_precision_truth": "every tree of the stand",
        "map_recall_truth": "trees with >= 5 returns in >= 3 scans",
    },
}


def _stand_and_run(
    seed: int, n_trees: int, drive_rng: np.random.Generator | None = None, scanner: Any = None
) -> Any:
    """The demo's stand (from ``seed``) and drive. ``drive_rng``: draw the drive's noise
    (scanner, odometry) from this generator instead of ``seed``'s stream after the stand (the
    same stand and path, another noise draw; benchmarks/sim_dbh_causes.py ``--redraw``).
    ``scanner``: a :class:`~stemmap.sim.scanner.ScannerModel` (or preset name) instead of the
    scenario's (benchmarks/_scan_sim.py ``set_sim_hit_fraction``)."""
    from stemmap.sim.forest import stand_from_spec
    from stemmap.sim.trajectory import loop_path, simulate_run

    s = DEMO_SCENARIO
    dr = s["drive"]
    rng = np.random.default_rng(seed)
    stand = stand_from_spec(s["stand"], s["clutter"], n_trees=n_trees, rng=rng)
    size = float(s["stand"]["size_m"])
    f = float(dr["radii_fraction"])
    path = loop_path((size / 2, size / 2), (f * size, f * size), laps=float(dr["laps"]))
    return simulate_run(
        stand,
        path,
        scanner=s["scanner"] if scanner is None else scanner,
        speed=dr["speed_m_s"],
        rate_hz=dr["scan_rate_hz"],
        corridor_half_width=dr["corridor_half_width_m"],
        odometry_noise=dr["odometry_noise"],
        rng=rng if drive_rng is None else drive_rng,
    )


def demo_detection_metrics(obs: StemObservations, run: SimRun) -> DetectionMetrics:
    """Per-scan detection metrics of ``obs`` on a demo drive ``run`` by the demo's scoring
    (``DEMO_SCENARIO["scoring"]``): :func:`run_demo`'s, and the benchmarks' that score the
    demo drive (benchmarks/_scan_sim.py, benchmarks/sim_dbh_causes.py)."""
    from stemmap.eval.detection import scan_detection_metrics

    sc = DEMO_SCENARIO["scoring"]
    return scan_detection_metrics(
        obs,
        run,
        gate=sc["scan_gate_m"],
        min_returns=sc["min_returns"],
        max_range=sc["max_range_m"],
        min_diameter=sc["min_dbh_m"],
    )


def run_demo(
    out_dir: Path,
    *,
    seed: int = 1,
    n_trees: int = 120,
    backend: str = DEMO_BACKEND,
    show_progress: bool = False,
    crs: str | None = None,
    gpkg: bool = False,
) -> dict[str, Any]:
    """Simulate, detect, map and score; write every product to ``out_dir``; return the metrics.

    Raises
    ------
    ConfigError
        On an unknown back-end or an impossible scenario (e.g. too many trees for the stand).

    Notes
    -----
    ``crs`` declares the simulated world frame as that CRS (a what-if for GIS checks: the
    simulator has no real position); ``gpkg`` adds ``map.gpkg``.
    """
    from stemmap.cli._geo import write_map_products
    from stemmap.cli._map import frames_metadata
    from stemmap.cli._summary import write_run_report
    from stemmap.eval.maps import map_metrics
    from stemmap.io.atomic import atomic_write
    from stemmap.io.maps import write_observations_csv
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.sim.observations import returns_per_tree
    from stemmap.slam.base import dead_reckoning, make_backend
    from stemmap.slam.uncertainty import annotate_uncertainty

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    run = _stand_and_run(seed, n_trees)
    timings["simulate_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    detector = ScanTrunkDetector()
    obs = detector.detect_batch(run.scans)
    timings["detect_s"] = time.perf_counter() - t0
    det = demo_detection_metrics(obs, run)
    sc = DEMO_SCENARIO["scoring"]

    t0 = time.perf_counter()
    problem, ctx = sim_problem(
        run,
        obs,
        name=f"demo(seed={seed}, trees={n_trees})",
        backend=backend,
    )
    be = make_backend(backend)
    with progress(show_progress) as bar:
        task = bar.add_task(f"{backend} SLAM", total=len(problem.frames))

        def tick(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        result = be.run(problem, progress=tick)
    result.stem_map, unc = annotate_uncertainty(result, problem)
    timings["slam_s"] = time.perf_counter() - t0
    slam, _, _ = slam_metrics(problem, result, ctx)

    # precision against every tree of the stand (a rarely seen real tree is no false tree);
    # recall against the trees the drive actually showed the scanner
    seen = (returns_per_tree(run) >= sc["min_returns"]).sum(axis=0) >= 3
    stand = run.stand
    mm = map_metrics(result.stem_map, None, stand.trees_xy, stand.diameters, gate=sc["map_gate_m"])
    mm_seen = map_metrics(
        result.stem_map, None, stand.trees_xy[seen], stand.diameters[seen], gate=sc["map_gate_m"]
    )
    map_dict = mm.to_dict()
    map_dict["recall_of_seen"] = mm_seen.recall
    map_dict["n_seen_matched"] = mm_seen.n_matched
    metrics: dict[str, Any] = {
        "seed": seed,
        "n_trees_in_stand": int(stand.n_trees),
        "n_trees_seen": int(seen.sum()),
        "n_scans": len(run.scans),
        "backend": backend,
        "detection": det.to_dict(),
        "map": map_dict,
        "slam": {k: v for k, v in slam.items() if k not in ("map", "scenario")},
        "uncertainty": unc.to_dict(),
        "timings": timings,
        "frames": frames_metadata(problem, crs),
        "scenario": DEMO_SCENARIO,
        "simulator": run.params,
    }

    out_dir.mkdir(parents=True, exist_ok=True)
    write_observations_csv(out_dir / "detections.csv", obs)
    write_map_products(
        out_dir, result.stem_map, result.trajectory, crs=crs, gpkg=gpkg, pose_covs=result.pose_covs
    )
    with atomic_write(out_dir / "truth_trees.csv") as fh:
        fh.write("id,x,y,diameter\n")
        for i, ((x, y), d) in enumerate(zip(stand.trees_xy, stand.diameters, strict=True)):
            fh.write(f"{i},{x:.4f},{y:.4f},{d:.4f}\n")
    with atomic_write(out_dir / "metrics.json") as fh:
        json.dump(clean_json(metrics), fh, indent=1, default=json_default, allow_nan=False)
    head = (
        f"stem map ({backend}): recall {map_dict['recall_of_seen']:.2f} of the "
        f"{int(seen.sum())} trees seen, precision {map_dict['precision']:.2f}, "
        f"position RMSE {100 * (map_dict.get('position_rmse') or math.nan):.0f} cm"
    )
    _figure(out_dir / "demo.png", run, obs, det, result, dead_reckoning(problem), head)
    write_run_report(
        out_dir,
        title=f"stemmap demo (seed {seed}, {backend})",
        headline=head,
        metrics=metrics,
        figure="demo.png",
        stem_map=result.stem_map,
        parameters={"seed": seed, "n_trees": n_trees, "backend": backend, "crs": crs},
        files=["detections.csv", "trees.csv", "trees.geojson", "trajectory.csv",
               "truth_trees.csv", "metrics.json", "demo.png"],
        crs=crs,
    )  # fmt: skip
    return metrics


def _figure(path: Path, run: Any, obs: Any, det: Any, result: Any, dr: Any, title: str) -> None:
    """Left: stem map, path, dead reckoning and truth. Right: per-scan DBH error vs range."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from stemmap.eval.matching import match_points
    from stemmap.io.atomic import atomic_write
    from stemmap.sim.observations import trees_in_sensor_frame
    from stemmap.viz.maps import plot_stem_map

    fig = Figure(figsize=(14, 6.5))
    ax = fig.add_subplot(1, 2, 1)
    plot_stem_map(
        ax,
        result.stem_map,
        result.trajectory,
        reference=dr,
        truth_xy=run.stand.trees_xy,
        title=title,
        gate=DEMO_SCENARIO["scoring"]["map_gate_m"],
    )
    ax2 = fig.add_subplot(1, 2, 2)
    # per-scan matches of detections to truth (sensor frame), same gate as the metrics
    rel = trees_in_sensor_frame(run)
    rng_all, err_all = [], []
    for k in np.unique(obs.index):
        sel = obs.index == k
        m = match_points(obs.centers[sel], rel[k], gate=0.5)
        if m.pairs.size:
            di, ti = m.pairs[:, 0], m.pairs[:, 1]
            d_est = 2.0 * obs.radii[sel][di]
            rng_all.append(np.hypot(*rel[k][ti].T))
            err_all.append(100.0 * (d_est - run.stand.diameters[ti]))
    if rng_all:
        r, e = np.concatenate(rng_all), np.concatenate(err_all)
        ax2.plot(r, e, ".", ms=2, alpha=0.4, color="tab:blue")
        ax2.axhline(0.0, color="k", lw=0.8)
    ax2.set_xlabel("range to trunk (m)")
    ax2.set_ylabel("DBH error per scan (cm)")
    ax2.set_ylim(-10, 10)
    ax2.set_title(
        f"per-scan detection: precision {det.precision:.3f}, recall {det.recall:.3f}, "
        f"DBH RMSE {100 * det.diameter_rmse:.2f} cm"
    )
    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=120)


_DEFAULT_BACKEND = Backend(DEMO_BACKEND)


def demo(
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path(
        "stemmap-demo"
    ),
    seed: Annotated[
        int,
        typer.Option(
            help="Simulation seed (same seed, same files).", callback=bounded("--seed", ge=0)
        ),
    ] = 1,
    n_trees: Annotated[
        int,
        typer.Option(
            "--n-trees",
            help="Trees drawn in the 60 x 60 m stand, before those within 2 m of the drive's "
            "path are cleared (seed 1: 120 -> 100; the summary's 'trees in the stand').",
            callback=bounded("--n-trees", ge=1),
        ),
    ] = 120,
    backend: Annotated[Backend, typer.Option("--backend", help="SLAM back-end.")] = (
        _DEFAULT_BACKEND
    ),
    show_progress: ProgressFlag = True,
    quiet: QuietFlag = False,
    as_json: JsonFlag = False,
    crs: CrsOption = None,
    gpkg: GpkgFlag = False,
) -> None:
    """Simulate a forest and a drive, detect every trunk, map it, and score it against truth.

    Needs no input. Writes detections.csv, trees.csv, trees.geojson, trajectory.csv,
    truth_trees.csv, metrics.json, demo.png and report.html (and map.gpkg with --gpkg) to
    --out, and prints a summary (--json: one JSON object). Every column: docs/outputs.md.

    Example: stemmap demo --out stemmap-demo --seed 1
    """
    from stemmap.io.products import run_products

    with fail_on_stemmap_error(), run_products("demo", out_dir=out_dir) as run:
        # after the output folder is checked, not before
        announce_compile("scan", backend=backend.value, quiet=quiet)
        m = run_demo(
            run.dir,
            seed=seed,
            n_trees=n_trees,
            backend=backend.value,
            show_progress=show_progress and not quiet,
            crs=checked_crs(crs),
            gpkg=gpkg,
        )
    d, mp, s = m["detection"], m["map"], m["slam"]
    rows = [
        ("trees in the stand / seen from the path",
         f"{m['n_trees_in_stand']} / {m['n_trees_seen']}", "n_trees_in_stand, n_trees_seen"),
        ("scans", fmt(m["n_scans"]), "n_scans"),
        ("per-scan detection: precision", fmt(d["precision"], digits=3), "detection.precision"),
        ("per-scan detection: recall", fmt(d["recall"], digits=3), "detection.recall"),
        ("per-scan DBH RMSE / bias",
         f"{fmt(d['diameter_rmse'], ' cm', 100)} / {fmt(d['diameter_bias'], ' cm', 100)}",
         "detection.diameter_rmse, .diameter_bias"),
        (f"stem map ({m['backend']}): trees mapped / matched",
         f"{mp['n_map']} / {mp['n_matched']}", "map.n_map, map.n_matched"),
        ("map recall of the trees seen", fmt(mp["recall_of_seen"], digits=3),
         "map.recall_of_seen"),
        ("map recall of all stand trees", fmt(mp["recall"], digits=3), "map.recall"),
        ("map precision", fmt(mp["precision"], digits=3), "map.precision"),
        ("tree position RMSE", fmt(mp["position_rmse"], " cm", 100), "map.position_rmse"),
        ("map DBH RMSE", fmt(mp["diameter_rmse"], " cm", 100), "map.diameter_rmse"),
        ("path RMSE", fmt(s.get("trajectory_rmse_m"), " cm", 100), "slam.trajectory_rmse_m"),
        ("RPE per 10 m of path: translation / rotation RMSE",
         f"{fmt(s.get('rpe_trans_rmse_m'), ' cm', 100)} / {fmt(s.get('rpe_rot_rmse_deg'), ' deg')}",
         "slam.rpe_trans_rmse_m, .rpe_rot_rmse_deg"),
        ("loop-closure error (dead reckoning)",
         f"{fmt(s.get('loop_closure_error_m'), ' cm', 100)} "
         f"({fmt(s.get('dead_reckoning_loop_closure_error_m'), ' cm', 100)})",
         "slam.loop_closure_error_m"),
    ]  # fmt: skip
    files = [
        "detections.csv", "trees.csv", "trees.geojson", "trajectory.csv", "truth_trees.csv",
        "metrics.json", "demo.png", "report.html", *(["map.gpkg"] if gpkg else []), "run.json",
    ]  # fmt: skip
    print_summary(
        f"stemmap demo (seed {m['seed']})", rows, out_dir, files, as_json=as_json,
        quiet=quiet, payload={"metrics": m},
    )  # fmt: skip


def register(app: typer.Typer) -> None:
    """Add ``stemmap demo`` to the CLI."""
    app.command("demo")(demo)
