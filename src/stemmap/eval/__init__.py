"""Evaluation: score every product against simulator ground truth.

Public API of the sim-eval area (matching, detection metrics, map metrics). The trajectory
metrics live in :mod:`stemmap.eval.trajectory` (import it from there).
"""

from stemmap.eval.detection import (
    DEFAULT_RANGE_BINS,
    DetectionMetrics,
    RangeBinMetrics,
    detectable_trees,
    detection_metrics,
    scan_detection_metrics,
    score_scan_detections,
)
from stemmap.eval.diameters import DiameterBin, DiameterErrors, diameter_errors
from stemmap.eval.maps import (
    MapMetrics,
    PairwiseDistanceErrors,
    align_rigid_2d,
    map_metrics,
    pairwise_distance_errors,
)
from stemmap.eval.matching import Matching, match_points

__all__ = [
    "DEFAULT_RANGE_BINS",
    "DetectionMetrics",
    "DiameterBin",
    "DiameterErrors",
    "MapMetrics",
    "Matching",
    "PairwiseDistanceErrors",
    "RangeBinMetrics",
    "align_rigid_2d",
    "detectable_trees",
    "detection_metrics",
    "diameter_errors",
    "map_metrics",
    "match_points",
    "pairwise_distance_errors",
    "scan_detection_metrics",
    "score_scan_detections",
]
