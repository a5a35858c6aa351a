"""``stemmap map``: tree-landmark SLAM on a dataset, a simulated run or a ROS bag.

Writes to ``--out DIR``: ``trees.csv`` (id,x,y,diameter,std_x,std_y,n_obs,...),
``trees.geojson``, ``trajectory.csv`` (time_s,x,y,theta and, where the back-end reports them,
the pose covariance columns), ``metrics.json`` and ``map.png``.
"""

from __future__ import annotations

import json
import logging
import math
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from stemmap.cli._common import clean_json, fail_on_stemmap_error, json_default, progress
from stemmap.cli._geo import (
    CrsOption,
    GpkgFlag,
    checked_crs,
    write_gps_frame,
    write_map_products,
)
from stemmap.cli._map_frames import Frontend
from stemmap.cli._map_motion import (
    Motion,
    motion_trajectory,
    resolve_motion,
    vehicle_path,
    wheel_drift_estimate,
)
from stemmap.cli._map_prior import (
    continue_from_map,
    false_trees_report,
    write_information,
)
from stemmap.cli._multilog import SchedulerOption, WorkersOption, run_many_logs, wants_logs
from stemmap.cli._summary import (
    JsonFlag,
    announce_compile,
    fmt,
    print_summary,
    write_run_report,
)
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError

__all__ = ["register", "sim_problem", "slam_metrics"]

log = logging.getLogger(__name__)


class Backend(StrEnum):
    treedb = "treedb"
    ekf = "ekf"
    fastslam = "fastslam"
    forestrix = "forestrix"
    isam2 = "isam2"


class TrajectoryFormat(StrEnum):
    csv = "csv"
    tum = "tum"


class Dataset(StrEnum):
    victoria_park = "victoria-park"


def _vp_inputs(data: Path | None) -> list[Path]:
    """The Victoria Park files a run reads (recorded and protected by the run manifest)."""
    from stemmap.datasets import find_datasets_dir

    if data is None:
        root = find_datasets_dir()
        if root is None:
            return []
        data = root / "victoria_park"
    return [data / n for n in ("inputs.dat", "measurements.dat", "gps.dat")]


def _victoria_park(
    data: Path | None, t_end: float | None, t_start: float = 0.0
) -> tuple[Any, dict[str, Any]]:
    from stemmap.datasets.victoria_park import load_victoria_park

    vp = load_victoria_park(data)
    if t_end is not None or t_start > 0:
        vp = vp.slice(t_start, math.inf if t_end is None else t_end)
    return vp.problem(), {"kind": "victoria-park", "vp": vp}


def _simulated(seed: int, n_trees: int, size: float) -> tuple[Any, dict[str, Any]]:
    from stemmap.sim.forest import random_stand
    from stemmap.sim.trajectory import loop_path, simulate_run

    stand = random_stand(n_trees, (size, size), rng=seed)
    path = loop_path((size / 2, size / 2), (0.35 * size, 0.35 * size), laps=1.0)
    run = simulate_run(stand, path, speed=1.0, rate_hz=5.0, corridor_half_width=2.0, rng=seed)
    return sim_problem(run, name=f"sim(seed={seed}, trees={n_trees}, size={size} m)")


def sim_problem(
    run: Any, obs: Any = None, *, name: str = "simulated run"
) -> tuple[Any, dict[str, Any]]:
    """A :class:`~stemmap.slam.base.SlamProblem` from a simulated run (and its context).

    ``obs`` are the run's per-scan trunk detections (default: the default detector on
    ``run.scans``). The motion noise comes from the simulator's own odometry spec, so nothing
    is tuned on the ground truth.
    """
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.slam.base import Controls, SlamProblem, TreeFrames
    from stemmap.slam.motion import UnicycleModel

    if obs is None:
        obs = ScanTrunkDetector().detect_batch(run.scans)
    frames = TreeFrames.from_observations(obs, run.scans.times)
    odo = run.odometry
    controls = Controls(odo.times, odo.speed, odo.yaw_rate, "unicycle")
    off = run.sensor_offset
    v0 = run.vehicle_poses.poses[0]
    # per-sample white noise at the odometry rate -> one-second average, plus the bias /
    # scale error as a 1-s equivalent
    on = run.params.get("odometry_noise") or {}
    rate = float(run.params.get("odom_rate_hz", 50.0))
    sig_v = float(on.get("speed_noise", 0.05)) / math.sqrt(rate) + abs(
        float(on.get("speed_scale", 1.0)) - 1.0
    )
    sig_w = float(on.get("yaw_rate_noise", 0.0175)) / math.sqrt(rate) + abs(
        float(on.get("yaw_rate_bias", 0.0))
    )
    problem = SlamProblem(
        controls,
        frames,
        UnicycleModel(sigma_speed=max(sig_v, 1e-3), sigma_steer=max(sig_w, 1e-4)),
        sensor_offset=(off.x, off.y),
        initial_pose=(float(v0[0]), float(v0[1]), float(v0[2])),
        name=name,
        max_range=run.scanner.range_max if hasattr(run.scanner, "range_max") else math.inf,
    )
    return problem, {"kind": "sim", "run": run, "params": run.params, "scans": run.scans}


def _with_gnss(problem: Any, path: Path, lever: str | None, sigma: float, backend: str) -> Any:
    """``problem`` with the fixes of ``path`` (``--gnss``); lever arm from ``--gnss-lever``."""
    import dataclasses

    from stemmap.slam.gnss import read_gnss_csv

    if backend != "isam2":
        raise ConfigError(f"--gnss is fused by the isam2 back-end only; got --backend {backend}.")
    if not (math.isfinite(sigma) and sigma > 0):
        raise ConfigError(f"--gnss-sigma must be a positive number of metres, got {sigma}.")
    if lever is None:  # Victoria Park: the antenna is at the laser (docs/algorithms/slam.md)
        arm = problem.sensor_offset if problem.name.startswith("victoria_park") else (0.0, 0.0)
    else:
        try:
            lx, ly = (float(v) for v in lever.split(","))
        except ValueError as exc:
            raise ConfigError(f"--gnss-lever must be 'x,y' in metres, got {lever!r}.") from exc
        arm = (lx, ly)
    fixes = read_gnss_csv(path, lever_arm=arm, default_sigma=sigma)
    return dataclasses.replace(problem, gnss=fixes)


def _realtime(problem: Any, backend: str, tick: Any, rrd: Path | None) -> Any:
    """``--realtime``: the log through :func:`stemmap.slam.online.replay` (latency in stats),
    logged to a Rerun recording with ``--rerun``."""
    from stemmap.slam.base import SlamResult
    from stemmap.slam.online import replay

    if backend != "isam2" or problem.gnss is not None or problem.prior_map is not None:
        raise ConfigError("--realtime runs the isam2 online mapper without --gnss/--prior-map.")
    rec = None
    if rrd is not None:
        from stemmap.viz.live import RerunRecorder

        rec = RerunRecorder(rrd)

    def on_scan(m: Any, f: int) -> None:
        if rec is not None:
            rec(m, f)
        tick(f + 1, len(problem.frames))

    try:
        st = replay(problem, on_scan=on_scan)
    finally:
        if rec is not None:
            rec.close()
    lat = np.asarray(st["latency_s"]) * 1e3
    stats = {"backend": "isam2-online", **st["stats"], "rss_mb": st["rss_mb_by_pass"][-1]}
    for q in (50, 90, 99):
        stats[f"latency_ms_p{q}"] = float(np.percentile(lat, q))
    stats["latency_ms_max"] = float(lat.max())
    return SlamResult(st["trajectory"], st["stem_map"], stats, pose_covs=st["pose_covs"])


def _motion_sigma(text: str | None) -> tuple[float, float] | None:
    """``--motion-sigma 'speed,yaw_rate'`` -> (m/s, rad/s); None when not given."""
    if text is None:
        return None
    try:
        sv, sw = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise ConfigError(
            f"--motion-sigma must be 'speed,yaw_rate' (m/s, rad/s), got {text!r}."
        ) from exc
    if not (sv > 0 and sw > 0 and math.isfinite(sv) and math.isfinite(sw)):
        raise ConfigError(f"--motion-sigma values must be finite and > 0, got {text!r}.")
    return sv, sw


RPE_DELTA_M = 10.0
"""Path length (m) of the relative pose error's stretches on simulated runs (evo's --delta)."""


def slam_metrics(
    problem: Any, result: Any, ctx: dict[str, Any], dr: Any = None
) -> tuple[dict[str, Any], Any, Any]:
    """Metrics for the run and (gps_xy_in_map, truth_xy) for the figure.

    ``dr`` is the run's dead reckoning (:func:`~stemmap.slam.base.dead_reckoning`), computed
    here when not given.
    """
    from stemmap.eval.trajectory import ate, loop_closure_error, rpe, screen_gps
    from stemmap.slam.base import dead_reckoning, duplicate_pairs, sensor_poses
    from stemmap.slam.motion import preintegrate

    m: dict[str, Any] = {
        "problem": problem.name,
        "backend_stats": result.stats,
        "n_trees": len(result.stem_map),
        "duplicates_1m": duplicate_pairs(result.stem_map, 1.0),
        "n_frames": len(problem.frames),  # "frames" holds the frame facts (frames_metadata)
        "detections": problem.frames.n_detections,
    }
    if "front_end" in ctx:  # a frames bundle's trunk detector (and EB-LiDAR's frame window)
        m["front_end"] = ctx["front_end"]
    if dr is None:
        dr = dead_reckoning(problem)
    gps_map = None
    truth_xy = None
    if ctx["kind"] == "victoria-park":
        vp = ctx["vp"]
        # poses and distances only: the covariance of every control segment would be the
        # command's largest allocation on a long drive (9 doubles x 4 arrays per segment)
        pre = preintegrate(vp.model, vp.controls, vp.gps_times, with_covariance=False)
        sp = sensor_poses(pre.poses, vp.model.sensor_offset)
        scr = screen_gps(
            vp.gps_times, vp.gps_xy, sp[:, :2], np.concatenate(([0.0], np.cumsum(pre.distance)))
        )
        off = vp.model.sensor_offset
        r = ate(result.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep)
        rd = ate(dr, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep)
        if problem.gnss is not None:  # map in the GPS frame: also scored as it is
            m.update(ate(result.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep,
                         align=False).as_dict("ate_unaligned_"))  # fmt: skip
        m["gps_fixes_kept"] = scr.n_kept
        m["gps_fixes_total"] = scr.n_total
        m["gps_screening"] = scr.rule
        if r:
            m.update(r.as_dict("ate_"))
            al = r.alignment
            assert al is not None
            ctx["alignment"] = al
            # GPS into the map frame (inverse of the map->GPS alignment) for the figure
            g = vp.gps_xy[scr.keep] - np.asarray(al.t)
            gps_map = g @ al.rotation
        else:
            m["ate_error"] = r.reason
        if rd:
            m.update(rd.as_dict("dead_reckoning_ate_"))
    elif ctx["kind"] == "sim":
        from stemmap.eval.maps import map_metrics

        run = ctx["run"]
        truth = run.vehicle_poses
        err = np.hypot(*(result.trajectory.interpolate(truth.times)[:, :2] - truth.xy).T)
        m["trajectory_rmse_m"] = float(np.sqrt(np.mean(err**2)))
        m["trajectory_max_m"] = float(err.max())
        r_rel = rpe(result.trajectory, truth, delta=RPE_DELTA_M)  # full poses: evo's RPE
        m.update(r_rel.as_dict("rpe_") if r_rel else {"rpe_error": r_rel.reason})
        true_disp = truth.xy[-1] - truth.xy[0]
        th0 = float(truth.poses[0, 2])
        c, s = math.cos(th0), math.sin(th0)
        body = (c * true_disp[0] + s * true_disp[1], -s * true_disp[0] + c * true_disp[1])
        m["loop_closure_error_m"] = loop_closure_error(result.trajectory, body)
        m["dead_reckoning_loop_closure_error_m"] = loop_closure_error(dr, body)
        truth_xy = run.stand.trees_xy
        mm = map_metrics(result.stem_map, None, truth_xy, run.stand.diameters, gate=1.0)
        m["map"] = mm.to_dict()
        m["scenario"] = ctx["params"]
    return m, gps_map, truth_xy


def summary_rows(m: dict[str, Any], stem_map: Any) -> list[tuple[str, str, str]]:
    """The terminal summary of a map run: (quantity, value, metrics.json key)."""
    rows = [
        ("trees mapped", fmt(m.get("n_trees")), "n_trees"),
        ("tree pairs closer than 1 m", fmt(m.get("duplicates_1m")), "duplicates_1m"),
    ]
    if "ate_rmse_m" in m:
        rows.append(("path error vs GPS (ATE RMSE)", fmt(m["ate_rmse_m"], " m"), "ate_rmse_m"))
        dr = m.get("dead_reckoning_ate_rmse_m")
        rows.append(("dead reckoning ATE RMSE", fmt(dr, " m"), "dead_reckoning_ate_rmse_m"))
    if "trajectory_rmse_m" in m:
        rows.append(("path RMSE vs truth", fmt(m["trajectory_rmse_m"], " m"), "trajectory_rmse_m"))
        lc = m.get("loop_closure_error_m")
        rows.append(("loop-closure error", fmt(lc, " m"), "loop_closure_error_m"))
    if "rpe_trans_rmse_m" in m:
        per = f"per {m['rpe_delta']:g} {m['rpe_delta_unit']}"
        rows.append((f"RPE translation RMSE ({per})", fmt(m["rpe_trans_rmse_m"], " m"),
                     "rpe_trans_rmse_m"))  # fmt: skip
        rows.append((f"RPE rotation RMSE ({per})", fmt(m["rpe_rot_rmse_deg"], " deg"),
                     "rpe_rot_rmse_deg"))  # fmt: skip
    ft = m.get("false_trees")
    if isinstance(ft, dict) and "method" in ft:  # forestrix: Öhman's ray-cast removal
        if ft.get("ran"):
            rows.append(("false trees removed (ray casting)", fmt(ft.get("removed")),
                         "false_trees.removed"))  # fmt: skip
        else:
            rows.append(("false-tree removal", f"skipped: {ft.get('reason')}", "false_trees"))
    rl = m.get("relocalisation")
    if isinstance(rl, dict) and "prior" in rl:
        rows.append(("prior map trees held by", f"{rl['prior']} prior", "relocalisation.prior"))
    mm = m.get("map")
    if isinstance(mm, dict):
        rows.append(("map recall (matched / all true trees)", fmt(mm.get("recall")), "map.recall"))
        rows.append(("map precision", fmt(mm.get("precision")), "map.precision"))
        pr = mm.get("position_rmse")
        rows.append(("tree position RMSE", fmt(pr, " cm", 100, 1), "map.position_rmse"))
        dr_ = mm.get("diameter_rmse")
        rows.append(("DBH RMSE", fmt(dr_, " cm", 100, 2), "map.diameter_rmse"))
    if len(stem_map):
        import numpy as np

        ds = np.array([t.diameter_std for t in stem_map])
        conf = np.array([t.confidence for t in stem_map])
        med = float(np.nanmedian(ds)) if np.isfinite(ds).any() else math.nan
        rows.append(("median DBH standard error", fmt(med, " cm", 100, 2), "trees.csv"))
        rows.append(("trees with confidence >= 0.5", fmt(int(np.sum(conf >= 0.5))), "trees.csv"))
    return rows


def headline(m: dict[str, Any]) -> str:
    """One line of the run's key numbers (figure titles, the terminal summary)."""
    parts = [f"{m.get('n_trees', 0)} trees"]
    mm = m.get("map")
    if isinstance(mm, dict):
        parts.append(f"recall {mm.get('recall', math.nan):.2f}")
        parts.append(f"precision {mm.get('precision', math.nan):.2f}")
    if "ate_rmse_m" in m:
        parts.append(f"ATE RMSE {m['ate_rmse_m']:.2f} m vs GPS")
    if "trajectory_rmse_m" in m:
        parts.append(f"path RMSE {m['trajectory_rmse_m']:.2f} m")
    return ", ".join(parts)


def frames_metadata(problem: Any, crs: str | None) -> dict[str, Any]:
    """What the map and trajectory coordinates mean (recorded in metrics.json)."""
    a, b = problem.sensor_offset
    return {
        "map_frame": "the frame of the initial pose (x, y metres; odometry frame, the "
        "simulator's world frame for --sim and demo)",
        "crs": crs,
        "georeferenced": crs is not None,
        "trajectory_point": "the vehicle reference point of the motion model (Victoria Park: "
        "the rear-axle centre), sensor_offset_m behind the laser",
        "sensor_offset_m": [a, b],
        "sensor_offset_meaning": f"the laser is {a} m ahead and {b} m left of the trajectory "
        "point, in the vehicle frame",
    }


def map_command(
    logs: Annotated[
        list[Path] | None,
        typer.Argument(
            metavar="INPUT",
            help="ROS1/ROS2 bag with LaserScan (+ Odometry, + Image/CameraInfo); scans (.npz / "
            ".csv, e.g. from `stemmap sim scans`) or a detections CSV (`stemmap detect`); or a "
            "frames bundle (.npz of 3D lidar and / or RGB-D frames, e.g. from `stemmap sim "
            "munjer`) with --frontend. Motion: see --motion. "
            "Several logs (files, a folder, a glob, a .txt list): one Dask task per log, "
            "OUT/LOG/ each, OUT/summary.csv.",
        ),
    ] = None,
    motion: Annotated[
        Motion | None,
        typer.Option(
            "--motion",
            help="Motion source of a log: wheel (--odometry FILE, the NAME_odometry.csv beside "
            "a scan file, or a bag's Odometry topic); lidar (KISS-ICP on the log's own scans or "
            "frames, + --imu); visual (stereo / RGB-D visual odometry of --camera); fused (the "
            "visual-lidar EKF of the two, + --imu). Recorded with its drift estimate in "
            "metrics.json 'motion' [default: wheel].",
        ),
    ] = None,
    odometry: Annotated[
        Path | None,
        typer.Option(
            help="--motion wheel: wheel odometry CSV time_s,speed,yaw_rate (s, m/s, rad/s) "
            "[default: INPUT's NAME_odometry.csv, as `stemmap sim scans` writes]; frames "
            "bundle: that, or a pose CSV time_s,x,y,theta (`stemmap odometry --out`). "
            "('--odometry lidar' is the deprecated spelling of --motion lidar.)",
        ),
    ] = None,
    imu: Annotated[
        Path | None,
        typer.Option(
            "--imu",
            help="--motion lidar|fused: IMU + wheel-speed CSV or bag fused with the lidar "
            "odometry (as `stemmap odometry --imu`).",
        ),
    ] = None,
    camera: Annotated[
        Path | None,
        typer.Option(
            "--camera",
            help="--motion visual|fused: camera frames folder (left/ + right/ or rgb/ + depth/, "
            "camera.json), a bag with Image + CameraInfo topics, or the trajectory CSV of "
            "`stemmap odometry --camera` [default: INPUT when it is a bag with Image topics].",
        ),
    ] = None,
    dataset: Annotated[
        Dataset | None, typer.Option("--dataset", help="A known public dataset.")
    ] = None,
    data: Annotated[
        Path | None, typer.Option("--data", help="Dataset folder (default: shared datasets).")
    ] = None,
    sim: Annotated[bool, typer.Option("--sim", help="Simulate a loop through a stand.")] = False,
    backend: Annotated[
        Backend | None,
        typer.Option(
            "--backend",
            help="SLAM back-end [default: isam2; fastslam (100 particles) + Kalman refinement "
            "of the trees for a frames bundle, Munjer 2025].",
        ),
    ] = None,
    frontend: Annotated[
        Frontend | None,
        typer.Option(
            "--frontend",
            help="Frames bundle: trunk detector per frame: eb-lidar (Munjer's EB-LiDAR on the "
            "lidar frames), daim (detector boxes + aligned depth), ours (stemmap's cloud "
            "detector on the lidar frames) [default: eb-lidar].",
        ),
    ] = None,
    eb_window: Annotated[
        int,
        typer.Option(
            "--eb-window",
            metavar="N",
            help="--frontend eb-lidar: cluster each lidar frame with the N - 1 frames before it, "
            "moved with the motion source's poses. Default 1 = strictly per frame, the paper's "
            "pipeline; N > 1 adds the joined cloud's trunks (20 points from one frame) to each "
            "frame's own: more trees on the simulator and on a real plot, no false ones there "
            "(docs/algorithms/cloud.md, 'Accumulated frames').",
            callback=bounded("--eb-window", ge=1),
        ),
    ] = 1,
    model: Annotated[
        Path | None,
        typer.Option(
            "--model",
            help="--frontend daim: ONNX trunk detector (default: the segmentation detector).",
        ),
    ] = None,
    motion_sigma: Annotated[
        str | None,
        typer.Option(
            "--motion-sigma",
            help="The motion source's error 'speed,yaw_rate' (m/s, rad/s, one-second averages) "
            "= the back-end's motion noise [default: 0.05,0.002 for a frames bundle, else "
            "0.05,0.01].",
        ),
    ] = None,
    refine: Annotated[
        bool,
        typer.Option(
            "--refine/--no-refine",
            help="Frames bundle with fastslam: per-tree Kalman refinement (Munjer §3.6).",
        ),
    ] = True,
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path(
        "stemmap_map"
    ),
    t_end: Annotated[
        float | None,
        typer.Option(
            "--t-end",
            help="Use the dataset only up to this time (s).",
            callback=bounded("--t-end", gt=0),
        ),
    ] = None,
    t_start: Annotated[
        float, typer.Option("--t-start", help="Use the dataset from this time (s).")
    ] = 0.0,
    seed: Annotated[
        int, typer.Option("--seed", help="Simulation seed.", callback=bounded("--seed", ge=0))
    ] = 1,
    sim_trees: Annotated[
        int,
        typer.Option(
            "--sim-trees", help="Trees in the stand.", callback=bounded("--sim-trees", ge=1)
        ),
    ] = 150,
    sim_size: Annotated[
        float,
        typer.Option(
            "--sim-size",
            help="Stand side (m), > 4 (the loop keeps 15 % of the side from the edge).",
            callback=bounded("--sim-size", gt=4),
        ),
    ] = 60.0,
    sensor_offset: Annotated[
        str, typer.Option("--sensor-offset", help="Bag: laser position 'a,b' (m) in the vehicle.")
    ] = "0,0",
    gnss: Annotated[
        Path | None,
        typer.Option("--gnss", help="GNSS fixes CSV 'time_s,x,y[,sigma]' (metric frame); isam2."),
    ] = None,
    gnss_lever: Annotated[
        str | None,
        typer.Option(
            "--gnss-lever",
            help="Antenna position 'x,y' (m) in the vehicle frame (default: the laser point "
            "for victoria-park, else 0,0).",
        ),
    ] = None,
    gnss_sigma: Annotated[
        float, typer.Option("--gnss-sigma", help="Fix sigma (m) where the CSV has none.")
    ] = 1.0,
    prior_map: Annotated[
        Path | None,
        typer.Option(
            "--prior-map",
            help="Map folder of an earlier session (its trees.csv): "
            "relocalise in it, map on, write the merged map; isam2.",
        ),
    ] = None,
    start_guess: Annotated[
        str | None,
        typer.Option(
            "--start-guess",
            help="With --prior-map: rough start 'x,y,heading_deg' in "
            "the map (searched within 30 m / 45 deg); default: global search.",
        ),
    ] = None,
    realtime: Annotated[
        bool,
        typer.Option(
            "--realtime",
            help="Replay the log scan by scan through the online mapper "
            "(OnlineMapper) and report per-scan latency; isam2.",
        ),
    ] = False,
    rerun: Annotated[
        Path | None,
        typer.Option(
            "--rerun",
            help="Write a Rerun recording (.rrd) of the run; implies --realtime (needs rerun-sdk).",
        ),
    ] = None,
    show_progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
    as_json: JsonFlag = False,
    crs: CrsOption = None,
    gpkg: GpkgFlag = False,
    trajectory_format: Annotated[
        TrajectoryFormat,
        typer.Option(
            help="trajectory.csv (time_s,x,y,theta + pose covariance columns where the back-end "
            "has them: fastslam, ekf, isam2) or TUM trajectory.tum for evo (no covariances)."
        ),
    ] = TrajectoryFormat.csv,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
) -> None:
    """Map trees and the machine's path with tree-landmark SLAM.

    Writes to --out: trees.csv, trees.geojson, trajectory.csv (--trajectory-format tum:
    trajectory.tum), metrics.json, map.png, report.html, and with --gpkg map.gpkg; Victoria
    Park also gps_trees.csv, gps_trees.geojson, gps_trajectory.csv and gps_alignment.json
    (the map in the GPS frame). Every column: docs/outputs.md.

    Example: stemmap map --dataset victoria-park --out vp

    Example: stemmap sim scans --out run.npz && stemmap map run.npz --out runmap

    Example: stemmap map drive.bag --sensor-offset 0.5,0 --crs EPSG:32633 --gpkg --out bagmap

    Example: stemmap map logs/ --workers 2 --out maps  (maps/LOG/ per log, maps/summary.csv)

    Example: stemmap sim munjer --out drive.npz && stemmap map drive.npz --frontend daim --out m

    Example: stemmap map drive.npz --motion lidar --imu drive_imu.csv --out m  (ICP + IMU EKF)

    Example: stemmap map run.npz --motion fused --camera frames/ --out m  (visual-lidar EKF)

    Example: stemmap map drive.bag --motion lidar --out m  (2D scan matching, no wheel odometry)
    """
    if wants_logs(logs, workers, scheduler):
        return run_many_logs("map", dict(locals()), as_json=as_json)
    bag = logs[0] if logs else None
    from stemmap.cli._map_frames import frames_problem
    from stemmap.cli._map_inputs import bag_problem, file_problem
    from stemmap.io.atomic import atomic_write
    from stemmap.io.frames import is_frames_npz
    from stemmap.io.products import run_products
    from stemmap.io.rosbag import is_bag
    from stemmap.slam.base import dead_reckoning, make_backend
    from stemmap.slam.uncertainty import annotate_uncertainty
    from stemmap.viz.maps import save_stem_map_png

    with fail_on_stemmap_error():
        motion_src, odometry = resolve_motion(motion, odometry, camera=camera, imu=imu)
        sigma = _motion_sigma(motion_sigma)
    inputs = [bag, odometry, imu, camera] if dataset is None else _vp_inputs(data)
    with fail_on_stemmap_error(), run_products("map", inputs=inputs, out_dir=out_dir) as run:
        crs = checked_crs(crs)
        sources = int(bag is not None) + int(dataset is not None) + int(sim)
        if sources != 1:
            raise ConfigError(
                "give exactly one input: a bag, scans or detections file, --dataset "
                "victoria-park, or --sim."
            )
        is_frames = bag is not None and is_frames_npz(bag)
        if frontend is not None and not is_frames:
            raise ConfigError("--frontend needs a frames bundle (.npz with lidar or RGB-D frames).")
        if eb_window != 1 and not is_frames:
            raise ConfigError("--eb-window needs a frames bundle (.npz with lidar frames).")
        if bag is None and (motion_src != Motion.wheel or motion_sigma is not None):
            raise ConfigError(
                "--motion and --motion-sigma are for a log input (bag, scans, frames)."
            )
        backend = backend or (Backend.fastslam if is_frames else Backend.isam2)
        announce_compile("slam") if dataset is not None else announce_compile("scan", "slam")
        motion_run = None
        if bag is not None and motion_src != Motion.wheel:
            motion_run = motion_trajectory(
                bag, motion_src, camera=camera, imu=imu, quiet=not show_progress
            )
        if is_frames:
            assert bag is not None
            sv, sw = sigma or (0.05, 0.002)
            problem, ctx = frames_problem(
                bag,
                odometry,
                frontend or Frontend.eb_lidar,
                model=model,
                sigma_speed=sv,
                sigma_yaw_rate=sw,
                motion=motion_run,
                eb_window=eb_window,
            )
        elif dataset is not None:
            problem, ctx = _victoria_park(data, t_end, t_start)
        elif sim:
            problem, ctx = _simulated(seed, sim_trees, sim_size)
        else:
            assert bag is not None
            if odometry is not None and is_bag(bag):
                raise ConfigError("--odometry is for scan / detection files; a bag has its own.")
            try:
                a_str, b_str = sensor_offset.split(",")
                off = (float(a_str), float(b_str))
            except ValueError as exc:
                raise ConfigError(
                    f"--sensor-offset must be 'a,b' in metres, got {sensor_offset!r}."
                ) from exc
            vpath = None
            if motion_run is not None:  # the lidar's path -> the vehicle reference point's
                src = motion_run[1]["source"]
                vpath = motion_run[0] if src == "visual" else vehicle_path(motion_run[0], off)
            if is_bag(bag):
                problem, ctx = bag_problem(bag, off, motion=vpath, motion_sigma=sigma)
            else:
                problem, ctx = file_problem(bag, odometry, off, motion=vpath, motion_sigma=sigma)
        if gnss is not None:
            problem = _with_gnss(problem, gnss, gnss_lever, gnss_sigma, backend.value)
        reloc = None
        isam2 = backend == Backend.isam2 and not (realtime or rerun is not None)
        if prior_map is not None:
            problem, reloc, prior_note = continue_from_map(
                problem, prior_map, start_guess, backend.value
            )
        # isam2 keeps the trees' joint information (trees_information.npz, for --prior-map)
        be = make_backend(backend.value, **({"joint_information": True} if isam2 else {}))
        with progress(show_progress) as bar:
            task = bar.add_task(f"{backend.value} SLAM", total=len(problem.frames))

            def tick(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            if realtime or rerun is not None:
                result = _realtime(problem, backend.value, tick, rerun)
            elif is_frames and backend == Backend.fastslam:
                from stemmap.slam.munjer import MunjerMapConfig, map_munjer

                result = map_munjer(problem, MunjerMapConfig(refine=refine, seed=seed))
                tick(len(problem.frames), len(problem.frames))
            elif backend == Backend.forestrix:  # raw scans: Öhman's ray-cast false trees
                result = be.run(problem, progress=tick, scans=ctx.get("scans"))  # type: ignore[call-arg]
            else:
                result = be.run(problem, progress=tick)
        result.stem_map, unc = annotate_uncertainty(result, problem)
        dr = dead_reckoning(problem)  # once, for the metrics and the figure
        metrics, gps_map, truth_xy = slam_metrics(problem, result, ctx, dr)
        if reloc is not None:
            metrics["relocalisation"] = {**reloc.__dict__, **prior_note}
        metrics["false_trees"] = false_trees_report(backend.value, result.stats, ctx["kind"])
        metrics["uncertainty"] = unc.to_dict()
        metrics["frames"] = frames_metadata(problem, crs)
        if bag is not None:
            metrics["motion"] = (
                motion_run[1]
                if motion_run is not None
                else {"source": "wheel", **wheel_drift_estimate(problem.controls, problem.motion)}
            )
            metrics["motion"]["sigma_speed"] = problem.motion.sigma_speed
            metrics["motion"]["sigma_yaw_rate"] = problem.motion.sigma_steer
            run.note(motion=metrics["motion"])
        run.note(frames=metrics["frames"])  # the body point and CRS travel with the manifest
        stage = run.dir
        if (
            "odometry" in ctx
            and isinstance(ctx["odometry"], str)
            and Path(ctx["odometry"]).is_file()
        ):
            run.add_input(ctx["odometry"])
        fmt = trajectory_format.value
        names = write_map_products(
            stage,
            result.stem_map,
            result.trajectory,
            crs=crs,
            gpkg=gpkg,
            trajectory_format=fmt,
            pose_covs=result.pose_covs,
        )
        names += write_information(stage, result.stem_map)
        if "alignment" in ctx:
            names += write_gps_frame(
                stage,
                ctx["alignment"],
                result.stem_map,
                result.trajectory,
                sensor_offset=problem.sensor_offset,
                gpkg=gpkg,
                trajectory_format=fmt,
                pose_covs=result.pose_covs,
            )
        names += ["metrics.json", "map.png"]
        with atomic_write(stage / "metrics.json") as fh:
            json.dump(clean_json(metrics), fh, indent=1, default=json_default, allow_nan=False)
        save_stem_map_png(
            stage / "map.png",
            result.stem_map,
            result.trajectory,
            gps_xy=gps_map,
            reference=dr,
            truth_xy=truth_xy,
            title=f"{problem.name}: {backend.value}\n{headline(metrics)}",
        )
        names.append(
            write_run_report(
                stage,
                title=f"stemmap map: {problem.name} ({backend.value})",
                headline=headline(metrics),
                metrics=metrics,
                figure="map.png",
                stem_map=result.stem_map,
                parameters={"backend": backend.value, "input": problem.name, "crs": crs,
                            "sensor_offset_m": list(problem.sensor_offset), "t_end": t_end},
                files=names,
                crs=crs,
            )
        )  # fmt: skip
    print_summary(
        f"stemmap map: {problem.name} ({backend.value})",
        summary_rows(metrics, result.stem_map),
        out_dir,
        [*names, "run.json"],
        as_json=as_json,
        payload={"metrics": metrics},
    )


def register(app: typer.Typer) -> None:
    """Add ``stemmap map`` to the CLI."""
    app.command("map")(map_command)
