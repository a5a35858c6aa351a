"""``stemmap sim munjer --out drive.npz``: a Munjer-like drive (16-beam lidar at 10 Hz, RGB-D
camera, park or orchard, 3-5 m/s; :func:`stemmap.sim.munjer.simulate_munjer_drive`) written as

* ``drive.npz`` -- the frames bundle (:mod:`stemmap.io.frames`: lidar frames and RGB-D frames);
* ``drive_odometry.csv`` -- the motion source ``time_s,speed,yaw_rate`` (s, m/s, rad/s);
* ``drive_imu.csv`` -- IMU (gyro, accelerometer, 50 Hz) + wheel speed (50 Hz) of the drive
  (:func:`stemmap.sim.imu.simulate_imu`, XSens preset; :mod:`stemmap.io.imu` layout), the
  ``--imu`` of ``stemmap odometry drive.npz`` / ``stemmap map drive.npz --odometry lidar``;
* ``drive_trees.csv`` -- truth trees ``id,x,y,diameter`` (world frame, metres);
* ``drive_objects.csv`` -- the non-tree objects ``id,x,y,radius,kind``;
* ``drive_poses.csv`` -- the true vehicle (= lidar) pose of every frame ``time_s,x,y,theta``.

The world frame is the map frame of ``stemmap map drive.npz`` only up to the start pose: the map
starts at (0, 0, 0); score with ``stemmap sim score``-style alignment or use the first pose.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from stemmap.cli._common import QuietFlag, fail_on_stemmap_error, out
from stemmap.cli._validate import bounded

__all__ = ["munjer"]


def munjer(
    out_path: Annotated[Path, typer.Option("--out", "-o", help="Frames bundle NPZ to write.")],
    seed: Annotated[
        int, typer.Option(help="Random seed (same files).", callback=bounded("--seed", ge=0))
    ] = 0,
    layout: Annotated[str, typer.Option(help="Stand layout: park or orchard.")] = "park",
    speed: Annotated[
        float, typer.Option(help="Robot speed, m/s.", callback=bounded("--speed", gt=0))
    ] = 4.0,
    duration: Annotated[
        float | None,
        typer.Option(
            help="Drive length, s [default: one lap].", callback=bounded("--duration", gt=0)
        ),
    ] = None,
    camera_every: Annotated[
        int,
        typer.Option(
            "--camera-every",
            help="An RGB-D frame every k-th lidar frame (0 = lidar only).",
            callback=bounded("--camera-every", ge=0),
        ),
    ] = 1,
    quiet: QuietFlag = False,
) -> None:
    """Simulate a Munjer et al. (2025) drive: 16-beam lidar + RGB-D frames, odometry, truth.

    Example: stemmap sim munjer --out drive.npz && stemmap map drive.npz --frontend eb-lidar
    """
    from stemmap.errors import ConfigError
    from stemmap.io.atomic import atomic_write
    from stemmap.io.frames import write_frames_npz
    from stemmap.io.imu import write_imu_csv
    from stemmap.io.products import run_products
    from stemmap.io.trajectory import write_trajectory_csv
    from stemmap.sim.imu import simulate_imu
    from stemmap.sim.munjer import simulate_munjer_drive
    from stemmap.types import Trajectory

    if layout not in ("park", "orchard"):
        raise typer.BadParameter(f"--layout must be park or orchard, got {layout!r}.")

    def sib(s: str) -> Path:
        return out_path.with_name(f"{out_path.stem}_{s}")

    o_path, i_path, t_path, b_path, p_path = (
        sib("odometry.csv"),
        sib("imu.csv"),
        sib("trees.csv"),
        sib("objects.csv"),
        sib("poses.csv"),
    )
    products = [out_path, o_path, i_path, t_path, b_path, p_path]
    with fail_on_stemmap_error(), run_products("sim munjer", outputs=products) as run:
        if out_path.suffix.lower() != ".npz":
            raise ConfigError(f"--out must end in .npz, got {out_path.name!r}.")
        d = simulate_munjer_drive(
            layout=layout,  # type: ignore[arg-type]
            speed=speed,
            duration=duration,
            camera_every=camera_every,
            rng=seed,
        )
        T = np.eye(4)
        to_body = d.rig.laser_to_camera.inverse()
        T[:3, :3], T[:3, 3] = to_body.R, to_body.t
        has_cam = len(d.images) > 0
        write_frames_npz(
            run.path(out_path),
            d.times,
            lidar=[f.xyz for f in d.frames],
            images=list(d.images) if has_cam else None,
            depths=list(d.depths) if has_cam else None,
            image_frames=d.camera_frames if has_cam else None,
            camera_matrix=d.rig.camera.K if has_cam else None,
            camera_to_body=T if has_cam else None,
        )
        with atomic_write(run.path(o_path)) as fh:
            fh.write("time_s,speed,yaw_rate\n")
            o = d.odometry
            rows = zip(o.times.tolist(), o.speed.tolist(), o.yaw_rate.tolist(), strict=True)
            for t, v, w in rows:
                fh.write(f"{t!r},{v!r},{w!r}\n")
        write_imu_csv(run.path(i_path), simulate_imu(d.odometry_true, rng=seed).log)
        st = d.stand2d
        with atomic_write(run.path(t_path)) as fh:
            fh.write("id,x,y,diameter\n")
            for i, ((x, y), dd) in enumerate(zip(st.trees_xy, st.diameters, strict=True)):
                fh.write(f"{i},{x:.6f},{y:.6f},{dd:.6f}\n")
        with atomic_write(run.path(b_path)) as fh:
            fh.write("id,x,y,radius,kind\n")
            for i, ((x, y), r, k) in enumerate(
                zip(st.clutter_objects_xy, st.clutter_objects_extent, st.clutter_kinds, strict=True)
            ):
                fh.write(f"{i},{x:.6f},{y:.6f},{r:.6f},{k}\n")
        write_trajectory_csv(run.path(p_path), Trajectory(d.times, d.poses, frame="world"))
        run.note(scenario=d.params, seed=seed)
    if not quiet:
        out.print(
            f"simulated {len(d.frames)} lidar frames, {len(d.images)} RGB-D frames, "
            f"{st.n_trees} trees, {st.n_clutter_objects} non-tree objects\n"
            f"  frames: {out_path}\n  odometry: {o_path}\n  imu: {i_path}\n  trees: {t_path}\n"
            f"  objects: {b_path}\n  poses: {p_path}"
        )
