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
"""

from __future__ import annotations

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
    u = _sight(centers)
    out[:, :2, :2] += outline_covs(centers, outline, along, across)
    q = 0.25 * outline * outline
    gu = along * u
    out[:, :2, 2] += q * gu
    out[:, 2, :2] += q * gu
    return out


def _sight(centers: FloatArray) -> FloatArray:
    """Unit vectors (K, 2) from the sensor to ``centers`` (0 where the centre is the sensor)."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    d = np.hypot(c[:, 0], c[:, 1])
    ok = np.isfinite(d) & (d > 0)
    dsafe = np.where(ok, d, 1.0)
    u: FloatArray = np.where(ok[:, None], c / dsafe[:, None], 0.0)
    return u


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
    u = _sight(centers)
    w = np.column_stack((-u[:, 1], u[:, 0]))
    q = 0.25 * outline * outline
    gu = along * u
    out: FloatArray = q * gu[:, :, None] * gu[:, None, :] + across * across * (
        w[:, :, None] * w[:, None, :]
    )
    return out


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
