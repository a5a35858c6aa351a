"""The centre (position) block of the covariance a first-echo detection reports
(``centre_sd_along``, ``centre_sd_across``; ours, issue 11, Dec 6, docs/algorithms/
scan-detection.md, "First-echo centre covariance").

The fit's covariance over (x, y, r) is its inverse Hessian at the noise it weighted by;
``dbh_sd_noise`` scales the radius row and column by the factor ``k`` of the noise present and
``dbh_sd_outline`` adds the real outline's diameter error ``b`` to ``C_rr``
(:func:`stemmap.scan._segment_fits.reported_covs`). The centre was left at the fit's own
scale and without an outline term, although a first echo sees one side of the trunk: the
centre is the near surface plus the radius along the line of sight, so a radius error moves
the centre with it (measured on the real slices: correlation 0.8-0.99 between the along-sight
centre error and the radius error, slope 1.1-1.4). :func:`centre_covs` puts both in:

* the centre's rows and columns are scaled by the same ``k`` (a covariance at noise ``s`` is
  ``s^2`` times the inverse information, every entry alike);
* the outline's radius error ``e_b`` (std ``b / 2``) moves the centre by ``g e_b`` along the
  line of sight ``u`` (sensor -> centre): ``(b / 2)^2 v v^T`` with ``v = (g u, 1)``, of which
  ``C_rr``'s ``(b / 2)^2`` is already there;
* a lobed or leaning outline also shifts the centre across the line of sight ``w``, by an
  amount the returns cannot show: ``c^2 w w^T``.

Each addition is positive semi-definite and the scaling multiplies rows and columns by the
same factor, so the result stays a covariance. Positions, radii and every test are unchanged
(the tests read the fit's own covariance).

An averaging (SICK-class) scanner's centre has the same cause and one more
(``centre_sd_footprint``, ``centre_sd_across_averaging``; Dec 6, "Averaging centre
covariance"): its fitted radius errs with the outline and with the averaged edge returns, whose
error grows with the footprint's width at the trunk (range ``d`` times the divergence), and the
centre follows the radius along the line of sight (measured on the real slices' averaging rows:
correlation 0.74-0.995, slope 1.0-1.3). :func:`averaging_centre_covs` adds
``((g b / 2)^2 + (f d theta)^2) u u^T + c_a^2 w w^T`` to the centre block and nothing to the
radius (that scanner's diameter std is the fit's own) nor to the centre-radius entries: a
positive semi-definite addition to the centre block alone, so the result stays a covariance.
The compiled path's fits carry no noise factor, so the centre is not scaled.

The same two errors move that scanner's radius (``dbh_sd_footprint``; Dec 6, "Averaging DBH
standard error"): the radius error has the outline's ``b / 2`` and a share ``h`` of the
footprint's width ``d theta`` (measured on the real slices' averaging rows: radius error RMS
1.4-1.8 cm at 0-4 m, 2.5-3.7 cm at 12-16 m on bark, against a fit's own radius std of 0.3 /
1.1 cm). With it on, each cause is one vector over (x, y, r) --
``v1 = (g b / 2 u, b / 2)`` for the outline and ``v2 = d theta (f u, h)`` for the footprint --
and the addition is ``v1 v1^T + v2 v2^T + c_a^2 w w^T``: the centre block as above, ``C_rr``
gains ``(b / 2)^2 + (h d theta)^2`` and the centre-radius covariance
``(g (b / 2)^2 + f h (d theta)^2) u``. A sum of outer products, so still a covariance.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from stemmap.types import FloatArray


def centre_covs(
    covs: FloatArray,
    k: FloatArray,
    centers: FloatArray,
    outline: float,
    along: float,
    across: float,
) -> FloatArray:
    """``covs`` (K, 3, 3), the covariance with the radius already reported
    (:func:`~stemmap.scan._segment_fits.reported_covs`: radius row and column scaled by ``k``,
    ``(outline / 2)^2`` added to ``C_rr``), with the centre as the module doc describes:
    centre rows and columns scaled by ``k`` (K,), ``(outline / 2)^2`` times ``(g u, 1)``'s
    outer product less its ``C_rr`` entry (``g`` = ``along``, ``u`` the unit vector from the
    sensor to ``centers`` (K, 2)) and ``across^2 w w^T`` (``w`` perpendicular to ``u``)."""
    out = np.array(covs, dtype=np.float64, copy=True)
    kk = np.where(np.isfinite(k), k, 1.0)
    out[:, :2, :] *= kk[:, None, None]
    out[:, :, :2] *= kk[:, None, None]
    u, _, _ = line_of_sight(centers)
    out[:, :2, :2] += outline_covs(centers, outline, along, across)
    q = 0.25 * outline * outline
    gu = along * u
    out[:, :2, 2] += q * gu
    out[:, 2, :2] += q * gu
    return out


def outline_centre_covs(centers: FloatArray, config: Any) -> FloatArray:
    """The outline's part (K, 2, 2) of the centre covariance the detections of ``config`` (a
    :class:`~stemmap.scan.config.DetectorConfig`) at ``centers`` (K, 2, sensor frame) report:
    :func:`outline_covs` with its ``dbh_sd_outline``, ``centre_sd_along`` and
    ``centre_sd_across`` for a first-echo ``ours`` fit (``beam_footprint_deg`` > 0), zeros
    otherwise (the options apply to those fits only). ``shared`` of
    :func:`stemmap.slam.uncertainty.fused_positions` when only the outline's part is taken as
    shared between one trunk's detections (benchmarks/centre_pass_fusion.py ``--shared
    both``; not the default)."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    on = config.beam_footprint_deg > 0 and config.fit_method == "ours"
    if not (on and (config.centre_sd_along > 0 or config.centre_sd_across > 0)):
        return np.zeros((c.shape[0], 2, 2))
    return outline_covs(c, config.dbh_sd_outline, config.centre_sd_along, config.centre_sd_across)


def outline_covs(centers: FloatArray, outline: float, along: float, across: float) -> FloatArray:
    """The outline's part (K, 2, 2) of a first-echo detection's reported centre covariance
    (:func:`centre_covs`): ``(g outline / 2)^2 u u^T + across^2 w w^T`` with ``u`` the unit
    vector from the sensor to ``centers`` (K, 2, sensor frame), ``w`` perpendicular to it and
    ``g`` = ``along``. What the fit's covariance at the noise present does not hold."""
    u, w, _ = line_of_sight(np.asarray(centers, dtype=np.float64).reshape(-1, 2))
    q = 0.25 * outline * outline
    gu = along * u
    out: FloatArray = q * gu[:, :, None] * gu[:, None, :] + across * across * (
        w[:, :, None] * w[:, None, :]
    )
    return out


def line_of_sight(centers: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The unit vector ``u`` from the sensor (the origin) to each of ``centers`` (K, 2), the
    unit vector ``w`` across it and the distance (0 vectors and distance where it is not
    finite and positive)."""
    d = np.hypot(centers[:, 0], centers[:, 1])
    ok = np.isfinite(d) & (d > 0)
    dsafe = np.where(ok, d, 1.0)
    u = np.where(ok[:, None], centers / dsafe[:, None], 0.0)
    w = np.column_stack((-u[:, 1], u[:, 0]))
    return u, w, np.where(ok, d, 0.0)


def averaging_centre_covs(
    covs: FloatArray,
    centers: FloatArray,
    outline_sd: float,
    footprint_sd: float,
    divergence: float,
    across: float,
    radius_outline: float = 0.0,
    radius_footprint: float = 0.0,
) -> FloatArray:
    """``covs`` (K, 3, 3) of averaging-scanner fits at ``centers`` (K, 2), sensor at the
    origin, with ``outline_sd^2 + (footprint_sd divergence d)^2`` added along the line of
    sight ``u`` and ``across^2`` across it (module doc): ``outline_sd`` (m) the outline's
    radius error carried to the centre (``centre_sd_along`` times ``dbh_sd_outline / 2``),
    ``footprint_sd`` the centre's std per footprint width, ``divergence`` the footprint's
    full angle (radians), ``d`` the range to the centre. ``radius_outline`` (m, the outline's
    radius std ``dbh_sd_outline / 2``) and ``radius_footprint`` (the radius std per footprint
    width, ``dbh_sd_footprint``): the same two errors on the radius, ``C_rr`` gaining
    ``radius_outline^2 + (radius_footprint divergence d)^2`` and the centre-radius entries
    ``(outline_sd radius_outline + footprint_sd radius_footprint (divergence d)^2) u``; both
    0 (the default): the radius row and column are unchanged."""
    out = np.array(covs, dtype=np.float64, copy=True).reshape(-1, 3, 3)
    u, w, d = line_of_sight(centers)
    va = outline_sd * outline_sd + (footprint_sd * divergence * d) ** 2
    out[:, :2, :2] += va[:, None, None] * (u[:, :, None] * u[:, None, :]) + across * across * (
        w[:, :, None] * w[:, None, :]
    )
    if radius_outline > 0 or radius_footprint > 0:
        wd = divergence * d
        out[:, 2, 2] += radius_outline * radius_outline + (radius_footprint * wd) ** 2
        cross = (outline_sd * radius_outline + footprint_sd * radius_footprint * wd * wd)[
            :, None
        ] * u
        out[:, :2, 2] += cross
        out[:, 2, :2] += cross
    return out


def averaging_report(cfg: Any, centers: FloatArray, covs: FloatArray) -> FloatArray:
    """The covariances an averaging ``ours`` fit of ``cfg`` (a
    :class:`~stemmap.scan.config.DetectorConfig`) reports for detections at ``centers``
    (sensor frame) with the fit's ``covs``: :func:`averaging_centre_covs` with the centre
    terms when ``centre_sd_footprint`` or ``centre_sd_across_averaging`` is on and the
    radius terms when ``dbh_sd_footprint`` is; neither: ``covs`` itself."""
    centre = averaging_centre_on(cfg)
    radius = averaging_radius_on(cfg)
    if not (centre or radius) or covs.shape[0] == 0:
        return covs
    return averaging_centre_covs(
        covs,
        centers,
        0.5 * cfg.centre_sd_along * cfg.dbh_sd_outline if centre else 0.0,
        cfg.centre_sd_footprint if centre else 0.0,
        math.radians(cfg.beam_divergence_deg),
        cfg.centre_sd_across_averaging if centre else 0.0,
        0.5 * cfg.dbh_sd_outline if radius else 0.0,
        cfg.dbh_sd_footprint if radius else 0.0,
    )


def _averaging_ours(cfg: Any) -> bool:
    return cfg.fit_method == "ours" and cfg.beam_footprint_deg == 0 and cfg.beam_divergence_deg > 0


def averaging_centre_on(cfg: Any) -> bool:
    """Whether ``cfg`` reads an averaging scanner with the ``ours`` fit and asks for its
    centre terms."""
    return _averaging_ours(cfg) and (
        cfg.centre_sd_footprint > 0 or cfg.centre_sd_across_averaging > 0
    )


def averaging_radius_on(cfg: Any) -> bool:
    """Whether ``cfg`` reads an averaging scanner with the ``ours`` fit and asks for its
    radius terms (``dbh_sd_footprint``)."""
    return _averaging_ours(cfg) and cfg.dbh_sd_footprint > 0


def noise_factors(
    fit_scale: FloatArray, measured: FloatArray, rms: FloatArray, n: np.ndarray
) -> FloatArray:
    """``k = max(1, measured / fit_scale, s_res / fit_scale)`` per fit, ``s_res = rms
    sqrt(n / (n - 3))`` the fit's residual scale (1 where not finite): the factor
    ``dbh_sd_noise`` puts on the fit's standard deviations."""
    nf = n.astype(np.float64)
    s_res = rms * np.sqrt(nf / np.maximum(nf - 3.0, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.fmax(1.0, np.fmax(measured / fit_scale, s_res / fit_scale))
    out: FloatArray = np.where(np.isfinite(k), k, 1.0)
    return out
