"""Depth-assisted image-based mapping (DAIM, Munjer et al. 2025, §3.4).

Per detected box: aligned depth pixels -> 3D points -> clustering (the trunk is the tallest
cluster) -> the arc near the base of the trunk -> centre and radius from three boundary
points (perpendicular bisectors, Munjer eqs. 5-8,
:func:`stemmap.scan.circle.fit_circle_three_point`).
Our variant fits every arc point (``fit="ours"`` or any name in
:data:`stemmap.scan.circle.FIT_METHODS`) instead of three.

Depth images hold z-depth (distance along the optical axis), metres, NaN / 0 for no data,
aligned pixel-for-pixel with the colour image (as a RealSense "aligned depth" stream).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from sklearn.cluster import DBSCAN

from stemmap.errors import InputError
from stemmap.scan.circle import fit_circle
from stemmap.types import FloatArray, StemObservations
from stemmap.vision.camera import CameraModel, RigidTransform
from stemmap.vision.detector import boxes_xywh

__all__ = [
    "D435_DEPTH_NOISE_K",
    "MUNJER2025",
    "DaimParams",
    "arc_width",
    "base_arc",
    "cluster_trunk_points",
    "daim_trunks",
    "depth_to_points",
    "pixel_depth_limit",
]


#: RealSense D435 depth RMS error ``sigma = k z^2`` (m): subpixel 0.08 / (focal 447 px x
#: baseline 0.05 m) at 848 x 480 (Intel's depth-camera tuning guide formula), the paper's camera.
D435_DEPTH_NOISE_K = 0.08 / (447.0 * 0.05)


@dataclass(frozen=True)
class DaimParams:
    """Parameters of DAIM (Munjer 2025 prints none of these; values are ours).

    Parameters
    ----------
    stride : int -- use every ``stride``-th pixel of the box (speed)
    max_depth : float, metres -- ignore trunks beyond (RealSense-class sensors: ~10 m): a
        box's trunk cluster whose median z-depth is at or beyond it gives no detection; its
        pixels are read up to :func:`pixel_depth_limit` (three noise sigmas further), so the
        cut does not truncate the noise of a trunk near it
    eps, min_samples : DBSCAN radius (m) and core size
    base_band : float, metres -- height of the "arc near the base" slice above the cluster's
        lowest point
    base_offset : float, metres -- skip this much above the lowest point (ground contact)
    arc_bins : int -- azimuth bins across the arc
    arc_point : "median" or "nearest" -- what each bin keeps: the point at the median range
        (default; robust to depth noise, which grows as z^2 on a stereo RealSense) or the
        nearest point (the surface when depth is exact, but biased towards the camera by ~2
        sigma of the noise). Munjer 2025 says only "three boundary points are extracted".
    fit : str -- "three_point" (Munjer) or any name in ``stemmap.scan.circle.FIT_METHODS``
    max_width_ratio : float or None -- a fit whose diameter exceeds this multiple of the arc's
        visible width (its bearing span times its median range) gets no radius (NaN): a
        cylinder's visible arc is as wide as the trunk, so a much larger circle is the depth
        noise flattening the arc (three points, D435 noise 0.18 m at 7 m against a 0.1 m
        sagitta), not the trunk; so does a fit whose centre is not behind the arc's middle
        point (:func:`~stemmap.vision._daim_noise.centre_behind_arc`: the noise bent the arc
        towards the camera, and the near side of a convex trunk cannot be seen hollow; 7-22 %
        of the fits of a 0.3 m trunk at 7-11 m, their centres 0.15-0.2 m short). Such a
        detection's centre is then the arc's middle point plus half the
        visible width along the ray (:func:`stemmap.vision._daim_noise.surface_centre`), and
        with ``cov_noise_k`` every fit's covariance is bounded by the trunk's geometry (the
        centre one radius of at most ``max_width_ratio`` x width / 2 behind the arc,
        :func:`~stemmap.vision._daim_noise.physical_bound`). None keeps every radius and
        three-point centre, covariances unbounded. Ours: Munjer 2025 prints no check and
        reports no diameters.
    depth_noise_k : float or None -- the sensor's depth noise ``sigma = k z^2`` (m); with it the
        DBSCAN radius of a box is ``max(eps, 2 k z^2)`` at the box's median depth z, so a far
        trunk's scattered depth still forms one cluster. None: ``eps`` at every depth. Ours:
        Munjer 2025 prints no clustering parameters.
    cov_noise_k : float or None -- the depth-noise model ``sigma = k z^2`` (m) each detection's
        covariance (``StemObservations.covs``, centre x, y and radius) is propagated from
        (:func:`stemmap.vision._daim_noise.fit_covariance`: along-ray ``k rho^2`` per arc point,
        the pixel column across it, through the fit). Default the D435's
        (:data:`D435_DEPTH_NOISE_K`, the paper's camera). None: NaN covariances. Ours: Munjer
        2025 gives detections no covariance. Only a back end that asks for them uses them
        (:class:`stemmap.slam.munjer.MunjerMapConfig` ``detection_noise``).
    """

    stride: int = 2
    max_depth: float = 12.0
    eps: float = 0.1
    min_samples: int = 8
    base_band: float = 0.3
    base_offset: float = 0.1
    arc_bins: int = 24
    arc_point: str = "median"
    fit: str = "three_point"
    max_width_ratio: float | None = None
    depth_noise_k: float | None = None
    cov_noise_k: float | None = D435_DEPTH_NOISE_K


#: DAIM as run in the Munjer pipeline (our additions, the paper prints none of them):
#: implausible three-point circles (too wide, or bulging away from the camera) carry no
#: diameter, the clustering radius is scaled by
#: the D435's depth-noise model (``depth_noise_k``), and every detection carries its
#: depth-model covariance (``cov_noise_k``), which the Munjer back end weighs it by
#: (:class:`stemmap.slam.munjer.MunjerMapConfig` ``detection_noise``). Chosen on simulated
#: drives with the simulator's D435 model only (docs/algorithms/vision-fusion.md, item 12;
#: docs/algorithms/cloud.md, "DAIM: per-detection noise"); ``replace(MUNJER2025,
#: depth_noise_k=None)`` is the fixed 0.1 m radius.
MUNJER2025 = DaimParams(max_width_ratio=1.5, depth_noise_k=D435_DEPTH_NOISE_K)


def pixel_depth_limit(params: DaimParams) -> float:
    """Depth (m) up to which :func:`daim_trunks` reads a box's pixels: ``max_depth`` plus three
    times the depth noise there, ``max_depth + 3 k max_depth^2`` (``k`` the params' depth-noise
    model, ``depth_noise_k`` or else ``cov_noise_k``; ``max_depth`` without one).

    ``max_depth`` limits the *trunk* (the median depth of its cluster), not its pixels: cutting
    every pixel at ``max_depth`` keeps only the near side of the noise of a trunk near the
    limit, so its median and arc are pulled towards the camera (D435 model, k = 0.0036: a trunk
    at z = 12 m by -0.36 m, at 12.5 m by -0.75 m, and one at 13 m still detected -- from its
    noise's near tail -- 1.2 m short; docs/algorithms/cloud.md, "DAIM: the depth cut"). Three
    sigma leaves a trunk at ``max_depth`` 0.13 % of its pixels cut.

    Examples
    --------
    >>> round(pixel_depth_limit(MUNJER2025), 2)
    13.55
    >>> pixel_depth_limit(DaimParams(cov_noise_k=None))
    12.0
    """
    k = params.depth_noise_k if params.depth_noise_k is not None else params.cov_noise_k
    m = params.max_depth
    if k is None or not math.isfinite(m):
        return m
    return m + 3.0 * k * m**2


def depth_to_points(
    depth: ArrayLike,
    camera: CameraModel,
    box: ArrayLike,
    *,
    stride: int = 1,
    max_depth: float = math.inf,
) -> FloatArray:
    """Back-project the depth pixels inside ``box`` (x, y, w, h) to camera-frame 3D points.

    Y = (v - cy) Z / fy, X = ((u - cx) Z - s Y) / fx, Z = depth (pinhole with skew s, no
    distortion).

    Returns
    -------
    (N, 3) metres, camera frame (x right, y down, z forward); pixels without depth dropped.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2 or d.shape != (camera.height, camera.width):
        raise InputError(
            f"depth must have the camera's shape ({camera.height}, {camera.width}), got {d.shape}."
        )
    b = boxes_xywh(box)[0]
    x0, y0 = max(0, int(b[0])), max(0, int(b[1]))
    x1, y1 = (
        min(d.shape[1], math.ceil(b[0] + b[2])),
        min(d.shape[0], math.ceil(b[1] + b[3])),
    )
    if x1 <= x0 or y1 <= y0:
        return np.zeros((0, 3))
    s = max(1, int(stride))
    vv, uu = np.mgrid[y0:y1:s, x0:x1:s]
    z = d[vv, uu]
    ok = np.isfinite(z) & (z > 0) & (z < max_depth)
    z, uu, vv = z[ok], uu[ok], vv[ok]
    K = camera.K
    y = (vv - K[1, 2]) * z / K[1, 1]
    x = ((uu - K[0, 2]) * z - K[0, 1] * y) / K[0, 0]
    return np.column_stack((x, y, z))


def cluster_trunk_points(
    points_body: ArrayLike, *, eps: float = 0.1, min_samples: int = 8
) -> NDArray[np.bool_]:
    """DBSCAN the box's points (z-up frame) and keep the trunk cluster: the one with the
    largest vertical extent (a box also holds ground, background and occluders; the trunk it
    was drawn around is the tallest structure in it; among clusters at least 70 % as tall as
    the tallest, the one with the most points wins, i.e. the trunk the box was drawn around
    rather than one seen through the gap). Munjer (2025) names the clustering but not the
    selection rule; this rule is ours."""
    p = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
    keep = np.zeros(p.shape[0], bool)
    if p.shape[0] < min_samples:
        return keep
    lab = DBSCAN(eps=eps, min_samples=min_samples).fit_predict(p)
    ids = np.unique(lab[lab >= 0])
    if ids.size == 0:
        return keep
    extent = np.array([np.ptp(p[lab == i, 2]) for i in ids])
    size = np.array([np.count_nonzero(lab == i) for i in ids])
    tall = extent >= 0.7 * extent.max()
    best = ids[tall][int(np.argmax(size[tall]))]
    return np.asarray(lab == best)


def base_arc(
    points_body: ArrayLike,
    origin_xy: ArrayLike,
    *,
    band: float = 0.3,
    offset: float = 0.1,
    bins: int = 24,
    point: str = "nearest",
) -> FloatArray:
    """The visible arc near the base of a trunk cluster, in the horizontal plane.

    Parameters
    ----------
    points_body : (N, 3) metres in a frame with z up (e.g. the laser frame)
    origin_xy : (2,) camera position in that frame (the arc is what faces it)
    band, offset : the slice [z_min + offset, z_min + offset + band]
    bins : azimuth bins; each keeps one point
    point : "nearest" (the point nearest to the origin: the surface, not the scatter behind it)
        or "median" (the point of median range in the bin: robust to depth noise)

    Returns
    -------
    (M, 2) arc points ordered by bearing from ``origin_xy``
    """
    if point not in ("nearest", "median"):
        raise InputError(f"base_arc point must be 'nearest' or 'median', got {point!r}.")
    p = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(origin_xy, dtype=np.float64).reshape(2)
    if p.shape[0] == 0:
        return np.zeros((0, 2))
    z0 = float(p[:, 2].min()) + offset
    sl = p[(p[:, 2] >= z0) & (p[:, 2] <= z0 + band)]
    if sl.shape[0] < 3:
        return np.zeros((0, 2))
    rel = sl[:, :2] - o
    az = np.arctan2(rel[:, 1], rel[:, 0])
    rr = np.hypot(rel[:, 0], rel[:, 1])
    edges = np.linspace(az.min(), az.max() + 1e-12, bins + 1)
    k = np.clip(np.searchsorted(edges, az, side="right") - 1, 0, bins - 1)
    order = np.lexsort((rr, k))
    ks = k[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    if point == "nearest":
        pick = order[start]
    else:
        count = np.diff(np.r_[start, ks.size])
        pick = order[start + (count - 1) // 2]
    pick = pick[np.argsort(az[pick])]
    return np.asarray(sl[pick, :2])


def arc_width(arc: ArrayLike, origin_xy: ArrayLike) -> float:
    """Visible width (m) of an arc seen from ``origin_xy``: its bearing span (rad) times its
    median range. A cylinder of diameter D at range rho shows an arc D sqrt(1 - (D / 2 rho)^2)
    wide, and a circle through the arc's ends is at least that wide.

    Examples
    --------
    >>> a = np.array([[5.0, -0.1], [4.9, 0.0], [5.0, 0.1]])
    >>> round(arc_width(a, [0.0, 0.0]), 3)
    0.2
    """
    rel = np.asarray(arc, dtype=np.float64).reshape(-1, 2) - np.asarray(origin_xy, float)
    bear = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    return float(np.ptp(bear) * np.median(np.hypot(rel[:, 0], rel[:, 1])))


def daim_trunks(
    depth: ArrayLike,
    camera: CameraModel,
    boxes: ArrayLike,
    *,
    camera_to_body: RigidTransform | None = None,
    params: DaimParams = MUNJER2025,
    time: float = 0.0,
) -> StemObservations:
    """Trunk centres and radii from detector boxes and aligned depth (Munjer 2025, §3.4).

    Parameters
    ----------
    depth : (H, W) z-depth, metres
    camera : CameraModel
    boxes : (R, 4) x, y, w, h pixels (from a :class:`~stemmap.vision.detector.TrunkDetector`)
    camera_to_body : RigidTransform, optional
        Camera -> a z-up body frame (e.g. ``laser_to_camera.inverse()``); without it the camera
        frame's (x, z) plane is taken as horizontal (a level camera).

    Returns
    -------
    StemObservations in the body frame (``frame="laser"`` if ``camera_to_body`` is given,
    else "camera_level"), ``source="vision:munjer2025:<fit>"``; boxes where no cluster or arc
    or fit was found, and trunks whose cluster's median depth is at or beyond
    ``params.max_depth``, are skipped; a fit failing the width check
    (``params.max_width_ratio``) or with its centre on the camera's side of the arc has radius
    NaN and its centre half the arc's visible width behind the arc's middle point (not the
    fit's). ``index`` is the box index.
    ``covs`` (k, 3, 3): each fit's (centre x, centre y, radius) covariance from the depth-noise
    model ``params.cov_noise_k`` (NaN without one), body frame.
    """
    b = boxes_xywh(boxes)
    from stemmap.vision._daim_noise import (
        bound_covariance,
        centre_behind_arc,
        fit_covariance,
        physical_bound,
        surface_centre,
    )

    centers, radii, npts, arcs, idx, covs = [], [], [], [], [], []
    pixel_angle = params.stride / float(camera.K[0, 0])
    pixel_limit = pixel_depth_limit(params)
    origin = camera_to_body.t[:2] if camera_to_body is not None else np.zeros(2)
    for i, box in enumerate(b):
        pc = depth_to_points(depth, camera, box, stride=params.stride, max_depth=pixel_limit)
        if pc.shape[0] < params.min_samples:
            continue
        if camera_to_body is not None:
            body = camera_to_body.apply(pc)
        else:  # level camera: x right, y down, z forward -> x forward, y left, z up
            body = np.column_stack((pc[:, 2], -pc[:, 0], -pc[:, 1]))
        eps = params.eps
        if params.depth_noise_k is not None:
            eps = max(eps, 2.0 * params.depth_noise_k * float(np.median(pc[:, 2])) ** 2)
        keep = cluster_trunk_points(body, eps=eps, min_samples=params.min_samples)
        if not keep.any() or float(np.median(pc[keep, 2])) >= params.max_depth:
            continue  # max_depth limits the trunk, not its pixels (see pixel_depth_limit)
        body = body[keep]
        arc = base_arc(
            body,
            origin,
            band=params.base_band,
            offset=params.base_offset,
            bins=params.arc_bins,
            point=params.arc_point,
        )
        if arc.shape[0] < 3:
            continue
        fit = fit_circle(arc, params.fit, origin=origin)
        if not fit:
            continue
        radius = fit.radius
        w_arc = arc_width(arc, origin)
        # not a trunk's circle: wider than the arc allows, or on the camera's side of the arc
        # (the visible side of a convex trunk bulges towards the camera)
        implausible = params.max_width_ratio is not None and (
            2.0 * radius > params.max_width_ratio * w_arc
            or not centre_behind_arc(arc, fit.center, origin)
        )
        center = fit.center
        if implausible:
            radius = math.nan
        rel = arc - fit.center
        ang = np.degrees(np.ptp(np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))))
        cov = np.full((3, 3), np.nan)
        if params.cov_noise_k is not None:
            cov = fit_covariance(
                arc,
                fit.center,
                origin,
                params.fit,
                depth_noise_k=params.cov_noise_k,
                pixel_angle=pixel_angle,
            )
        if params.max_width_ratio is not None:
            # a trunk's centre is one radius (at most the width check's) behind its arc: the
            # first-order covariance of a nearly collinear arc is bounded by that, and an
            # implausible fit's centre is the arc's middle point plus half its width
            # (_daim_noise)
            if implausible:
                center = surface_centre(arc, origin, 0.5 * w_arc)
            if params.cov_noise_k is not None:
                bound = physical_bound(
                    arc, origin, 0.5 * params.max_width_ratio * w_arc,
                    depth_noise_k=params.cov_noise_k, pixel_angle=pixel_angle,
                    keep_cross=None if implausible else cov,
                )  # fmt: skip
                cov = bound if implausible else bound_covariance(cov, bound)
        centers.append(center)
        covs.append(cov)
        radii.append(radius)
        npts.append(arc.shape[0])
        arcs.append(ang)
        idx.append(i)
    k = len(idx)
    if k == 0:
        return StemObservations.empty(
            source=f"vision:munjer2025:{params.fit}",
            frame="laser" if camera_to_body is not None else "camera_level",
        )
    return StemObservations(
        centers=np.asarray(centers),
        radii=np.asarray(radii),
        covs=np.asarray(covs),
        n_points=np.asarray(npts),
        arc_deg=np.asarray(arcs),
        widths=np.full(k, np.nan),
        quality=np.ones(k),
        index=np.asarray(idx),
        times=np.full(k, float(time)),
        source=f"vision:munjer2025:{params.fit}",
        frame="laser" if camera_to_body is not None else "camera_level",
    )
