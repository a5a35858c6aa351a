"""Per-stem uncertainty from the slice fits (ours, docs/algorithms/cloud.md "Uncertainty"):
the variance of the radius and the covariance of the centre at the measurement height, from
the slices' fit covariances (``s^2 (J^T J)^-1``, Chernov 2010, "Circular and linear
regression", §6.4; :func:`~stemmap.cloud.slicefit._segment_covariances`) and from the
scatter of the slices about their Theil-Sen lines."""

from __future__ import annotations

import math

import numpy as np

from stemmap.types import FloatArray


def _line_uncertainty(
    hh: FloatArray,
    r: FloatArray,
    c: FloatArray,
    coefs: tuple[tuple[float, float], ...],
    cov_i: FloatArray,
) -> tuple[float, FloatArray]:
    """Variance of the radius and covariance of the centre at ``hh = 0`` of the slice lines.

    Two estimates, the larger kept: the slices' fit covariances
    (:func:`~stemmap.cloud.slicefit._segment_covariances`) averaged and divided by the number
    of slices (independent slices, intercept at the band's middle), and the scatter of the
    slice values about the Theil-Sen lines (1.4826 MAD, squared, over the number of slices):
    bark roughness and branch stubs move whole slices, which no single fit's covariance sees.
    """
    n = hh.shape[0]
    coef_r, coef_x, coef_y = coefs
    fit_r = float(np.nanmean(cov_i[:, 2, 2])) / n
    fit_xy = np.nanmean(cov_i[:, :2, :2], axis=0) / n
    res_r = r - (coef_r[0] + coef_r[1] * hh)
    res_c = c - np.column_stack((coef_x[0] + coef_x[1] * hh, coef_y[0] + coef_y[1] * hh))
    dof = max(n - 2, 1)
    sc_r = (1.4826 * float(np.median(np.abs(res_r)))) ** 2 * n / dof / n
    sc_xy = (res_c.T @ res_c) / dof / n
    var_r = max(fit_r, sc_r) if math.isfinite(fit_r) else sc_r
    cov_xy = (
        sc_xy if not np.isfinite(fit_xy).all() or np.trace(sc_xy) > np.trace(fit_xy) else fit_xy
    )
    return var_r, np.asarray(cov_xy, dtype=np.float64)


def _mean_uncertainty(cov_i: FloatArray) -> tuple[float, FloatArray]:
    """Inverse-variance combination of the slices' fit covariances (fewer than 3 slices)."""
    good = np.isfinite(cov_i).all(axis=(1, 2))
    if not good.any():
        return math.nan, np.full((2, 2), np.nan)
    info_r = float(np.sum(1.0 / np.maximum(cov_i[good, 2, 2], 1e-12)))
    info_xy = np.sum(np.linalg.inv(cov_i[good, :2, :2] + 1e-12 * np.eye(2)), axis=0)
    return 1.0 / info_r, np.asarray(np.linalg.inv(info_xy), dtype=np.float64)
