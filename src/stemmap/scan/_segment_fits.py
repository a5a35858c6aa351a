"""The numpy pipeline's circle fits of candidate segments and the columns derived from them
(:class:`~stemmap.scan.detect.ScanTrunkDetector`): batched Kasa, the other methods through
:func:`stemmap.scan.circle.fit_circles_batch`, fit RMS, the geometric covariance fallback, arc
extent, quality and the output columns of the kept candidates; :func:`fit_candidates`, every
candidate's fit with what the plausibility tests read (the body of
``ScanTrunkDetector._fit_candidates``, moved here from :mod:`stemmap.scan.detect`). The compiled
kernel (:mod:`stemmap.scan._detect_fast`) repeats these expressions."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stemmap.scan import circle as _circle
from stemmap.scan._centre_cov import centre_covs, noise_factors
from stemmap.scan._fast_robust import segment_step_medians
from stemmap.scan._lobed import lobed_refit
from stemmap.scan.features import (
    edge_silhouette,
    first_echo_edge_prior,
    segment_sum,
    segment_widths,
)
from stemmap.scan.plausibility import (
    own_noise,
    range_roughness,
    residual_smoothness,
    robust_residual_scale,
    segment_sigma,
)
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig


def fit_kasa_segments(segs: Segments) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Kasa algebraic circle fit of every segment at once (same algebra as
    :func:`stemmap.scan.circle.fit_circle_kasa`, solved as one batched 3x3 system).

    Each segment is centred and scaled (RMS distance 1) before forming the normal equations of
    ``x^2 + y^2 + D x + E y + F = 0``.

    Returns
    -------
    centers : ndarray of shape (K, 2), metres (NaN where the fit failed)
    radii : ndarray of shape (K,), metres (NaN where the fit failed)
    ok : ndarray of shape (K,), bool -- False for < 3 returns, collinear or degenerate segments
    """
    k = len(segs)
    if k == 0:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0, dtype=bool)
    p = segs.points
    lab = segs.labels
    n = segs.counts.astype(np.float64)
    mx = segment_sum(p.x, segs) / n
    my = segment_sum(p.y, segs) / n
    qx = p.x - mx[lab]
    qy = p.y - my[lab]
    q2 = qx * qx + qy * qy
    s2 = segment_sum(q2, segs) / n
    scale = np.sqrt(s2)
    good = (segs.counts >= 3) & (scale > 0)
    sc = np.where(good, scale, 1.0)
    qx = qx / sc[lab]
    qy = qy / sc[lab]
    q2 = qx * qx + qy * qy
    sxx = segment_sum(qx * qx, segs)
    syy = segment_sum(qy * qy, segs)
    sxy = segment_sum(qx * qy, segs)
    bx = -segment_sum(qx * q2, segs)
    by = -segment_sum(qy * q2, segs)
    bz = -segment_sum(q2, segs)
    # centred: sum qx = sum qy = 0, so the system decouples into a 2x2 for (D, E) and F = bz / n
    det = sxx * syy - sxy * sxy
    tr = sxx + syy
    good &= det > 1e-9 * np.maximum(tr, 1e-300) ** 2
    dsafe = np.where(good, det, 1.0)
    D = (syy * bx - sxy * by) / dsafe
    E = (sxx * by - sxy * bx) / dsafe
    F = bz / n
    cx, cy = -D / 2.0, -E / 2.0
    r2 = cx * cx + cy * cy - F
    good &= r2 > 0
    radius = np.where(good, np.sqrt(np.where(good, r2, 1.0)) * sc, np.nan)
    centers = np.column_stack(
        (np.where(good, cx * sc + mx, np.nan), np.where(good, cy * sc + my, np.nan))
    )
    return centers, radius, good


def _fit_rms(segs: Segments, centers: FloatArray, radii: FloatArray) -> FloatArray:
    """RMS orthogonal residual of every segment's returns to its fitted circle, metres."""
    p = segs.points
    lab = segs.labels
    res = np.hypot(p.x - centers[lab, 0], p.y - centers[lab, 1]) - radii[lab]
    out: FloatArray = np.sqrt(segment_sum(res * res, segs) / segs.counts)
    return out


def _geometric_cov(
    segs: Segments, centers: FloatArray, radii: FloatArray, sigma: float | FloatArray
) -> FloatArray:
    """Covariance over (x, y, r) of every fitted circle from the orthogonal-distance Jacobian,
    ``s^2 (J^T J)^-1`` with ``s^2 = max(sigma^2, sum res^2 / (n - 3))`` (NaN if singular)."""
    k = len(segs)
    p = segs.points
    lab = segs.labels
    dx = p.x - centers[lab, 0]
    dy = p.y - centers[lab, 1]
    d = np.hypot(dx, dy)
    dsafe = np.where(d > 0, d, 1.0)
    ux, uy = dx / dsafe, dy / dsafe
    res = d - radii[lab]
    n = segs.counts.astype(np.float64)
    rss = segment_sum(res * res, segs)
    sig = np.asarray(sigma, dtype=np.float64)
    s2 = np.maximum(sig * sig, np.where(n > 3, rss / np.maximum(n - 3, 1), 0.0))
    JtJ = np.empty((k, 3, 3))
    JtJ[:, 0, 0] = segment_sum(ux * ux, segs)
    JtJ[:, 1, 1] = segment_sum(uy * uy, segs)
    JtJ[:, 0, 1] = JtJ[:, 1, 0] = segment_sum(ux * uy, segs)
    JtJ[:, 0, 2] = JtJ[:, 2, 0] = segment_sum(ux, segs)
    JtJ[:, 1, 2] = JtJ[:, 2, 1] = segment_sum(uy, segs)
    JtJ[:, 2, 2] = n
    cov = np.full((k, 3, 3), np.nan)
    detj = np.linalg.det(JtJ) if k else np.zeros(0)
    inv_ok = np.isfinite(detj) & (np.abs(detj) > 1e-12 * np.maximum(n, 1.0) ** 3)
    if np.any(inv_ok):
        cov[inv_ok] = np.linalg.inv(JtJ[inv_ok]) * s2[inv_ok, None, None]
    return cov


def _fit_segments(
    segs: Segments,
    method: str,
    sigma: FloatArray,
    *,
    silhouette: FloatArray | None = None,
    beam_divergence: float = 0.0,
    residuals: str = "range",
    edge_window: float = 0.5,
) -> tuple[FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Fit every segment with ``method``: centers (K, 2), radii (K,), covs (K, 3, 3), ok (K,).

    Kasa runs as one vectorised solve (:func:`fit_kasa_segments`); every other method goes
    through :func:`stemmap.scan.circle.fit_circles_batch` (compiled loop for "ours"), with the
    sensor at the origin, the beam spacing, and each end flagged as a true silhouette edge
    unless it is occluded or truncated. ``silhouette`` (K, 2, 2) (segment start, end: offset,
    std in beams; :func:`~stemmap.scan.features.edge_silhouette`), ``beam_divergence`` (rad),
    ``residuals`` and ``edge_window`` (the edge range window's least share of the footprint,
    :func:`stemmap.scan.circle.fit_circles_batch`) are passed to "ours". The fits take the
    ends in bearing order, so with a negative angle increment the start is the *last* end.
    """
    k = len(segs)
    covs = np.full((k, 3, 3), np.nan)
    if method == "kasa":
        centers, radii, ok = fit_kasa_segments(segs)
        return centers, radii, covs, ok
    p = segs.points
    edges = np.column_stack(
        (~(segs.occluded_start | segs.truncated_start), ~(segs.occluded_end | segs.truncated_end))
    )
    if p.angle_increment < 0:  # bearing order is the reverse of beam order
        edges = edges[:, ::-1]
        if silhouette is not None:
            silhouette = silhouette[:, ::-1]
    batch_fn = getattr(_circle, "fit_circles_batch", None)
    if batch_fn is not None:
        extra: dict[str, Any] = {}
        if method == "ours":
            extra = {
                "silhouette": silhouette,
                "beam_divergence": beam_divergence,
                "residuals": residuals,
                "edge_window": edge_window,
            }
        res = batch_fn(
            np.column_stack((p.x, p.y)),
            segs.labels,
            method,
            origin=np.zeros(2),
            sigma=sigma if np.all(sigma > 0) else None,
            angle_increment=abs(p.angle_increment),
            edges=edges,
            **extra,
        )
        centers = np.asarray(res.centers, dtype=np.float64).reshape(k, 2)
        radii = np.asarray(res.radii, dtype=np.float64).reshape(k)
        ok = np.asarray(res.ok, dtype=bool).reshape(k)
        covs = np.asarray(res.covs, dtype=np.float64).reshape(k, 3, 3).copy()
        return centers, radii, covs, ok
    centers = np.full((k, 2), np.nan)  # pragma: no cover - only before circle.py had a batch API
    radii = np.full(k, np.nan)
    ok = np.zeros(k, dtype=bool)
    xy = np.column_stack((p.x, p.y))
    for j in range(k):
        fit = _circle.fit_circle(xy[segs.start[j] : segs.stop[j]], method=method)
        if fit:
            centers[j], radii[j], ok[j] = fit.center, fit.radius, True
    return centers, radii, covs, ok


class _Fitted(NamedTuple):
    """Circle fits of candidate segments and what the plausibility tests read."""

    centers: FloatArray  # (K, 2)
    radii: FloatArray
    covs: FloatArray  # (K, 3, 3)
    ok: NDArray[np.bool_]  # the fit converged
    sigma: FloatArray  # per-segment range noise
    mean_r: FloatArray  # mean range of the returns
    width: FloatArray  # edge-beam chord
    sil_width: FloatArray  # silhouette width (chord widened by mixed-pixel neighbours)
    rms: FloatArray  # RMS orthogonal residual
    test_rms: FloatArray  # what the RMS test reads (the RMS or the robust residual scale)
    smooth: FloatArray | None = None  # residuals' high-frequency scale (lobe_roughness only)
    own_noise: FloatArray | None = None  # the relaxed RMS test's noise (rms_noise_from_fit)
    dbh_sd: FloatArray | None = None  # the fit's diameter std, 2 sqrt(C_rr) (max_dbh_sd only)
    cov_out: FloatArray | None = None  # the covariance reported (dbh_sd_noise; else covs)


def fit_sigma(
    floor: float, segs: Segments, sigma: FloatArray, cap: bool = True
) -> FloatArray | None:
    """``fit_noise_floor``: the range noise the fits of ``segs`` weight the returns by (ours,
    issue 11, Dec 5), None when the option is off (the fits use ``sigma``).

    Per segment ``sqrt(n^2 + m^2 / 12)`` between ``floor`` and the tests' ``sigma``: ``n``
    the measured range noise of its scan (``segs.points.fit_noise``) and ``m`` the median
    absolute range step between its adjacent returns. A first-echo return lies anywhere in
    its beam's footprint (one beam spacing) and the footprint correction puts it at one side,
    so its range is off by up to the range step across a beam: uniformly, a standard
    deviation of step / sqrt(12). On a near stem that is millimetres; on a 4-return arc far
    away, centimetres (there the fit keeps ``sigma``). The median, not the RMS: the steep
    silhouette steps are two of many on a long arc (measured: docs/algorithms/
    scan-detection.md, "lidR view by view"). ``cap`` False: not capped by ``sigma`` (the
    measured scale itself, for ``stub_runs_snoop``)."""
    noise = segs.points.fit_noise
    if noise is None:
        return None
    med = segment_step_medians(segs.points.r, segs.start, segs.stop)
    scale = np.sqrt(noise[segs.scan] ** 2 + med * med / 12.0)
    out: FloatArray = np.maximum(floor, scale)
    return np.minimum(sigma, out) if cap else out


def reported_covs(
    covs: FloatArray,
    fit_scale: FloatArray,
    measured: FloatArray,
    rms: FloatArray,
    n: np.ndarray,
    outline: float,
) -> FloatArray:
    """The covariance a first-echo detection reports (``dbh_sd_noise``, ``dbh_sd_outline``;
    issue 11, Dec 5): the fit's ``covs`` (K, 3, 3) with the radius row and column scaled by
    ``k = max(1, measured / fit_scale, s_res / fit_scale)``, ``s_res = rms sqrt(n / (n - 3))``
    the fit's residual scale (:func:`~stemmap.scan._centre_cov.noise_factors`), and
    ``(outline / 2)^2`` added to ``C_rr`` (a diameter std of ``outline`` in quadrature).
    Scaling one row and column by ``k >= 1`` and adding to the diagonal keeps the matrix
    positive semi-definite; the centre's block is unchanged (``centre_sd_along`` /
    ``centre_sd_across``: :func:`~stemmap.scan._centre_cov.centre_covs`)."""
    return _radius_reported(covs, noise_factors(fit_scale, measured, rms, n), outline)


def _radius_reported(covs: FloatArray, k: FloatArray, outline: float) -> FloatArray:
    """``covs`` with the radius row and column scaled by ``k`` and ``(outline / 2)^2`` added
    to ``C_rr`` (:func:`reported_covs`, given its noise factors)."""
    out = covs.copy()
    out[:, 2, :] *= k[:, None]
    out[:, :, 2] *= k[:, None]
    out[:, 2, 2] += 0.25 * outline * outline
    return out


def reported_first_echo_covs(
    cfg: Any,
    segs: Segments,
    covs: FloatArray,
    sigma: FloatArray,
    f_sigma: FloatArray | None,
    rms: FloatArray,
    centers: FloatArray | None = None,
) -> FloatArray | None:
    """The covariances a first-echo ``ours`` fit of ``cfg`` (a
    :class:`~stemmap.scan.config.DetectorConfig`) reports (``dbh_sd_noise``,
    ``dbh_sd_outline``: :func:`reported_covs`; ``centre_sd_along``, ``centre_sd_across``
    with the fits' ``centers``: :func:`~stemmap.scan._centre_cov.centre_covs`), None where
    the fit's own stand (another scanner or fit, or every option off). ``sigma``: the tests'
    noise; ``f_sigma``: the noise the fit weighted by (:func:`fit_sigma`, None: ``sigma``);
    ``rms``: the fits' RMS. The plausibility tests and trims keep reading the fit's own
    ``covs``."""
    centre = centers is not None and (cfg.centre_sd_along > 0 or cfg.centre_sd_across > 0)
    if not (cfg.dbh_sd_noise or cfg.dbh_sd_outline > 0 or centre):
        return None
    if not (cfg.beam_footprint_deg > 0 and cfg.fit_method == "ours"):
        return None
    scale = sigma if f_sigma is None else f_sigma
    meas = fit_sigma(cfg.fit_noise_floor, segs, sigma, cap=False) if cfg.dbh_sd_noise else None
    args = (
        scale,
        scale if meas is None else meas,
        rms if cfg.dbh_sd_noise else np.zeros_like(rms),
        segs.counts,
    )
    k = noise_factors(*args)  # once: the radius and the centre share it
    out = _radius_reported(covs, k, cfg.dbh_sd_outline)
    if centre:
        assert centers is not None
        out = centre_covs(
            out, k, centers, cfg.dbh_sd_outline, cfg.centre_sd_along, cfg.centre_sd_across
        )
    return out


def _output_columns(
    segs: Segments, fitted: _Fitted, ok: NDArray[np.bool_], cfg: Any = None
) -> dict[str, np.ndarray]:
    """The output columns of the kept candidates (``ok``): the fit's covariance (or the
    geometric one where the fit gave none), arc extent, quality. ``cfg`` (the detector's
    config, None: no option read): ``dbh_sd_jackknife`` raises the reported radius variance
    towards its jackknife (:mod:`stemmap.scan._dbh_jackknife`)."""
    centers, radii, covs, sigma, rms = (
        fitted.centers,
        fitted.radii,
        (fitted.covs if fitted.cov_out is None else fitted.cov_out).copy(),
        fitted.sigma,
        fitted.rms,
    )
    n = segs.counts
    missing = ok & ~np.all(np.isfinite(covs), axis=(1, 2))
    if np.any(missing):
        sub = segs.select(missing)
        covs[missing] = _geometric_cov(sub, centers[missing], radii[missing], sigma[missing])
    if cfg is not None and cfg.dbh_sd_jackknife > 0 and np.any(ok):
        from stemmap.scan._dbh_jackknife import jackknife_covs

        covs[ok] = jackknife_covs(cfg, segs.select(ok), covs[ok], sigma[ok])
    with np.errstate(invalid="ignore"):
        arc = _arc_deg(segs, centers)
        quality = _quality(n, rms, sigma, segs.partial)
    return {
        "centers": centers[ok],
        "radii": radii[ok],
        "covs": covs[ok],
        "n_points": n[ok],
        "arc_deg": arc[ok],
        "widths": fitted.width[ok],
        "quality": quality[ok],
        "index": segs.scan[ok],
    }


def _arc_deg(segs: Segments, centers: FloatArray) -> FloatArray:
    """Angular extent of each segment's returns around its fitted centre, degrees."""
    p = segs.points
    lab = segs.labels
    ref = np.arctan2(-centers[:, 1], -centers[:, 0])  # direction centre -> sensor
    phi = np.arctan2(p.y - centers[lab, 1], p.x - centers[lab, 0]) - ref[lab]
    phi = np.pi - np.mod(np.pi - phi, 2.0 * np.pi)
    out: FloatArray = np.degrees(
        np.maximum.reduceat(phi, segs.start) - np.minimum.reduceat(phi, segs.start)
    )
    return out


def _quality(n: np.ndarray, rms: FloatArray, sigma: FloatArray, partial: np.ndarray) -> FloatArray:
    """Heuristic quality in [0, 1]: support (n / 10, capped), fit residual against the noise,
    halved for partial (occluded or truncated) segments."""
    support = np.minimum(n / 10.0, 1.0)
    s = np.maximum(sigma, 1e-6)
    fit = np.exp(-np.square(np.maximum(rms - s, 0.0) / (3.0 * s)))
    out: FloatArray = support * fit * np.where(partial, 0.5, 1.0)
    return out


def residual_floor_refit(
    cfg: DetectorConfig,
    segs: Segments,
    sigma: FloatArray,
    fit: tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]],
    sil: FloatArray | None,
    divergence: float,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """``residual_floor`` (ours, issue 11, Dec 6; a measurement, off by default): the fits
    ``fit`` (centers, radii, covs, ok) of ``segs``, weighted by ``sigma``, fitted again where
    the upper ``residual_floor`` confidence bound of their own residual scale is below
    ``sigma``, weighted by that bound (at least the scan's measured noise).

    With ``nu = n - 3`` degrees of freedom the residual scale ``s = RMS sqrt(n / nu)`` of a
    fit to returns of noise ``sigma_true`` has ``nu s^2 / sigma_true^2 ~ chi^2(nu)``, so
    ``s sqrt(nu / chi^2_{1 - c}(nu))`` bounds ``sigma_true`` from above with confidence ``c``.
    A floor above that bound (the preset's 1 cm on a noise-free scan) weighs the ranges less
    than they deserve and lets the tangent prior decide the radius (docs/algorithms/
    scan-detection.md, "The two FORTLS rows left against textbook Kasa"); a real outline's
    departure from its circle shows in the residuals and keeps the bound up."""
    from scipy.special import chdtri

    centers, radii, covs, ok = fit
    n = segs.counts.astype(np.float64)
    nu = n - 3.0
    with np.errstate(invalid="ignore"):
        rms = _fit_rms(segs, centers, radii)
        s_res = rms * np.sqrt(n / np.maximum(nu, 1.0))
        bound = s_res * np.sqrt(nu / chdtri(np.maximum(nu, 1.0), cfg.residual_floor))
    noise = segs.points.noise
    measured = np.zeros(len(segs)) if noise is None else np.nan_to_num(noise[segs.scan])
    lower = np.maximum(bound, np.maximum(measured, 1e-4))
    redo = ok & (nu >= 1) & np.isfinite(lower) & (lower < sigma)
    if not np.any(redo):
        return fit
    sub = segs.select(redo)
    c2, r2, v2, ok2 = _fit_segments(
        sub,
        cfg.fit_method,
        lower[redo],
        silhouette=None if sil is None else sil[redo],
        beam_divergence=divergence,
        residuals=cfg.fit_residuals,
        edge_window=cfg.edge_window_share(),
    )
    centers, radii, covs = centers.copy(), radii.copy(), covs.copy()
    rows = np.flatnonzero(redo)[ok2]
    centers[rows], radii[rows], covs[rows] = c2[ok2], r2[ok2], v2[ok2]
    return centers, radii, covs, ok


def fit_candidates(cfg: DetectorConfig, segs: Segments, grid: FloatArray, wrap: bool) -> _Fitted:
    """Circle fit of every candidate segment (sensor at the origin) with what the fit
    plausibility tests need (:func:`~stemmap.scan.plausibility.fit_reasons`;
    ``ScanTrunkDetector._fit_candidates`` of a detector with config ``cfg``)."""
    p = segs.points
    n = segs.counts
    mean_r = segment_sum(p.r, segs) / n
    sigma = segment_sigma(cfg, segs, mean_r)  # per-segment range noise
    if cfg.sigma_from_data and (cfg.sigma > 0 or cfg.sigma_rel > 0):
        # (sigma 0: the fit estimates its own scale, nothing to raise)
        sigma = np.maximum(
            sigma, np.minimum(range_roughness(segs), cfg.roughness_max_factor * sigma)
        )
    # a footprint correction means a first-echo sensor: no averaging-scanner edge model
    divergence = 0.0 if cfg.beam_footprint_deg > 0 else math.radians(cfg.beam_divergence_deg)
    sil = None
    if cfg.fit_method == "ours" and cfg.neighbour_silhouette and divergence > 0:
        sil = edge_silhouette(
            segs,
            grid,
            divergence,
            margin=cfg.occlusion_margin,
            wrap=wrap,
            hit_range=(cfg.edge_hit_min, cfg.edge_hit_max),
        )
    elif cfg.fit_method == "ours" and cfg.beam_footprint_deg > 0 and cfg.edge_protrusion > 0:
        # first echo: the last beam that returns may have caught a bark flake or twig
        sil = first_echo_edge_prior(segs, cfg.edge_protrusion)
    # fit_noise_floor: the fit weights by the measured noise, the tests keep sigma
    f_sigma = fit_sigma(cfg.fit_noise_floor, segs, sigma)
    centers, radii, covs, ok = _fit_segments(
        segs,
        cfg.fit_method,
        sigma if f_sigma is None else f_sigma,
        silhouette=sil,
        beam_divergence=divergence,
        residuals=cfg.fit_residuals,
        edge_window=cfg.edge_window_share(),
    )
    if cfg.residual_floor > 0 and cfg.fit_method == "ours" and cfg.beam_footprint_deg == 0:
        # the fit weighted again by its own residuals' upper confidence bound, where that
        # is below the noise it used (residual_floor_refit)
        centers, radii, covs, ok = residual_floor_refit(
            cfg, segs, sigma if f_sigma is None else f_sigma, (centers, radii, covs, ok),
            sil, divergence,
        )  # fmt: skip
    f_width = segment_widths(segs)
    sil_width = f_width
    if sil is not None:
        # a neighbour that saw a mixed pixel puts the tangent up to ~1 beam beyond the edge
        # return: the silhouette is wider than the edge-beam chord by that much
        beyond = np.nansum(np.maximum(sil[:, :, 0] - 0.5, 0.0), axis=1)
        sil_width = f_width + beyond * mean_r * abs(segs.points.angle_increment)
    with np.errstate(invalid="ignore"):
        rms = _fit_rms(segs, centers, radii)
        # the RMS test reads the robust scale when asked (quality keeps the plain RMS)
        test_rms = robust_residual_scale(segs, centers, radii) if cfg.rms_robust else rms
        if cfg.rms_dof:
            # the residual scale over the fit's n - 3 degrees of freedom
            n = segs.counts.astype(np.float64)
            test_rms = test_rms * np.sqrt(n / np.maximum(n - 3.0, 1.0))
    if cfg.lobe_harmonics:
        # a candidate that fails the RMS test as a circle may pass it as a lobed outline
        centers, radii, covs, test_rms, lobed = lobed_refit(
            cfg, segs, centers, radii, covs, ok, test_rms, sigma, sil_width
        )
        rms = np.where(lobed, test_rms, rms)
    smooth = own = None
    if cfg.lobe_roughness > 0 or cfg.rms_noise_from_fit > 0:
        smooth = residual_smoothness(segs, centers, radii)
        if cfg.rms_noise_from_fit > 0:
            own = own_noise(cfg, segs, sigma, smooth)
    dbh_sd = None
    if math.isfinite(cfg.max_dbh_sd) and cfg.beam_footprint_deg > 0 and cfg.fit_method == "ours":
        # the diameter's standard deviation by the fit's own covariance (max_dbh_sd)
        dbh_sd = 2.0 * np.sqrt(np.maximum(covs[:, 2, 2], 0.0))
    # the reported DBH std at the noise present, plus the outline's share (first echo)
    cov_out = reported_first_echo_covs(cfg, segs, covs, sigma, f_sigma, rms, centers)
    return _Fitted(
        centers,
        radii,
        covs,
        ok,
        sigma,
        mean_r,
        f_width,
        sil_width,
        rms,
        test_rms,
        smooth,
        own,
        dbh_sd,
        cov_out,
    )
