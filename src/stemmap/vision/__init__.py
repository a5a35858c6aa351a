"""Camera side of stemmap: calibration to the laser, trunk segmentation, edge diameters, DAIM.

Modules
-------
camera
    Pinhole model, rigid transforms, projection of laser / 3D points, the laser-plane
    homography of a known rig.
calibrate
    Laser-to-image matrix G (Xue 2018 eq. 11; normalised DLT; RANSAC; LM), the notched plate
    (Xue eqs. 4-6), PnP (visual-lidar §2.1).
segment
    Stripping segmentation and matching level alpha (Xue §2.4.3, eq. 18).
edges
    Edge-based trunk diameter (Öhman 2007 §3).
depth
    Depth-assisted image-based mapping (Munjer 2025 §3.4).
detector
    Pluggable box detectors: classical segmentation or a user-supplied ONNX model.
"""

from stemmap.vision.calibrate import (
    HomographyFit,
    PlateModel,
    PoseFit,
    fit_homography,
    fit_homography_dlt,
    fit_homography_ransac,
    fit_homography_xue2018,
    plate_edges_from_scan,
    refine_homography,
    solve_plate_points,
    solve_pnp,
)
from stemmap.vision.camera import (
    CameraModel,
    RigidTransform,
    apply_homography,
    laser_plane_homography,
    project_laser_points,
    project_points,
)
from stemmap.vision.depth import DaimParams, daim_trunks
from stemmap.vision.detector import Detections, OnnxDetector, SegmentationDetector, TrunkDetector
from stemmap.vision.edges import EdgeParams, measure_diameter
from stemmap.vision.segment import Regions, Segmentation, SegmentParams, segment_trunks

__all__ = [
    "CameraModel",
    "DaimParams",
    "Detections",
    "EdgeParams",
    "HomographyFit",
    "OnnxDetector",
    "PlateModel",
    "PoseFit",
    "Regions",
    "RigidTransform",
    "SegmentParams",
    "Segmentation",
    "SegmentationDetector",
    "TrunkDetector",
    "apply_homography",
    "daim_trunks",
    "fit_homography",
    "fit_homography_dlt",
    "fit_homography_ransac",
    "fit_homography_xue2018",
    "laser_plane_homography",
    "measure_diameter",
    "plate_edges_from_scan",
    "project_laser_points",
    "project_points",
    "refine_homography",
    "segment_trunks",
    "solve_plate_points",
    "solve_pnp",
]
