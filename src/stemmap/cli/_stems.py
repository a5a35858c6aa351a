"""``stemmap stems``: stem positions and DBH from a 3D point cloud."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stemmap.cli._common import console, fail_on_stemmap_error, out, progress

__all__ = ["register"]


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
    chunk_size: Annotated[int, typer.Option(help="Points per chunk when streaming LAS/LAZ.")] = (
        2_000_000
    ),
) -> None:
    """Find stems in CLOUD and write x, y, z, diameter, n_points, quality per stem (cloud frame,
    metres). LAS/LAZ files are streamed in chunks (progress bar). munjer2025 expects one lidar
    frame in the sensor frame (pass-through box x 0..10, y -10..10, z -0.5..0 m).

    Example: stemmap stems plot.laz --out stems.csv --png stems.png
    """
    from dataclasses import replace

    from stemmap.cloud.export import plot_stems, write_stems_csv, write_stems_geojson
    from stemmap.cloud.stems import (
        StemConfig,
        detect_stems,
        detect_stems_file,
        detect_stems_munjer,
        get_preset,
    )
    from stemmap.io.clouds import read_cloud

    with fail_on_stemmap_error():
        cfg = get_preset(preset)
        if isinstance(cfg, StemConfig) and heights:
            cfg = replace(cfg, estimate_height=True)
        ext = cloud.suffix.lower()
        bg = None
        if ext in (".las", ".laz"):
            with progress() as bar:
                task = bar.add_task(f"reading {cloud.name}", total=None)

                def tick(done: int, total: int) -> None:
                    bar.update(task, completed=done, total=total)

                result = detect_stems_file(cloud, cfg, chunk_size=chunk_size, on_chunk=tick)
        else:
            pc = read_cloud(cloud, topic=topic)
            result = (
                detect_stems(pc.xyz, cfg)
                if isinstance(cfg, StemConfig)
                else detect_stems_munjer(pc.xyz, cfg)
            )
            bg = pc.xyz[:: max(1, len(pc) // 200_000), :2]
        write_stems_csv(out_csv, result)
        if geojson is not None:
            write_stems_geojson(geojson, result)
        if png is not None:
            if bg is None and ext in (".las", ".laz"):
                import numpy as np

                from stemmap.io.clouds import count_points, iter_las_chunks

                # background: every k-th point of the whole file (one more streaming pass)
                step = max(1, (count_points(cloud) or 0) // 200_000)
                bg = np.concatenate([c.xyz[::step, :2] for c in iter_las_chunks(cloud, chunk_size)])
            plot_stems(png, result, background_xy=bg, title=f"{cloud.name}: {len(result)} stems")
        out.print(
            f"{len(result)} stems ({result.method}) written to {out_csv}"
            + (f", {geojson}" if geojson else "")
            + (f", {png}" if png else "")
        )
        if len(result) == 0:
            console.print(f"[yellow]warning:[/yellow] no stems found: {result.reason}.")


def register(app: typer.Typer) -> None:
    app.command("stems")(stems)
