"""Laser + vision evidence fusion (Dempster-Shafer; Xue et al. 2018, and ours).

Modules
-------
evidence
    Mass functions on {T, NT}, Dempster's rule (eq. 16), decision rule (eq. 17).
bpa
    Laser BPA from width (eq. 13), vision BPA from alpha (eqs. 14-15), presets; ours.
associate
    Laser regions of interest and their association with image regions through G.
fuse
    The Xue (2018) pipeline and our fusion.
scenes
    Simulated laser + camera scenes with distractors, and their scoring.
"""

from stemmap.fusion.associate import Association, LaserRois, associate, laser_rois
from stemmap.fusion.bpa import PRESETS, BpaParams, laser_bpa, laser_bpa_ours, vision_bpa
from stemmap.fusion.evidence import Combination, Mass, combine_dempster, decide_xue2018
from stemmap.fusion.fuse import FusionParams, FusionResult, discount, fuse_ours, fuse_xue2018

__all__ = [
    "PRESETS",
    "Association",
    "BpaParams",
    "Combination",
    "FusionParams",
    "FusionResult",
    "LaserRois",
    "Mass",
    "associate",
    "combine_dempster",
    "decide_xue2018",
    "discount",
    "fuse_ours",
    "fuse_xue2018",
    "laser_bpa",
    "laser_bpa_ours",
    "laser_rois",
    "vision_bpa",
]
