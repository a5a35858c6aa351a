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
segment_features, segment_classifier
    Trainable ilastik-style pixel classifier (multi-scale features, gradient-boosted trees in
    a pickle-free model file); the default of ``stemmap segment``.
photometric
    Camera-like colour changes (white balance, exposure, tone, hue, blur, JPEG) and grey-world
    white balance: augmentation and robustness checks of the classifier.
image_io
    Safe photo reading: pixel limit from the header, truncated / damaged files refused.
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
    undistort_image,
    undistort_region,
)
from stemmap.vision.depth import DaimParams, daim_trunks
from stemmap.vision.detector import Detections, OnnxDetector, SegmentationDetector, TrunkDetector
from stemmap.vision.edges import EdgeParams, measure_diameter, phase_congruency_edges
from stemmap.vision.image_io import read_image
from stemmap.vision.segment import Regions, Segmentation, SegmentParams, segment_trunks
from stemmap.vision.segment_classifier import (
    PixelModel,
    default_model,
    load_model,
    save_model,
    segment_pixels,
    train_pixel_classifier,
)

__all__ = [
    "CameraModel",
    "DaimParams",
    "Detections",
    "EdgeParams",
    "HomographyFit",
    "OnnxDetector",
    "PixelModel",
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
    "default_model",
    "fit_homography",
    "fit_homography_dlt",
    "fit_homography_ransac",
    "fit_homography_xue2018",
    "laser_plane_homography",
    "load_model",
    "measure_diameter",
    "phase_congruency_edges",
    "plate_edges_from_scan",
    "project_laser_points",
    "project_points",
    "read_image",
    "refine_homography",
    "save_model",
    "segment_pixels",
    "segment_trunks",
    "solve_plate_points",
    "solve_pnp",
    "train_pixel_classifier",
    "undistort_image",
    "undistort_region",
]
