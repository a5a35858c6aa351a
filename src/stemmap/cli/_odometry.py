"""``stemmap odometry``: odometry from sensor data (camera frames).

Minimal command of the visual odometry work (issue 16); the lidar/IMU side lives next to it after
the merge. ``--camera FRAMES`` runs :func:`stemmap.cli._odometry_camera.camera_odometry`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stemmap.cli._common import fail_on_stemmap_error, print_error

__all__ = ["register"]


def odometry(
    camera: Annotated[
        Path | None,
        typer.Option(
            "--camera",
            help="Camera frames folder (left/ + right/ rectified stereo, or rgb/ + depth/, with "
            "camera.json intrinsics) or a ROS bag with Image + CameraInfo topics (docs/cli.md).",
        ),
    ] = None,
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Trajectory CSV to write (time_s,x,y,theta).")
    ] = Path("odometry.csv"),
    max_corners: Annotated[
        int | None, typer.Option(help="Shi-Tomasi corners per keyframe (default 400).")
    ] = None,
    left_topic: Annotated[
        str | None, typer.Option(help="Bag: left (or colour) Image topic; guessed if unique.")
    ] = None,
    right_topic: Annotated[str | None, typer.Option(help="Bag: right Image topic.")] = None,
    depth_topic: Annotated[
        str | None, typer.Option(help="Bag: depth Image topic (RGB-D instead of stereo).")
    ] = None,
    info_topic: Annotated[
        str | None, typer.Option(help="Bag: CameraInfo topic of the left camera.")
    ] = None,
    baseline: Annotated[
        float | None,
        typer.Option(help="Bag: stereo baseline, m (default: from the right CameraInfo's P)."),
    ] = None,
) -> None:
    """Estimate the vehicle's path from sensor data.

    Examples: stemmap odometry --camera frames/ --out traj.csv;
    stemmap odometry --camera run.bag --left-topic /zed2/left/image_rect_color --out traj.csv
    """
    if camera is None:
        print_error("give a sensor input: --camera FRAMES_DIR.")
        raise typer.Exit(code=2)
    from stemmap.cli._odometry_camera import camera_odometry

    with fail_on_stemmap_error():
        camera_odometry(
            camera,
            out,
            max_corners=max_corners,
            left_topic=left_topic,
            right_topic=right_topic,
            depth_topic=depth_topic,
            info_topic=info_topic,
            baseline=baseline,
        )


def register(app: typer.Typer) -> None:
    app.command("odometry")(odometry)
