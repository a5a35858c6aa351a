"""Stems and DBH from 3D lidar and terrestrial point clouds.

* :func:`detect_stems` -- ours (ground model, multi-slice robust geometric fits, quality tests;
  thresholds from the measured point spacing); :func:`detect_stems_file` streams LAS/LAZ;
  :class:`SensorPositions` (a station, or a trajectory + point times) for its along-ray fits.
* :func:`detect_stems_munjer` + :func:`associate_proximity` -- EB-LiDAR (Munjer et al. 2025).
* Building blocks: :mod:`~stemmap.cloud.filters` (pass-through, voxel grid, spacing),
  :mod:`~stemmap.cloud.cluster` (DBSCAN, grid components), :mod:`~stemmap.cloud.shape`
  (covariances, PCA eccentricity, arc coverage), :mod:`~stemmap.cloud.ground` (ground raster,
  height normalisation), :mod:`~stemmap.cloud.export` (CSV, GeoJSON, PNG).

See docs/algorithms/cloud.md for the paper-to-function map and measured numbers.
"""

from stemmap.cloud.cluster import dbscan, grid_components
from stemmap.cloud.filters import pass_through, point_spacing, voxel_downsample
from stemmap.cloud.ground import GroundAccumulator, GroundModel, fit_ground, normalize_heights
from stemmap.cloud.sensor import SensorPositions
from stemmap.cloud.shape import (
    arc_coverage_deg,
    cluster_covariances,
    major_axis_tilt_deg,
    pca_eccentricity,
)
from stemmap.cloud.stems import (
    PRESETS,
    CloudStems,
    MunjerConfig,
    PreparedCloud,
    StemConfig,
    associate_proximity,
    detect_prepared,
    detect_statistics,
    detect_stems,
    detect_stems_file,
    detect_stems_munjer,
    get_preset,
    grid_anchors,
    prepare_cloud,
)

__all__ = [
    "PRESETS",
    "CloudStems",
    "GroundAccumulator",
    "GroundModel",
    "MunjerConfig",
    "PreparedCloud",
    "SensorPositions",
    "StemConfig",
    "arc_coverage_deg",
    "associate_proximity",
    "cluster_covariances",
    "dbscan",
    "detect_prepared",
    "detect_statistics",
    "detect_stems",
    "detect_stems_file",
    "detect_stems_munjer",
    "fit_ground",
    "get_preset",
    "grid_anchors",
    "grid_components",
    "major_axis_tilt_deg",
    "normalize_heights",
    "pass_through",
    "pca_eccentricity",
    "point_spacing",
    "prepare_cloud",
    "voxel_downsample",
]
