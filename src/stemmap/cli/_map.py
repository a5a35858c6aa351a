"""``stemmap map``: tree-landmark SLAM on a dataset, a simulated run or a ROS bag.

Writes to ``--out DIR``: ``trees.csv`` (id,x,y,diameter,std_x,std_y,n_obs,...),
``trees.geojson``, ``trajectory.csv`` (time,x,y,theta), ``metrics.json`` and ``map.png``.
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

from stemmap.cli._common import clean_json, fail_on_stemmap_error, json_default, out, progress
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError, InputError

__all__ = ["register", "sim_problem", "slam_metrics"]

log = logging.getLogger(__name__)


class Backend(StrEnum):
    treedb = "treedb"
    ekf = "ekf"
    fastslam = "fastslam"
    forestrix = "forestrix"
    isam2 = "isam2"


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


def _victoria_park(data: Path | None, t_end: float | None) -> tuple[Any, dict[str, Any]]:
    from stemmap.datasets.victoria_park import load_victoria_park

    vp = load_victoria_park(data)
    if t_end is not None:
        vp = vp.slice(0.0, t_end)
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
    return problem, {"kind": "sim", "run": run, "params": run.params}


def _bag(path: Path, sensor_offset: tuple[float, float]) -> tuple[Any, dict[str, Any]]:
    from stemmap.io.rosbag import iter_laser_scans, read_odometry
    from stemmap.scan.detect import ScanTrunkDetector
    from stemmap.slam.base import Controls, SlamProblem, TreeFrames
    from stemmap.slam.motion import UnicycleModel
    from stemmap.types import ScanBatch

    scans = list(iter_laser_scans(path))
    if not scans:
        raise InputError(f"bag {path} has no usable LaserScan messages.")
    batch = ScanBatch.from_scans(scans)
    odo = read_odometry(path)
    if len(odo) < 2:
        raise InputError(f"bag {path} has fewer than 2 Odometry messages; cannot dead-reckon.")
    obs = ScanTrunkDetector().detect_batch(batch)
    frames = TreeFrames.from_observations(obs, batch.times)
    keep = np.concatenate(([True], np.diff(odo.times) > 0))
    controls = Controls(odo.times[keep], odo.twists[keep, 0], odo.twists[keep, 2], "unicycle")
    p0 = odo.trajectory().interpolate([float(batch.times[0])])[0]
    problem = SlamProblem(
        controls,
        frames,
        UnicycleModel(),
        sensor_offset=sensor_offset,
        initial_pose=(float(p0[0]), float(p0[1]), float(p0[2])),
        name=str(path),
        max_range=float(batch.range_max),
    )
    return problem, {"kind": "bag", "odometry": odo}


def slam_metrics(problem: Any, result: Any, ctx: dict[str, Any]) -> tuple[dict[str, Any], Any, Any]:
    """Metrics for the run and (gps_xy_in_map, truth_xy) for the figure."""
    from stemmap.eval.trajectory import ate, loop_closure_error, screen_gps
    from stemmap.slam.base import dead_reckoning, duplicate_pairs, sensor_poses
    from stemmap.slam.motion import preintegrate

    m: dict[str, Any] = {
        "problem": problem.name,
        "backend_stats": result.stats,
        "n_trees": len(result.stem_map),
        "duplicates_1m": duplicate_pairs(result.stem_map, 1.0),
        "frames": len(problem.frames),
        "detections": problem.frames.n_detections,
    }
    dr = dead_reckoning(problem)
    gps_map = None
    truth_xy = None
    if ctx["kind"] == "victoria-park":
        vp = ctx["vp"]
        pre = preintegrate(vp.model, vp.controls, vp.gps_times)
        sp = sensor_poses(pre.poses, vp.model.sensor_offset)
        scr = screen_gps(
            vp.gps_times, vp.gps_xy, sp[:, :2], np.concatenate(([0.0], np.cumsum(pre.distance)))
        )
        off = vp.model.sensor_offset
        r = ate(result.trajectory, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep)
        rd = ate(dr, vp.gps_times, vp.gps_xy, offset=off, keep=scr.keep)
        m["gps_fixes_kept"] = scr.n_kept
        m["gps_fixes_total"] = scr.n_total
        m["gps_screening"] = scr.rule
        if r:
            m.update(r.as_dict("ate_"))
            al = r.alignment
            assert al is not None
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


def map_command(
    bag: Annotated[
        Path | None, typer.Argument(help="ROS1/ROS2 bag with LaserScan + Odometry.")
    ] = None,
    dataset: Annotated[
        Dataset | None, typer.Option("--dataset", help="A known public dataset.")
    ] = None,
    data: Annotated[
        Path | None, typer.Option("--data", help="Dataset folder (default: shared datasets).")
    ] = None,
    sim: Annotated[bool, typer.Option("--sim", help="Simulate a loop through a stand.")] = False,
    backend: Annotated[Backend, typer.Option("--backend", help="SLAM back-end.")] = (Backend.isam2),
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
    show_progress: Annotated[bool, typer.Option("--progress/--no-progress")] = True,
) -> None:
    """Map trees and the machine's path with tree-landmark SLAM."""
    from stemmap.io.atomic import atomic_write
    from stemmap.io.maps import write_trees_csv, write_trees_geojson
    from stemmap.io.products import run_products
    from stemmap.io.trajectory import write_trajectory_csv
    from stemmap.slam.base import dead_reckoning, make_backend
    from stemmap.viz.maps import save_stem_map_png

    inputs = [bag] if dataset is None else _vp_inputs(data)
    with fail_on_stemmap_error(), run_products("map", inputs=inputs, out_dir=out_dir) as run:
        sources = int(bag is not None) + int(dataset is not None) + int(sim)
        if sources != 1:
            raise ConfigError("give exactly one input: a BAG, --dataset victoria-park, or --sim.")
        if dataset is not None:
            problem, ctx = _victoria_park(data, t_end)
        elif sim:
            problem, ctx = _simulated(seed, sim_trees, sim_size)
        else:
            assert bag is not None
            try:
                a_str, b_str = sensor_offset.split(",")
                off = (float(a_str), float(b_str))
            except ValueError as exc:
                raise ConfigError(
                    f"--sensor-offset must be 'a,b' in metres, got {sensor_offset!r}."
                ) from exc
            problem, ctx = _bag(bag, off)
        be = make_backend(backend.value)
        with progress(show_progress) as bar:
            task = bar.add_task(f"{backend.value} SLAM", total=len(problem.frames))

            def tick(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            result = be.run(problem, progress=tick)
        metrics, gps_map, truth_xy = slam_metrics(problem, result, ctx)
        stage = run.dir
        write_trees_csv(stage / "trees.csv", result.stem_map)
        write_trees_geojson(stage / "trees.geojson", result.stem_map)
        write_trajectory_csv(stage / "trajectory.csv", result.trajectory)
        with atomic_write(stage / "metrics.json") as fh:
            json.dump(clean_json(metrics), fh, indent=1, default=json_default, allow_nan=False)
        save_stem_map_png(
            stage / "map.png",
            result.stem_map,
            result.trajectory,
            gps_xy=gps_map,
            reference=dead_reckoning(problem),
            truth_xy=truth_xy,
            title=f"{problem.name}: {backend.value}",
        )
    summary = {k: metrics[k] for k in metrics if k.startswith(("ate_", "n_trees", "dup", "loop"))}
    out.print(
        f"wrote {out_dir}/: trees.csv trees.geojson trajectory.csv metrics.json map.png run.json",
        markup=False,
        soft_wrap=True,
    )
    out.print(json.dumps(clean_json(summary), default=json_default))


def register(app: typer.Typer) -> None:
    """Add ``stemmap map`` to the CLI."""
    app.command("map")(map_command)
