"""stemmap.scan -- 2D laser scans: pre-processing, segmentation, segment features, circle fits
and the trunk detector.

The detector is ``ScanTrunkDetector(config).detect(scan)`` / ``.detect_batch(batch)``; every
paper step is also a public function of its module (see docs/algorithms/scan-detection.md).
"""

from stemmap.scan.detect import (
    PRESET_NOTES,
    PRESETS,
    DetectorConfig,
    ScanTrunkDetector,
    fit_kasa_segments,
)
from stemmap.scan.features import (
    SegmentFeatures,
    chord_width,
    cluster_curvature,
    footprint_correct,
    is_straight,
    line_fit_rms,
    point_curvature,
    radius_median_filter,
    sagitta_depth,
    segment_features,
    segment_widths,
)
from stemmap.scan.preprocess import (
    fov_window,
    gate_ranges,
    median_filter3,
    project_tilted,
    roll_beams,
    rotation_rpy,
    seam_shift,
    tilt_compensate,
)
from stemmap.scan.segment import (
    ScanPoints,
    Segments,
    build_segments,
    euclidean_breaks,
    extract_points,
    range_jump_breaks,
)

__all__ = [
    "PRESETS",
    "PRESET_NOTES",
    "DetectorConfig",
    "ScanPoints",
    "ScanTrunkDetector",
    "SegmentFeatures",
    "Segments",
    "build_segments",
    "chord_width",
    "cluster_curvature",
    "euclidean_breaks",
    "extract_points",
    "fit_kasa_segments",
    "footprint_correct",
    "fov_window",
    "gate_ranges",
    "is_straight",
    "line_fit_rms",
    "median_filter3",
    "point_curvature",
    "project_tilted",
    "radius_median_filter",
    "range_jump_breaks",
    "roll_beams",
    "rotation_rpy",
    "sagitta_depth",
    "seam_shift",
    "segment_features",
    "segment_widths",
    "tilt_compensate",
]
