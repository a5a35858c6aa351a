"""``stemmap map``: tree-landmark SLAM on a dataset, a simulated run or a ROS bag.

Writes to ``--out DIR``: ``trees.csv`` (id,x,y,diameter,std_x,std_y,n_obs,...),
``trees.geojson``, ``trajectory.csv`` (time_s,x,y,theta and, where the back-end reports them,
the pose covariance columns), ``metrics.json`` and ``map.png``; with ``--gnss`` also the
GNSS-frame track (:mod:`stemmap.cli._map_gnss`).
"""

from __future__ import annotations

import json
import logging
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from stemmap._memory import TRIM_INTERVAL_S as _TRIM_S
from stemmap._memory import HeapTrimmer
from stemmap.cli._common import (
    ProgressFlag,
    QuietFlag,
    clean_json,
    console,
    fail_on_stemmap_error,
    json_default,
    progress,
)
from stemmap.cli._geo import (
    CrsOption,
    GpkgFlag,
    checked_crs,
    write_gps_frame,
    write_map_products,
)
from stemmap.cli._map_frames import Frontend
from stemmap.cli._map_gnss import gnss_track, gnss_track_layers, write_gnss_track
from stemmap.cli._map_motion import (
    Motion,
    motion_trajectory,
    resolve_motion,
    vehicle_path,
    wheel_drift_estimate,
)
from stemmap.cli._map_prior import (
    PriorType,
    check_gnss_frame,
    continue_from_map,
    false_trees_report,
    gnss_start_check,
    prior_map_frame,
    read_prior_map,
    session_graph_report,
    write_information,
)
from stemmap.cli._map_problems import check_gnss, sim_problem
from stemmap.cli._map_problems import motion_sigma as _motion_sigma
from stemmap.cli._map_problems import realtime as _realtime
from stemmap.cli._map_problems import simulated as _simulated
from stemmap.cli._map_problems import victoria_park as _victoria_park
from stemmap.cli._map_problems import vp_inputs as _vp_inputs
from stemmap.cli._map_problems import wheel_systematic as _wheel_systematic
from stemmap.cli._map_problems import with_gnss as _with_gnss
from stemmap.cli._map_report import frames_metadata, headline, slam_metrics, summary_rows
from stemmap.cli._multilog import SchedulerOption, WorkersOption, run_many_logs, wants_logs
from stemmap.cli._summary import (
    JsonFlag,
    compile_notice,
    print_summary,
    write_run_report,
)
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError

__all__ = ["register", "sim_problem", "slam_metrics"]

log = logging.getLogger(__name__)

#: least CPU seconds between two heap trims during SLAM (``malloc_trim(0)``, glibc only)
TRIM_INTERVAL_S = _TRIM_S


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
            "odometry (as `stemmap odometry --imu`); its gyro also checks that the scans turn "
            "its way (a warning for mirrored scans or a z-down gyro).",
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
        Path | None,
        typer.Option(
            "--data",
            help="Folder of the dataset's files (victoria-park: inputs.dat, measurements.dat, "
            "gps.dat) [default: $STEMMAP_DATASETS/victoria_park, else shared/datasets/"
            "victoria_park in the working folder or one of its parents].",
        ),
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
    wheel_systematic: Annotated[
        str | None,
        typer.Option(
            "--wheel-systematic",
            help="--motion wheel: the odometry's 1-sigma speed scale error and yaw-rate bias "
            "'scale,yaw_rate_bias' (fraction, rad/s; 0 leaves a term out) in the drift "
            "estimate of metrics.json motion (a report only) [default: 0.005,0.003, measured on "
            "Victoria Park].",
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
        typer.Option(
            "--gnss",
            help="GNSS fixes CSV 'time_s,x,y[,sigma]' (metric frame); isam2. Fused as robust "
            "priors: trajectory.csv is then the tree-consistent path in the GNSS frame (use it "
            "with the map); also writes trajectory_gnss.csv, the path as the receiver would "
            "read it (follows its correlated error; use it to drive to GNSS waypoints).",
        ),
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
            help="Map folder of an earlier session (trees.csv [+ graph.npz]): "
            "relocalise in it, map on (continuing its graph.npz when present), write the "
            "merged map, in the map's frame; isam2. With --gnss the map must have been made "
            "in the fixes' frame (with --gnss, same --crs), else an error.",
        ),
    ] = None,
    prior_type: Annotated[
        PriorType | None,
        typer.Option(
            "--prior-type",
            help="With --prior-map: how it enters the graph -- huber (default) or cauchy "
            "(each tree's own robust prior on its marginal), joint (one prior over all trees "
            "from trees_information.npz), graph (the earlier session's graph.npz continued: "
            "its poses and trees stay variables; Victoria Park, 5 session splits 400-1200 s: "
            "session 2 ATE 1.282 / 1.367 / 1.446 / 1.448 / 0.855 m vs huber's 1.256 / 1.306 / "
            "1.444 / 1.441 / 0.834 m, per-keyframe CPU p99 17-33 vs 7-11 ms).",
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
    show_progress: ProgressFlag = True,
    quiet: QuietFlag = False,
    as_json: JsonFlag = False,
    crs: CrsOption = None,
    gpkg: GpkgFlag = False,
    trajectory_format: Annotated[
        TrajectoryFormat,
        typer.Option(
            help="trajectory.csv (time_s,x,y,theta in s, m, m, rad + the pose covariance "
            "columns, which every back-end writes: docs/outputs.md) or TUM trajectory.tum for "
            "evo (no covariances)."
        ),
    ] = TrajectoryFormat.csv,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
) -> None:
    """Map trees and the machine's path with tree-landmark SLAM.

    Writes to --out: trees.csv, trees.geojson, trajectory.csv (--trajectory-format tum:
    trajectory.tum), metrics.json, map.png, report.html, run.json, with isam2 graph.npz and
    trees_information.npz (what a later --prior-map reads), and with --gpkg map.gpkg; Victoria
    Park also gps_trees.csv, gps_trees.geojson, gps_trajectory.csv and gps_alignment.json
    (the map in the GPS frame). With --gnss also trajectory_gnss.csv (or .tum; with --crs
    trajectory_gnss.geojson; in map.gpkg layers trajectory_gnss, poses_gnss): the path as the
    GNSS receiver reads it, its error model estimated from the run's own fixes (metrics.json
    gnss_track). Every column: docs/outputs.md.

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
    show_progress = show_progress and not quiet
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
        systematic = _wheel_systematic(wheel_systematic)
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
        if systematic is not None and (bag is None or motion_src != Motion.wheel):
            raise ConfigError(
                "--wheel-systematic is for the wheel odometry of a log input (--motion wheel)."
            )
        backend = backend or (Backend.fastslam if is_frames else Backend.isam2)
        areas = () if dataset is not None else ("scan",)
        # said right before the first kernel call, once the inputs are read and checked
        notice = compile_notice(*areas, backend=backend.value, quiet=quiet)
        if gnss is not None:
            check_gnss(gnss, gnss_lever, gnss_sigma, backend.value)
        # the prior map is read and checked with the other inputs, before any slow work
        loaded_prior = None
        if prior_map is not None:
            if gnss is not None:  # with --gnss the map must be in the fixes' frame
                check_gnss_frame(prior_map, crs)
            loaded_prior = read_prior_map(prior_map, start_guess, backend.value, prior_type)
        elif prior_type is not None:
            raise ConfigError("--prior-type needs --prior-map.")
        off = (0.0, 0.0)
        if bag is not None and not is_frames:
            try:
                a_str, b_str = sensor_offset.split(",")
                off = (float(a_str), float(b_str))
            except ValueError as exc:
                raise ConfigError(
                    f"--sensor-offset must be 'a,b' in metres, got {sensor_offset!r}."
                ) from exc
            if odometry is not None and is_bag(bag):
                raise ConfigError("--odometry is for scan / detection files; a bag has its own.")
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
                before_compute=notice,
            )
        elif dataset is not None:
            problem, ctx = _victoria_park(data, t_end, t_start)
            notice()
        elif sim:
            notice()
            online = realtime or rerun is not None  # the realtime mapper does not calibrate
            problem, ctx = _simulated(
                seed, sim_trees, sim_size, backend="online" if online else backend.value
            )
        else:
            assert bag is not None
            vpath = None
            if motion_run is not None:  # the lidar's path -> the vehicle reference point's
                src = motion_run[1]["source"]
                vpath = motion_run[0] if src == "visual" else vehicle_path(motion_run[0], off)
            if is_bag(bag):
                problem, ctx = bag_problem(
                    bag, off, motion=vpath, motion_sigma=sigma, before_compute=notice
                )
            else:
                problem, ctx = file_problem(
                    bag, odometry, off, motion=vpath, motion_sigma=sigma, before_compute=notice
                )
            if vpath is None:  # a wheel odometry: do the scans turn the way it turns?
                from stemmap.cli._map_handedness import mirror_warning

                mirrored = mirror_warning(problem, ctx.get("scans"))
                if mirrored is not None:
                    console.print(f"[yellow]warning:[/yellow] {mirrored}")
        if gnss is not None:
            problem = _with_gnss(problem, gnss, gnss_lever, gnss_sigma, backend.value)
        reloc = None
        isam2 = backend == Backend.isam2 and not (realtime or rerun is not None)
        be_cfg: dict[str, object] = (
            {"joint_information": True, "export_graph": True} if isam2 else {}
        )
        gnss_frame = problem.gnss is not None
        if prior_map is not None and loaded_prior is not None:
            # the prior map's frame rules: with --gnss it is the fixes' frame (checked above)
            if problem.gnss is None:
                gnss_frame = bool(prior_map_frame(prior_map)["gnss_frame"])
            problem, reloc, prior_note = continue_from_map(problem, loaded_prior)
            if problem.gnss is not None:
                prior_note.update(gnss_start_check(problem))
            if prior_type is not None:
                be_cfg["prior_map_robust"] = prior_type.robust
        # isam2 keeps the trees' joint information (trees_information.npz, for --prior-map)
        be = make_backend(backend.value, **be_cfg)
        with progress(show_progress) as bar:
            task = bar.add_task(f"{backend.value} SLAM", total=len(problem.frames))
            # freed heap back to the OS during long runs, at most every 0.2 s of CPU time
            # (glibc; no-op elsewhere): RSS then follows the heap in use (docs/reliability.md,
            # "Soak", "The RSS staircase is the allocator")
            trim = HeapTrimmer(TRIM_INTERVAL_S)

            def tick(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)
                trim()

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
        metrics["session_graph"] = session_graph_report(
            backend.value, realtime or rerun is not None, result.graph
        )
        metrics["uncertainty"] = unc.to_dict()
        metrics["frames"] = frames_metadata(problem, crs, gnss_frame=gnss_frame)
        if bag is not None:
            metrics["motion"] = (
                motion_run[1]
                if motion_run is not None
                else {
                    "source": "wheel",
                    **wheel_drift_estimate(
                        problem.controls,
                        problem.motion,
                        sigma_scale=None if systematic is None else systematic[0],
                        sigma_bias=None if systematic is None else systematic[1],
                    ),
                }
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
        track = None
        if problem.gnss is not None:  # the path as the receiver reads it (cli/_map_gnss.py)
            track, metrics["gnss_track"] = gnss_track(problem, result)
        names = write_map_products(
            stage,
            result.stem_map,
            result.trajectory,
            crs=crs,
            gpkg=gpkg,
            trajectory_format=fmt,
            pose_covs=result.pose_covs,
            gpkg_layers=gnss_track_layers(track) if track is not None else (),
        )
        if track is not None:
            names += write_gnss_track(
                stage, track, crs=crs, frame=result.stem_map.frame, trajectory_format=fmt
            )
        names += write_information(stage, result.stem_map, result.graph)
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
        quiet=quiet,
    )


def register(app: typer.Typer) -> None:
    """Add ``stemmap map`` to the CLI."""
    app.command("map")(map_command)
