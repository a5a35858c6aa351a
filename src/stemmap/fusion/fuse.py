"""Decision-level laser + vision fusion: Xue et al. (2018) and ours.

:func:`fuse_xue2018` reproduces the paper (§2.4, §3.2.4): laser BPA from width (eq. 13), vision
BPA from the matching level (eqs. 14-15), Dempster's rule (eq. 16), decision (eq. 17); a region
seen by one sensor only gets m(T) = 0, m(NT) = 1 from the other.

:func:`fuse_ours` adds, as separate evidence:

0. *a tentative laser BPA* (:func:`stemmap.fusion.bpa.laser_bpa_ours`): a trunk-like width
   puts 0.65 on T and 0.25 on ignorance instead of Xue's 0.9 on T;
1. *reliability discounting* (Shafer): the laser mass is discounted by beta_l = min(1, n / n_ref)
   (few returns -> unreliable width), the vision mass by beta_v(range), falling linearly from 1 at
   ``range_near`` to ``beta_far`` at ``range_far`` (small, far regions);
2. *diameter agreement*: for a matched pair, the trunk diameter measured from the region's edges
   (:func:`stemmap.vision.edges.measure_diameter`, with the laser's range and width bounds) is
   compared with the laser width; agreement supports T, disagreement NT;
3. *strip evidence for laser RoIs without a region*: the fraction of trunk-coloured pixels
   (Xue's RGB rules) in the image strip above the RoI's projection is weak evidence, instead of
   the paper's certain "not a trunk" -- the segmentation misses trunks that touch a bush or
   another trunk (their regions are merged and not taller than wide).

Vision regions without laser support keep the paper's rule (m(T) = 0, m(NT) = 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import ConfigError
from stemmap.fusion.associate import Association, LaserRois, associate, project_rois
from stemmap.fusion.bpa import (
    PRESETS,
    BpaParams,
    laser_bpa,
    laser_bpa_ours,
    no_support_mass,
    vision_bpa,
)
from stemmap.fusion.evidence import Mass, combine_dempster, decide_xue2018
from stemmap.types import FloatArray
from stemmap.vision.camera import CameraModel, RigidTransform
from stemmap.vision.edges import COLOUR_PCA, measure_diameter
from stemmap.vision.segment import Regions, rgb_trunk_mask

__all__ = [
    "FusionParams",
    "FusionResult",
    "discount",
    "fuse_ours",
    "fuse_xue2018",
]


def discount(m: Mass, beta: ArrayLike) -> Mass:
    """Shafer discounting: m'(A) = beta m(A) for A != Omega, m'(Omega) = 1 - beta + beta m(Omega).

    ``beta`` in [0, 1] is the reliability of the source (1: fully reliable, 0: vacuous)."""
    b = np.clip(np.asarray(beta, dtype=np.float64), 0.0, 1.0)
    return Mass(b * m.t, b * m.nt, 1.0 - b + b * m.theta)


@dataclass(frozen=True)
class FusionParams:
    """Parameters of :func:`fuse_ours` (all ours unless noted).

    bpa : BPA preset or params (eq. 13-15 constants)
    eps1, eps2 : eq. 17 thresholds (Xue: 0.1 and 0.1). Discounting leaves some ignorance on
        far or sparsely hit trunks, so ours accepts m(Omega) < 0.2.
    n_ref : laser returns at which the laser is fully reliable
    range_near, range_far, beta_far : vision reliability ramp (metres, metres, [0, 1])
    k_diam : maximum mass of the diameter-agreement evidence
    sigma_rel : relative std of (edge diameter - laser width) / laser width for a true trunk
        (edge ~8 %, laser chord under-estimates by up to ~15 % at few returns)
    k_strip : maximum mass of the strip evidence for laser RoIs without a region
    k_t : in-band laser belief in T (:func:`stemmap.fusion.bpa.laser_bpa_ours`)
    strip_height : metres of trunk above the laser plane inspected in the strip
    min_iou : association threshold
    """

    bpa: BpaParams | str = "forest"
    eps1: float = 0.1
    eps2: float = 0.2
    n_ref: int = 6
    range_near: float = 6.0
    range_far: float = 15.0
    beta_far: float = 0.6
    k_diam: float = 0.6
    sigma_rel: float = 0.2
    k_strip: float = 0.9
    k_t: float = 0.65
    strip_height: float = 0.5
    min_iou: float = 0.2

    def bpa_params(self) -> BpaParams:
        if isinstance(self.bpa, str):
            try:
                return PRESETS[self.bpa]
            except KeyError:
                raise ConfigError(
                    f"unknown BPA preset {self.bpa!r}; choose one of {sorted(PRESETS)}."
                ) from None
        return self.bpa


@dataclass(frozen=True, eq=False)
class FusionResult:
    """One fused decision per object (matched pair, laser-only RoI or vision-only region).

    Attributes
    ----------
    laser_index, region_index : (N,) int, -1 where the sensor has no part
    m_laser, m_vision, m_fused : Mass batches (N,)
    conflict : (N,) K of eq. 16
    is_trunk : (N,) bool -- eq. 17 on m_fused
    centers : (N, 2) metres, laser frame (laser RoI centre; NaN for vision-only objects)
    diameters : (N,) metres (laser width, or the edge diameter in ours when measured)
    association : the underlying :class:`Association`
    laser_only_trunk, vision_only_trunk : decisions of each sensor alone (eq. 17 on its own
        mass) over *its* objects, for comparison
    """

    laser_index: NDArray[np.int64]
    region_index: NDArray[np.int64]
    m_laser: Mass
    m_vision: Mass
    m_fused: Mass
    conflict: FloatArray
    is_trunk: NDArray[np.bool_]
    centers: FloatArray
    diameters: FloatArray
    association: Association
    laser_only_trunk: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    vision_only_trunk: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))

    def __len__(self) -> int:
        return int(self.laser_index.shape[0])


def _layout(assoc: Association) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    li = np.concatenate((assoc.pairs[:, 0], assoc.laser_only, np.full(len(assoc.vision_only), -1)))
    ri = np.concatenate((assoc.pairs[:, 1], np.full(len(assoc.laser_only), -1), assoc.vision_only))
    return li.astype(np.int64), ri.astype(np.int64)


def _stack(parts: list[Mass]) -> Mass:
    return Mass(
        np.concatenate([p.t.reshape(-1) for p in parts]),
        np.concatenate([p.nt.reshape(-1) for p in parts]),
        np.concatenate([p.theta.reshape(-1) for p in parts]),
    )


def _roi_centers(rois: LaserRois, li: NDArray[np.int64]) -> FloatArray:
    """(N, 2) laser RoI centre of each fused object; NaN rows for vision-only objects.

    Always (N, 2), also when the scan had no laser RoI at all (an empty scan: issue 13).
    """
    out = np.full((li.shape[0], 2), np.nan)
    if len(rois):
        has = li >= 0
        out[has] = np.asarray(rois.centers)[li[has]]
    return out


def _pick(m: Mass, idx: NDArray[np.int64], fallback: Mass) -> Mass:
    """Rows ``idx`` of ``m``; rows with idx < 0 take ``fallback`` (a scalar mass)."""
    ok = idx >= 0
    safe = np.where(ok, idx, 0)
    if len(m) == 0:
        t = np.full(idx.shape, float(fallback.t))
        return Mass(
            t, np.full(idx.shape, float(fallback.nt)), np.full(idx.shape, float(fallback.theta))
        )
    return Mass(
        np.where(ok, m.t[safe], fallback.t),
        np.where(ok, m.nt[safe], fallback.nt),
        np.where(ok, m.theta[safe], fallback.theta),
    )


def fuse_xue2018(
    rois: LaserRois,
    regions: Regions,
    G: ArrayLike,
    *,
    image_width: int | None = None,
    bpa: BpaParams | str = "xue2018",
    eps1: float = 0.1,
    eps2: float = 0.1,
    min_iou: float = 0.2,
) -> FusionResult:
    """Xue et al. (2018) decision-level fusion (§2.4, §3.2.4), see the module docstring.

    Laser RoIs inside the image without a region get the vision mass m(T) = 0, m(NT) = 1 (the
    paper's rule for region 5, applied symmetrically).
    """
    assoc = associate(rois, regions, G, image_width=image_width, min_iou=min_iou)
    li, ri = _layout(assoc)
    ml_all = laser_bpa(rois.widths, bpa)
    mv_all = (
        vision_bpa(regions.alpha, bpa)
        if len(regions)
        else Mass(np.zeros(0), np.zeros(0), np.zeros(0))
    )
    ns = no_support_mass()
    ml = _pick(ml_all, li, ns)
    mv = _pick(mv_all, ri, ns)
    comb = combine_dempster(ml, mv)
    dec = decide_xue2018(comb.mass, eps1=eps1, eps2=eps2) & comb.ok
    centers = _roi_centers(rois, li)
    diam = np.where(li >= 0, rois.widths[np.maximum(li, 0)] if len(rois) else np.nan, np.nan)
    return FusionResult(
        li,
        ri,
        ml,
        mv,
        comb.mass,
        comb.conflict,
        dec,
        centers,
        diam,
        assoc,
        laser_only_trunk=decide_xue2018(ml_all, eps1=eps1, eps2=eps2),
        vision_only_trunk=decide_xue2018(mv_all, eps1=eps1, eps2=eps2),
    )


def _strip_fraction(
    image: NDArray[np.uint8], umin: float, umax: float, v: float, height_px: float
) -> float:
    H, W = image.shape[:2]
    x0, x1 = max(0, math.floor(umin)), min(W, math.ceil(umax) + 1)
    y1 = min(H, round(v))
    y0 = max(0, round(v - height_px))
    if x1 <= x0 or y1 <= y0:
        return math.nan
    return float(rgb_trunk_mask(image[y0:y1, x0:x1], "xue2018").mean())


def fuse_ours(
    rois: LaserRois,
    regions: Regions,
    G: ArrayLike,
    image: NDArray[np.uint8],
    camera: CameraModel,
    *,
    laser_to_camera: RigidTransform | None = None,
    params: FusionParams | None = None,
) -> FusionResult:
    """Our fusion (module docstring): Xue's BPAs + reliability discounting, diameter agreement
    from image edges, and strip evidence for laser RoIs without a region."""
    p = params or FusionParams()
    bp = p.bpa_params()
    W = image.shape[1]
    assoc = associate(rois, regions, G, image_width=W, min_iou=p.min_iou)
    li, ri = _layout(assoc)
    n = len(li)
    ns = no_support_mass()
    # 1. Laser evidence, discounted by the number of returns.
    ml_raw = laser_bpa(rois.widths, bp)
    beta_l = np.minimum(1.0, rois.n_points / float(p.n_ref))
    ml_all = discount(laser_bpa_ours(rois.widths, bp, k_t=p.k_t), beta_l)
    ml = _pick(ml_all, li, ns)
    # 2. Vision evidence, discounted by range (regions without laser: no range -> 1).
    mv_raw = (
        vision_bpa(regions.alpha, bp)
        if len(regions)
        else Mass(np.zeros(0), np.zeros(0), np.zeros(0))
    )
    mv = _pick(mv_raw, ri, ns)
    rng_obj = np.where(li >= 0, rois.ranges[np.maximum(li, 0)] if len(rois) else np.nan, np.nan)
    ramp = np.clip((rng_obj - p.range_near) / (p.range_far - p.range_near), 0.0, 1.0)
    beta_v = np.where(np.isfinite(rng_obj), 1.0 - (1.0 - p.beta_far) * ramp, 1.0)
    paired = (li >= 0) & (ri >= 0)
    laser_alone = (li >= 0) & (ri < 0)
    # 3. Strip evidence for laser RoIs without a region.
    umin, umax, vmed = project_rois(rois, G)
    t_v, nt_v, th_v = mv.t.copy(), mv.nt.copy(), mv.theta.copy()
    for k in np.flatnonzero(laser_alone):
        j = li[k]
        h_px = camera.fy * p.strip_height / max(float(rois.ranges[j]), 0.1)
        f = _strip_fraction(image, umin[j], umax[j], vmed[j], h_px)
        if math.isfinite(f):
            t_v[k], nt_v[k], th_v[k] = p.k_strip * f, p.k_strip * (1 - f), 1 - p.k_strip
    mv = discount(Mass(t_v, nt_v, th_v), np.where(paired | laser_alone, beta_v, 1.0))
    comb = combine_dempster(ml, mv)
    fused = comb.mass
    conflict = comb.conflict.copy()
    ok = comb.ok.copy()
    # 4. Diameter agreement for matched pairs.
    diam = np.where(li >= 0, rois.widths[np.maximum(li, 0)] if len(rois) else np.nan, np.nan)
    t3, nt3, th3 = np.zeros(n), np.zeros(n), np.ones(n)
    for k in np.flatnonzero(paired):
        j, r = li[k], ri[k]
        w = float(rois.widths[j])
        rng_j = float(rois.ranges[j])
        # Search the region's columns widened by the laser's maximum width on both sides.
        pad = camera.fx * (bp.w_max + bp.dw) / max(rng_j, 0.1)
        yc = regions.y[r] + regions.h[r] / 2.0
        box = (
            regions.x[r] - pad,
            yc - regions.h[r] / 4.0,
            regions.w[r] + 2 * pad,
            max(regions.h[r] / 2.0, 6.0),
        )
        e = measure_diameter(
            image,
            box,
            rng_j,
            (max(bp.w_min - bp.dw, 0.01), bp.w_max + bp.dw),
            camera,
            COLOUR_PCA,
            laser_to_camera=laser_to_camera,
        )
        if e:
            z = (e.diameter - w) / (p.sigma_rel * max(w, 1e-3))
            g = math.exp(-0.5 * z * z)
            t3[k], nt3[k], th3[k] = p.k_diam * g, p.k_diam * (1 - g), 1 - p.k_diam
            diam[k] = 0.5 * (e.diameter + w)
        else:
            t3[k], nt3[k], th3[k] = 0.0, 0.2, 0.8
    comb3 = combine_dempster(fused, Mass(t3, nt3, th3))
    fused = comb3.mass
    ok &= comb3.ok
    conflict = 1 - (1 - conflict) * (1 - comb3.conflict)
    dec = decide_xue2018(fused, eps1=p.eps1, eps2=p.eps2) & ok
    centers = _roi_centers(rois, li)
    return FusionResult(
        li,
        ri,
        ml,
        mv,
        fused,
        conflict,
        dec,
        centers,
        diam,
        assoc,
        laser_only_trunk=decide_xue2018(ml_raw, eps1=p.eps1, eps2=p.eps2),
        vision_only_trunk=decide_xue2018(mv_raw, eps1=p.eps1, eps2=p.eps2),
    )
