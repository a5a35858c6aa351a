"""The compiled detector's parameter vector (:mod:`stemmap.scan._detect_fast`): the names of
its entries, in order, and :func:`kernel_params`, which reads them off a
:class:`~stemmap.scan.config.DetectorConfig` for one scan layout.

The kernels index the vector by position (numba cannot look names up), so the order of
:data:`PARAM_NAMES` is part of the compiled code: ``_detect_fast`` lists this file among the
files whose edit drops its numba cache.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from stemmap.scan import circle as _circle
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig

__all__ = ["N_PARAMS", "OUT_COLUMNS", "PARAM_INDEX", "PARAM_NAMES", "kernel_params"]

#: Names of the entries of the kernel's parameter vector, in order.
PARAM_NAMES = (
    "lo",  # range gate, exclusive, metres
    "hi",
    "median",  # 1: three-neighbour median filter
    "wrap",  # 1: 360-degree scan, cut at the seam
    "first_beam",  # first / last beam of the field of view (-1 / N when wrapping)
    "last_beam",
    "euclidean",  # 1: Euclidean segmentation, 0: range jump
    "max_jump",
    "range_factor",
    "max_skip",
    "occlusion_margin",
    "pcur_on",  # single-point curvature filter
    "pcur_min",
    "rmed_on",  # radius median filter
    "rmed",
    "split",  # split_merged
    "min_points",
    "min_points_partial",
    "max_points",  # inf = none
    "min_width",
    "max_width",
    "min_depth",
    "min_curvature",
    "max_curvature",
    "reject_straight",
    "straight_chi2",  # 1: chi-square test, 0: residual/width ratio
    "straight_ratio",
    "straight_min_points",
    "drop_partial",
    "sigma",
    "sigma_rel",
    "fit_sigma_given",  # 1: pass the per-segment sigma to the fit, 0: let it estimate
    "min_radius",
    "max_radius",
    "max_radius_width_ratio",
    "max_rms_sigma",
    "divergence",  # radians, full footprint of an averaging scanner
    "use_silhouette",  # 1: priors from the beams beyond each end
    "range_model",  # 1: range residuals, 0: orthogonal
    "angle_increment",  # signed, radians
    "sigma_from_data",  # 1: per-segment sigma >= the robust range roughness of the returns
    "roughness_max_factor",  # ... but at most this multiple of the configured sigma
    "rms_robust",  # 1: the RMS test reads 1.4826 x the median absolute residual
    "bark_roughness",  # RMS bound sqrt(sigma^2 + (bark x radius)^2) when > 0
    "corners_on",  # 1: cut segments at concave corners
    "corner_span",
    "corner_depth",
    "corner_depth_convex",  # inf: convex segments are never cut
    "corner_sigmas",  # corners at least this many sigma deep
    "gap_splits",  # passes of cutting non-convex segments at their largest gap
    "gap_ratio",  # ... if it exceeds this multiple of the segment's median gap
    "gap_sigmas",  # ... and the median gap by this many range-noise sigmas
    "straight_depth_sigmas",  # a sagitta of this many sigmas is never straight
    "sigma_from_scan",  # 1: sigma >= the scan's own range-noise estimate (plausibility.scan_noise)
    "scan_noise_jump",  # ... over triples of adjacent beams with range steps <= this
    "scan_noise_surface",  # ... less the surfaces' own share, in quadrature
    "refit_corners",  # 1: refit_pieces with refit_split="corners" (_refit.split_refit)
    "refit_validate",  # 1: ... accepted only as the parent's one passing piece
    "arc_refit",  # 1: the largest consistent arc of a non-convex candidate (_fast_arcs)
    "arc_sigmas",  # ... grown while a return is within this many robust residual scales
    "arc_floor_sigmas",  # ... but at least this many range-noise sigmas
    "arc_replace",  # an accepted candidate gives way to its arc at this RMS ratio (inf: off)
    "arc_short_steps",  # 1: arcs of min_points returns set off by a range step count
    "arc_tangent_sigmas",  # an arc's returns no farther than its tangent range + this (inf: off)
    "arc_chi2",  # 1: an arc's residuals pass the upper 1 % chi-square test
    "scan_noise_pool",  # 1: scans without their own noise estimate share the batch's
    "edge_hit_min",  # the averaging scanner's return threshold (share of the footprint) ...
    "edge_hit_max",  # ... assumed in [min, max]: the default tangent prior (edge_default_prior)
    "scan_noise_batch_min",  # scans without an estimate take the batch's when >= this (inf: off)
    "step_split",  # 1: a candidate failing the RMS test cut at its largest step (_fast_step_split)
    "step_noise_on",  # 1: ... the step read against the scans' pooled noise (step_noise_pool)
    "step_noise_pool",  # ... scans without an estimate share their pooled one (scan_noise pool)
    "step_noise_batch_min",  # ... still without one take every scan's when >= this (inf: off)
    "batch_noise_biweight",  # 1: every scan's pooled estimate is the biweight's (not the MAD's)
    "edge_window",  # least share of the footprint in the edge returns' range window (0.5)
)
PARAM_INDEX = {name: i for i, name in enumerate(PARAM_NAMES)}
N_PARAMS = len(PARAM_NAMES)

#: Output columns of the kernel, one row per detection.
OUT_COLUMNS = 16  # cx, cy, r, cov (9, row-major over cx, cy, r), arc_deg, width, quality, n


def kernel_params(
    cfg: DetectorConfig,
    lo: float,
    hi: float,
    inc: float,
    first_beam: int,
    last_beam: int,
    wrap: bool,
) -> FloatArray:
    """``cfg`` as the kernel's parameter vector (:data:`PARAM_NAMES` order) for a scan gated
    to ``(lo, hi)`` metres with signed beam step ``inc`` radians and field of view
    ``first_beam`` to ``last_beam``; read-only."""
    # decisions the numpy path takes per batch, resolved once: the chi-square straightness
    # test and the fit's given sigma need sigma + sigma_rel * mean range > 0, which holds
    # for every segment exactly when sigma > 0 or sigma_rel > 0 (ranges are > 0)
    sigma_pos = cfg.sigma > 0 or cfg.sigma_rel > 0
    divergence = math.radians(cfg.beam_divergence_deg)
    values: dict[str, float] = {
        "lo": lo,
        "hi": hi,
        "median": cfg.median_filter,
        "wrap": wrap,
        "first_beam": first_beam,
        "last_beam": last_beam,
        "euclidean": cfg.segmentation == "euclidean",
        "max_jump": cfg.max_jump,
        "range_factor": cfg.range_factor,
        "max_skip": cfg.max_skip,
        "occlusion_margin": cfg.occlusion_margin,
        "pcur_on": cfg.point_curvature_min is not None,
        "pcur_min": cfg.point_curvature_min or 0.0,
        "rmed_on": cfg.radius_median is not None,
        "rmed": cfg.radius_median or 0.0,
        "split": cfg.split_merged,
        "min_points": cfg.min_points,
        "min_points_partial": cfg.min_points_partial,
        "max_points": math.inf if cfg.max_points is None else cfg.max_points,
        "min_width": cfg.min_width,
        "max_width": cfg.max_width,
        "min_depth": cfg.min_depth,
        "min_curvature": cfg.min_curvature,
        "max_curvature": cfg.max_curvature,
        "reject_straight": cfg.reject_straight,
        "straight_chi2": cfg.straight_test == "chi2" and sigma_pos,
        "straight_ratio": cfg.straight_ratio,
        "straight_min_points": cfg.straight_min_points,
        "drop_partial": cfg.drop_partial,
        "sigma": cfg.sigma,
        "sigma_rel": cfg.sigma_rel,
        "fit_sigma_given": sigma_pos,
        "min_radius": cfg.min_radius,
        "max_radius": cfg.max_radius,
        "max_radius_width_ratio": cfg.max_radius_width_ratio,
        "max_rms_sigma": cfg.max_rms_sigma,
        "divergence": divergence,
        "use_silhouette": cfg.neighbour_silhouette and divergence > 0,
        "range_model": _circle._check_residuals(cfg.fit_residuals),
        "angle_increment": inc,
        "sigma_from_data": cfg.sigma_from_data,
        "roughness_max_factor": cfg.roughness_max_factor,
        "rms_robust": cfg.rms_robust,
        "sigma_from_scan": cfg.sigma_from_scan,
        "scan_noise_jump": cfg.scan_noise_jump,
        "scan_noise_surface": cfg.scan_noise_surface,
        "bark_roughness": cfg.bark_roughness,
        "corners_on": cfg.split_corners,
        "corner_span": cfg.corner_span,
        "corner_depth": cfg.corner_depth,
        "corner_depth_convex": cfg.corner_depth_convex,
        "corner_sigmas": cfg.corner_sigmas,
        "gap_splits": cfg.gap_splits,
        "gap_ratio": cfg.gap_ratio,
        "gap_sigmas": cfg.gap_sigmas,
        "straight_depth_sigmas": cfg.straight_depth_sigmas,
        "refit_corners": cfg.refit_pieces and cfg.refit_split == "corners",
        "refit_validate": cfg.refit_validate,
        "arc_refit": cfg.arc_refit,
        "arc_sigmas": cfg.arc_sigmas,
        "arc_floor_sigmas": cfg.arc_floor_sigmas,
        "arc_replace": cfg.arc_replace,
        "arc_short_steps": cfg.arc_short_steps,
        "arc_tangent_sigmas": cfg.arc_tangent_sigmas,
        "arc_chi2": cfg.arc_chi2,
        "scan_noise_pool": cfg.sigma_from_scan and cfg.scan_noise_pool,
        "edge_hit_min": cfg.edge_hit_min,
        "edge_hit_max": cfg.edge_hit_max,
        "scan_noise_batch_min": cfg.scan_noise_batch_min(),
        "step_split": cfg.step_split,
        "step_noise_on": cfg.step_split and bool(cfg.step_noise_pool) and cfg.sigma_from_scan,
        "step_noise_pool": cfg.step_noise_pool != "batch",
        "step_noise_batch_min": _step_batch_min(cfg),
        "batch_noise_biweight": cfg.batch_noise_scale == "biweight",
        "edge_window": cfg.edge_window_share(),
    }
    prm = np.empty(N_PARAMS)
    for name, v in values.items():
        prm[PARAM_INDEX[name]] = float(v)
    prm.setflags(write=False)
    return prm


def _step_batch_min(cfg: DetectorConfig) -> float:
    """``batch_min`` of the step noise (``ScanTrunkDetector._step_noise``): 0 with
    ``step_noise_pool="batch"`` (every scan's pooled estimate where a scan has none), else the
    scan noise's own (``step_noise_pool=True`` with ``scan_noise_pool``: the step noise is the
    scan noise) or none (inf)."""
    if cfg.step_noise_pool == "batch":
        return 0.0
    return cfg.scan_noise_batch_min() if cfg.scan_noise_pool else math.inf
