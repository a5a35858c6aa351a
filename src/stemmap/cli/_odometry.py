"""``stemmap odometry``: lidar frames (+ IMU and wheel speed), or camera frames (``--camera``,
:mod:`stemmap.cli._odometry_camera`) -> a trajectory CSV / TUM file."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
import typer

from stemmap.cli._common import (
    QuietFlag,
    console,
    fail_on_stemmap_error,
    out,
    print_error,
    progress,
)
from stemmap.cli._validate import bounded

if TYPE_CHECKING:
    from collections.abc import Sequence

    from stemmap.odometry.fusion import OdometrySource

__all__ = ["lidar_front_end", "lidar_trajectory", "odometry", "register", "summary_lines"]

_TUM_SUFFIXES = (".tum", ".txt")


def odometry(
    frames: Annotated[
        Path | None,
        typer.Argument(
            help="Lidar frames: a folder of per-frame clouds (.pcd/.ply/.las/.laz/.xyz, timed by "
            "a times.csv sidecar, by file names in seconds, or by --rate), a 2D scan file "
            "(.npz/.csv), a frames bundle (.npz, `stemmap sim munjer`), or a ROS bag "
            "(PointCloud2 or LaserScan topic).",
            show_default=False,
        ),
    ] = None,
    out_path: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            help="Trajectory to write: .csv (time_s,x,y,theta) or .tum/.txt (TUM: t x y z qx qy "
            "qz qw); one pose per lidar frame.",
        ),
    ] = Path("odometry.csv"),
    imu: Annotated[
        Path | None,
        typer.Option(
            help="IMU + wheel-speed CSV (time_s,gyro_z[,wheel_speed,...]; docs/cli.md) or a ROS "
            "bag with a sensor_msgs/Imu topic (times in s, gyro_z in rad/s counter-clockwise: "
            "a warning when the scans turn against it). Without it: lidar-only odometry.",
        ),
    ] = None,
    topic: Annotated[
        str | None,
        typer.Option(help="Lidar topic of a bag (default: the only PointCloud2, else LaserScan)."),
    ] = None,
    imu_topic: Annotated[
        str | None, typer.Option(help="Imu topic of the --imu bag (default: the only one).")
    ] = None,
    odom_topic: Annotated[
        str | None,
        typer.Option(help="nav_msgs/Odometry topic of the --imu bag giving the wheel speed."),
    ] = None,
    rate: Annotated[
        float | None,
        typer.Option(
            help="Frame rate (Hz) of a folder whose files carry no time.",
            callback=bounded("--rate", gt=0),
        ),
    ] = None,
    max_range: Annotated[
        float,
        typer.Option(
            help="Drop points farther than this (m).", callback=bounded("--max-range", gt=0)
        ),
    ] = 100.0,
    min_range: Annotated[
        float,
        typer.Option(
            help="Drop points nearer than this (m).", callback=bounded("--min-range", ge=0)
        ),
    ] = 0.5,
    voxel: Annotated[
        float | None,
        typer.Option(
            help="KISS-ICP map voxel (m); default max_range / 100.",
            callback=bounded("--voxel", gt=0),
        ),
    ] = None,
    keep_ground: Annotated[
        bool,
        typer.Option(
            "--keep-ground",
            help="Register 3D frames with their ground points (default: removed, a level "
            "lidar's ground rings pin ICP to zero motion).",
        ),
    ] = False,
    camera: Annotated[
        Path | None,
        typer.Option(
            "--camera",
            help="Camera frames folder (left/ + right/ rectified stereo, or rgb/ + depth/, with "
            "camera.json intrinsics) or a ROS bag with Image + CameraInfo topics: visual "
            "odometry; with lidar FRAMES too, fused with the lidar odometry in the EKF (the "
            "visual-lidar coupling of `stemmap map --motion fused`; docs/cli.md).",
        ),
    ] = None,
    max_corners: Annotated[
        int | None, typer.Option(help="Camera: Shi-Tomasi corners per keyframe (default 400).")
    ] = None,
    left_topic: Annotated[
        str | None,
        typer.Option(help="Camera bag: left (or colour) Image topic; guessed if unique."),
    ] = None,
    right_topic: Annotated[str | None, typer.Option(help="Camera bag: right Image topic.")] = None,
    depth_topic: Annotated[
        str | None, typer.Option(help="Camera bag: depth Image topic (RGB-D instead of stereo).")
    ] = None,
    info_topic: Annotated[
        str | None, typer.Option(help="Camera bag: CameraInfo topic of the left camera.")
    ] = None,
    baseline: Annotated[
        float | None,
        typer.Option(help="Camera bag: stereo baseline, m (default: the right CameraInfo's P)."),
    ] = None,
    quiet: QuietFlag = False,
) -> None:
    """Odometry from lidar frames, fused with an IMU and wheel speed (Munjer 2025 §3.5).

    Every frame is registered to a local map of the previous ones (KISS-ICP point-to-point ICP;
    3D frames lose their ground points first). With --imu, the gyro and wheels give each
    ICP its starting guess and bridge frames too sparse to register, and an EKF fuses lidar
    poses, gyro yaw rate and wheel speed, learning the gyro bias and the wheel scale.

    The trajectory is planar (x, y, heading) in the frame of the first lidar pose, one row per
    frame. Frames are in the sensor frame (x forward, z up); the lidar is taken to sit at the
    vehicle's reference point.

    Example: stemmap odometry frames/ --imu imu.csv --out traj.csv

    Example: stemmap odometry drive.bag --imu drive.bag --odom-topic /wheel_odom --out traj.tum

    Example: stemmap odometry scans.npz --imu imu.csv --max-range 80 --out traj.csv  (2D scans)

    Example: stemmap odometry --camera frames/ --out traj.csv  (stereo / RGB-D visual odometry)

    Example: stemmap odometry scans.npz --camera frames/ --out traj.csv  (visual-lidar EKF)
    """
    cam_opts: dict[str, Any] = {
        "max_corners": max_corners,
        "left_topic": left_topic,
        "right_topic": right_topic,
        "depth_topic": depth_topic,
        "info_topic": info_topic,
        "baseline": baseline,
    }
    from stemmap.io.products import run_products

    if camera is not None and frames is None:
        from stemmap.cli._odometry_camera import camera_odometry

        with (
            fail_on_stemmap_error(),
            run_products("odometry", inputs=[camera], outputs=[out_path]) as run,
        ):
            _, cam_summary = camera_odometry(camera, run.path(out_path), **cam_opts)
            run.note(**cam_summary)
        if not quiet:
            s = cam_summary
            out.print(
                f"{s['frames']} {s['mode']} frames, {s['keyframes']} keyframes, "
                f"{s['lost_frames']} lost (pose extrapolated), path {s['distance_m']:.2f} m "
                f"-> {out_path}",
                markup=False,
                highlight=False,
            )
        return
    if frames is None:
        print_error("give a sensor input: lidar FRAMES, or --camera FRAMES_DIR for a camera.")
        raise typer.Exit(code=2)
    lidar_opts: dict[str, Any] = {
        "topic": topic,
        "imu_topic": imu_topic,
        "odom_topic": odom_topic,
        "rate": rate,
        "max_range": max_range,
        "min_range": min_range,
        "voxel": voxel,
        "keep_ground": keep_ground,
    }
    with (
        fail_on_stemmap_error(),
        run_products("odometry", inputs=[frames, imu, camera], outputs=[out_path]) as run,
    ):
        if camera is not None:  # the visual-lidar loose coupling (stemmap map --motion fused)
            from stemmap.cli._map_motion import Motion, motion_trajectory

            traj, summary = motion_trajectory(
                frames,
                Motion.fused,
                camera=camera,
                imu=imu,
                quiet=quiet,
                camera_options=cam_opts,
                lidar_options=lidar_opts,
            )
        else:
            traj, summary = lidar_trajectory(frames, imu=imu, quiet=quiet, **lidar_opts)
        _write(run.path(out_path), traj)
        run.note(**summary)
    if not quiet:
        for line in summary_lines(summary, out_path):
            out.print(line, markup=False, highlight=False, soft_wrap=True)


#: Unit of each calibration state by the end of its name (odometry.fusion.FusedOdometry).
_CALIBRATION_UNITS = (
    ("yaw_rate_bias", "rad/s"),
    ("speed_scale", "relative: the source reads (1 + k) v"),
    ("_theta", "rad"),
    ("_x", "m"),
    ("_y", "m"),
)


def summary_lines(summary: dict[str, Any], out_path: Path) -> list[str]:
    """The lidar odometry's summary (``lidar_front_end``'s, or ``motion_trajectory``'s for a
    fused run) as sentences with units, the written file on the first line."""
    lid = summary.get("lidar", summary)
    imu = " + IMU/wheels" if lid.get("imu") else ""
    lines = [
        f"{lid['frames']} lidar frames{imu}, {lid['held_frames']} held (too few points to "
        f"register) -> {out_path}"
    ]
    vis = summary.get("visual")
    if vis:
        lines.append(
            f"camera ({vis.get('kind', vis.get('mode', '?'))}): {vis['frames']} frames"
            + (
                f", {vis['keyframes']} keyframes, {vis['lost_frames']} lost"
                if "keyframes" in vis
                else ""
            )
        )
    if lid.get("rejected"):
        lines.append(
            "measurements rejected by the EKF gate: "
            + ", ".join(f"{k} {v}" for k, v in lid["rejected"].items())
        )
    if lid.get("calibration"):
        parts = []
        for name, v in lid["calibration"].items():
            unit = next((u for end, u in _CALIBRATION_UNITS if name.endswith(end)), "")
            parts.append(f"{name} {v:+.6g}" + (f" ({unit})" if unit else ""))
        lines.append("learned calibration: " + ", ".join(parts))
    lines.append(f"distance travelled: {summary['distance_m']:.3f} m (chords >= 0.5 m)")
    for key, text in (
        ("drift_estimate_percent", "drift estimate (1 sigma): {:.3g} % of the distance"),
        ("ekf_final_position_std_m", "EKF position std at the end: {:.3g} m"),
        ("visual_vs_lidar_percent", "visual vs lidar disagreement: {:.3g} % over 10 m"),
    ):
        if summary.get(key) is not None:
            lines.append(text.format(summary[key]))
    return lines


def _read_inertial(imu: Path | None, imu_topic: str | None, odom_topic: str | None) -> Any:
    if imu is None:
        return None
    from stemmap.io.rosbag import is_bag

    if is_bag(imu):
        from stemmap.io.imu import inertial_from_bag

        return inertial_from_bag(imu, imu_topic, odom_topic)
    from stemmap.io.imu import read_imu_csv

    return read_imu_csv(imu)


def lidar_trajectory(
    frames: Path, *, imu: Path | None, quiet: bool, **opt: Any
) -> tuple[Any, dict[str, Any]]:
    """The lidar (+ IMU / wheel EKF) trajectory of ``frames`` (one pose per frame, frame
    ``odom``) and a summary; ``opt`` holds this command's other options (topic, imu_topic,
    odom_topic, rate, max_range, min_range, voxel, keep_ground)."""
    traj, _, _, summary = lidar_front_end(frames, imu=imu, quiet=quiet, **opt)
    return traj, summary


def lidar_front_end(
    frames: Path,
    *,
    imu: Path | None,
    quiet: bool,
    extra: Sequence[OdometrySource] = (),
    **opt: Any,
) -> tuple[Any, Any, Any, dict[str, Any]]:
    """:func:`lidar_trajectory` with further velocity sources fused in (``extra``, e.g. the
    visual odometry of ``stemmap map --motion fused``); returns (trajectory, the
    :class:`~stemmap.odometry.lidar.LidarOdometryResult`, the
    :class:`~stemmap.odometry.fusion.FusedOdometry` or None, summary)."""
    from stemmap.eval.trajectory import path_length
    from stemmap.io.lidar_frames import open_frames
    from stemmap.odometry.inertial import lidar_inertial_odometry
    from stemmap.odometry.lidar import LidarOdometryConfig

    seq = open_frames(frames, topic=opt["topic"], rate_hz=opt["rate"])
    inertial = _read_inertial(imu, opt["imu_topic"], opt["odom_topic"])
    cfg = LidarOdometryConfig(
        max_range=opt["max_range"],
        min_range=opt["min_range"],
        voxel_size=opt["voxel"],
        remove_ground=not opt["keep_ground"],
    )
    extra = list(extra)
    with progress(not quiet) as bar:
        task = bar.add_task("registering frames", total=len(seq) or None)

        def counted() -> Any:
            for item in seq:
                yield item
                bar.advance(task)

        traj, lidar, fused = lidar_inertial_odometry(counted(), inertial, cfg, extra=extra)
    summary: dict[str, Any] = {
        "frames": len(lidar),
        "held_frames": int(lidar.held.sum()),
        "imu": inertial is not None,
    }
    if fused is not None:
        summary["rejected"] = dict(zip(fused.source_names, fused.n_rejected.tolist(), strict=True))
        summary["calibration"] = dict(
            zip(fused.calibration_names, np.round(fused.calibration, 6).tolist(), strict=True)
        )
    summary["distance_m"] = round(path_length(traj), 3)
    if inertial is not None:  # do the scans turn the way the gyro turns?
        from stemmap.cli._map_handedness import gyro_heading, turn_sense_warning

        gt, gh = gyro_heading(inertial)
        warning = turn_sense_warning(lidar.trajectory(), gt, gh, "the IMU's gyro")
        if warning is not None:
            summary["turn_sense_warning"] = warning
            console.print(f"[yellow]warning:[/yellow] {warning}")
    if summary["held_frames"]:
        console.print(
            f"warning: {summary['held_frames']} of {len(lidar)} frames had too few points to "
            "register; their poses come from the IMU/wheels (or constant velocity).",
            markup=False,
        )
    return traj, lidar, fused, summary


def _write(path: Path, traj: Any) -> None:
    from stemmap.io.trajectory import write_trajectory_csv, write_trajectory_tum

    if path.suffix.lower() in _TUM_SUFFIXES:
        write_trajectory_tum(path, traj)
    else:
        write_trajectory_csv(path, traj)


def register(app: typer.Typer) -> None:
    app.command("odometry")(odometry)
