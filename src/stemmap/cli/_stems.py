"""``stemmap stems``: stem positions and DBH from a 3D point cloud."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from stemmap.cli._common import console, fail_on_stemmap_error, out, progress
from stemmap.cli._validate import bounded
from stemmap.errors import ConfigError

if TYPE_CHECKING:
    from stemmap.cloud.sensor import SensorPositions

__all__ = ["register"]


def _floats(text: str, option: str, form: str, sizes: tuple[int, ...]) -> tuple[float, ...]:
    """'a,b[,c]' -> floats; ConfigError naming the option and the expected form otherwise."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) not in sizes or not all(math.isfinite(v) for v in vals):
        raise ConfigError(f"{option} must be {form} in metres, got {text!r}.")
    return vals


def _sensor(
    origin: str | None,
    trajectory: Path | None,
    time_field: str | None,
    time_offset: float,
    sensor_offset: str | None,
) -> SensorPositions | None:
    """The sensor positions the options describe (None without --origin / --trajectory)."""
    from stemmap.cloud.sensor import SensorPositions

    if origin is not None and trajectory is not None:
        raise ConfigError("give either --origin (one station) or --trajectory, not both.")
    if trajectory is None:
        used = [
            n
            for n, v in (
                ("--time-field", time_field),
                ("--time-offset", time_offset or None),
                ("--sensor-offset", sensor_offset),
            )
            if v is not None
        ]
        if used:
            raise ConfigError(f"{', '.join(used)} only apply with --trajectory.")
        if origin is None:
            return None
        return SensorPositions(station=_floats(origin, "--origin", "'X,Y' or 'X,Y,Z'", (2, 3)))
    from stemmap.io.trajectory import read_trajectory_csv, read_trajectory_tum

    reader = read_trajectory_csv if trajectory.suffix.lower() == ".csv" else read_trajectory_tum
    off = _floats(sensor_offset, "--sensor-offset", "'A,B'", (2,)) if sensor_offset else (0.0, 0.0)
    return SensorPositions(
        trajectory=reader(trajectory),
        time_field=time_field,
        time_offset=time_offset,
        sensor_offset=(off[0], off[1]),
    )


def stems(
    cloud: Annotated[Path, typer.Argument(help="LAS/LAZ, PLY, PCD, XYZ text or a ROS bag.")],
    out_csv: Annotated[Path, typer.Option("--out", help="CSV to write, one row per stem.")] = Path(
        "stems.csv"
    ),
    preset: Annotated[
        str, typer.Option(help="Method: ours (default), ours_kasa or munjer2025.")
    ] = "ours",
    geojson: Annotated[Path | None, typer.Option(help="Also write a GeoJSON of the stems.")] = None,
    png: Annotated[Path | None, typer.Option(help="Also write a top-view PNG.")] = None,
    topic: Annotated[str | None, typer.Option(help="PointCloud2 topic (bags only).")] = None,
    heights: Annotated[bool, typer.Option(help="Also estimate stem heights (ours).")] = False,
    chunk_size: Annotated[
        int,
        typer.Option(
            help="Points per chunk when streaming LAS/LAZ.", callback=bounded("--chunk-size", ge=1)
        ),
    ] = 2_000_000,
    origin: Annotated[
        str | None,
        typer.Option(
            help="Scanner position 'X,Y[,Z]' (m, cloud frame) of a single-station scan: fits "
            "along the rays (ours).",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    trajectory: Annotated[
        Path | None,
        typer.Option(
            help="Machine path, stemmap CSV time,x,y,theta (.csv) or TUM 't x y z qx qy qz qw'; "
            "each point's sensor position is interpolated at its time stamp (ours).",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    time_field: Annotated[
        str | None,
        typer.Option(
            help="Per-point time field [default: gps_time, time or timestamp, the first present].",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
    time_offset: Annotated[
        float,
        typer.Option(
            help="Seconds added to the point times before the trajectory look-up (e.g. 1e9 for "
            "LAS adjusted standard GPS time against GPS seconds).",
            callback=bounded("--time-offset"),
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = 0.0,
    sensor_offset: Annotated[
        str | None,
        typer.Option(
            help="Scanner position 'A,B' (m) forward and left of the trajectory's reference "
            "point [default: 0,0].",
            rich_help_panel="Sensor positions (along-ray fits)",
        ),
    ] = None,
) -> None:
    """Find stems in CLOUD and write x, y, z, diameter, n_points, quality per stem (cloud frame,
    metres). LAS/LAZ files are streamed in chunks (progress bar). munjer2025 expects one lidar
    frame in the sensor frame (pass-through box x 0..10, y -10..10, z -0.5..0 m).

    With the scanner's positions (--origin for one station, or --trajectory plus the points'
    time stamps for a mobile cloud) the circle fits of preset ours minimise the range errors
    along each point's ray, which removes the low DBH bias of a noisy mobile lidar.

    Example: stemmap stems plot.laz --out stems.csv --png stems.png

    Mobile: stemmap stems drive.laz --trajectory path.csv --sensor-offset 1.2,0

    One station: stemmap stems station.ply --origin 12.5,3.0
    """
    from dataclasses import replace

    from stemmap.cloud.export import plot_stems, write_stems_csv, write_stems_geojson
    from stemmap.cloud.stems import StemConfig, detect_stems_file, get_preset
    from stemmap.io.clouds import count_points, iter_cloud_chunks
    from stemmap.io.products import run_products

    with (
        fail_on_stemmap_error(),
        run_products("stems", inputs=[cloud, trajectory], outputs=[out_csv, geojson, png]) as run,
    ):
        cfg = get_preset(preset)
        if isinstance(cfg, StemConfig) and heights:
            cfg = replace(cfg, estimate_height=True)
        sensor = _sensor(origin, trajectory, time_field, time_offset, sensor_offset)
        with progress() as bar:
            task = bar.add_task(f"reading {cloud.name}", total=None)

            def tick(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            result = detect_stems_file(
                cloud, cfg, chunk_size=chunk_size, on_chunk=tick, sensor=sensor, topic=topic
            )
        write_stems_csv(run.path(out_csv), result)
        if geojson is not None:
            write_stems_geojson(run.path(geojson), result)
        if png is not None:
            import numpy as np

            # background: every k-th point of the whole file (one more streaming pass; the
            # size of a non-LAS file is known only once it is read, as one chunk)
            total = count_points(cloud)
            bg = np.concatenate(
                [
                    c.xyz[:: max(1, (total or len(c)) // 200_000), :2]
                    for c in iter_cloud_chunks(cloud, chunk_size, topic=topic)
                ]
            )
            title = f"{cloud.name}: {len(result)} stems"
            plot_stems(run.path(png), result, background_xy=bg, title=title)
        out.print(
            f"{len(result)} stems ({result.method}"
            + (", along-ray fits" if sensor is not None else "")
            + f") written to {out_csv}"
            + (f", {geojson}" if geojson else "")
            + (f", {png}" if png else "")
        )
        if len(result) == 0:
            console.print(f"[yellow]warning:[/yellow] no stems found: {result.reason}.")


def register(app: typer.Typer) -> None:
    app.command("stems")(stems)
