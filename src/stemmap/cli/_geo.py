"""CLI helpers for georeferenced map products: the ``--crs`` / ``--gpkg`` options and the
writers of the stem map + path products shared by ``stemmap map`` and ``stemmap demo``."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

__all__ = ["CrsOption", "GpkgFlag", "checked_crs", "write_gps_frame", "write_map_products"]

CrsOption = Annotated[
    str | None,
    typer.Option(
        "--crs",
        help="CRS of the map frame's x, y (EPSG code, WKT or PROJ string, e.g. EPSG:32633): "
        "GeoJSON is then WGS84 lon/lat (RFC 7946) and the GeoPackage keeps this CRS. Without "
        "it the frame is declared local (metres, not georeferenced).",
        rich_help_panel="Georeferencing",
    ),
]
GpkgFlag = Annotated[
    bool,
    typer.Option(
        "--gpkg/--no-gpkg",
        help="Also write a GeoPackage (trees, trajectory, poses layers) in the native CRS.",
        rich_help_panel="Georeferencing",
    ),
]


def checked_crs(crs: str | None) -> str | None:
    """``--crs`` normalised to ``EPSG:code`` (or WKT); ConfigError when pyproj rejects it."""
    if crs is None:
        return None
    from stemmap.io.geo import crs_label, parse_crs

    return crs_label(parse_crs(crs))


def write_map_products(
    out_dir: Path,
    stem_map: Any,
    trajectory: Any,
    *,
    crs: str | None,
    gpkg: bool,
    trajectory_format: str = "csv",
    prefix: str = "",
    pose_covs: Any = None,
    gpkg_layers: Any = (),
) -> list[str]:
    """Write ``{prefix}trees.csv``, ``trees.geojson``, the trajectory (``trajectory.csv`` or
    TUM ``trajectory.tum``) and optionally ``map.gpkg`` (with ``gpkg_layers`` added, e.g. the
    GNSS-frame track); return the file names written.
    ``pose_covs`` (N, 3, 3), the back-end's pose covariances (``SlamResult.pose_covs``), go
    into trajectory.csv's covariance columns (the TUM format has no place for them)."""
    from dataclasses import replace

    from stemmap.io.geo import write_map_gpkg
    from stemmap.io.maps import write_trees_csv, write_trees_geojson
    from stemmap.io.trajectory import write_trajectory_csv, write_trajectory_tum

    sm = replace(stem_map, crs=crs) if crs is not None else stem_map
    names = [f"{prefix}trees.csv", f"{prefix}trees.geojson"]
    write_trees_csv(out_dir / names[0], sm)
    write_trees_geojson(out_dir / names[1], sm)
    if trajectory_format == "tum":
        names.append(f"{prefix}trajectory.tum")
        write_trajectory_tum(out_dir / names[-1], trajectory)
    else:
        names.append(f"{prefix}trajectory.csv")
        write_trajectory_csv(out_dir / names[-1], trajectory, covs=pose_covs)
    if gpkg:
        names.append(f"{prefix}map.gpkg")
        write_map_gpkg(out_dir / names[-1], sm, trajectory, extra_layers=gpkg_layers)
    return names


def write_gps_frame(
    out_dir: Path,
    alignment: Any,
    stem_map: Any,
    trajectory: Any,
    *,
    sensor_offset: tuple[float, float],
    gpkg: bool,
    trajectory_format: str = "csv",
    pose_covs: Any = None,
) -> list[str]:
    """Victoria Park: the map and path moved into the GPS frame by the ATE alignment
    (``gps_`` products, pose covariances rotated with the path) and the alignment itself
    (``gps_alignment.json``)."""
    from dataclasses import replace

    from stemmap.io.atomic import atomic_write
    from stemmap.types import StemMap, Trajectory

    r = alignment.rotation
    trees = []
    for t, (x, y) in zip(stem_map.trees, alignment.apply(stem_map.xy), strict=True):
        trees.append(replace(t, x=float(x), y=float(y), cov=r @ t.cov @ r.T))
    sm = StemMap(tuple(trees), frame="gps", crs=None)
    tr = Trajectory(trajectory.times, alignment.apply_poses(trajectory.poses), frame="gps")
    covs = None
    if pose_covs is not None:
        rot3 = np.eye(3)
        rot3[:2, :2] = r
        covs = rot3 @ np.asarray(pose_covs) @ rot3.T
    names = write_map_products(
        out_dir,
        sm,
        tr,
        crs=None,
        gpkg=gpkg,
        trajectory_format=trajectory_format,
        prefix="gps_",
        pose_covs=covs,
    )
    doc = {
        "from_frame": stem_map.frame,
        "to_frame": "gps (the dataset's gps.dat metres, shifted and rotated by its "
        "redistributor: a local frame, no CRS)",
        "transform": "p_gps = R(theta) p_map + t",
        "theta_rad": float(alignment.theta),
        "theta_deg": math.degrees(float(alignment.theta)),
        "t_m": [float(alignment.t[0]), float(alignment.t[1])],
        "fitted_on": "the laser position (sensor_offset_m ahead of the trajectory's rear-axle "
        "point) at the screened GPS fix times, least squares (stemmap.eval.trajectory.align_se2)",
        "sensor_offset_m": list(sensor_offset),
    }
    with atomic_write(out_dir / "gps_alignment.json") as fh:
        json.dump(doc, fh, indent=1)
    return [*names, "gps_alignment.json"]
