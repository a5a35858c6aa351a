"""Cluster shape descriptors: per-cluster covariance, PCA eigenvalues, eccentricity, arc coverage.

Vectorised over all clusters at once (``np.bincount``), no Python loop over points.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stemmap.errors import InputError
from stemmap.types import FloatArray

__all__ = ["arc_coverage_deg", "cluster_covariances", "major_axis_tilt_deg", "pca_eccentricity"]


def cluster_covariances(
    xyz: ArrayLike, labels: ArrayLike, n_clusters: int | None = None
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Centroids, covariance matrices and sizes of labelled clusters.

    Parameters
    ----------
    xyz : array_like (N, D)
    labels : array_like (N,), int
        Cluster index per point, ``< 0`` for noise (ignored).
    n_clusters : int, optional
        Number of clusters (default ``labels.max() + 1``).

    Returns
    -------
    centroids : (K, D); cov : (K, D, D) population covariance (Munjer eq. 3, 1/|C|); sizes : (K,)
    """
    p = np.asarray(xyz, dtype=np.float64)
    lab = np.asarray(labels).astype(np.int64).reshape(-1)
    if p.ndim != 2 or lab.shape[0] != p.shape[0]:
        raise InputError(f"labels ({lab.shape[0]}) must match points ({p.shape}).")
    k = int(lab.max() + 1) if n_clusters is None and lab.size else int(n_clusters or 0)
    d = p.shape[1]
    ok = lab >= 0
    lab_ok, p_ok = lab[ok], p[ok]
    sizes = np.bincount(lab_ok, minlength=k).astype(np.int64)
    safe = np.maximum(sizes, 1)
    cen = np.column_stack([np.bincount(lab_ok, p_ok[:, j], k) / safe for j in range(d)])
    q = p_ok - cen[lab_ok]
    cov = np.empty((k, d, d))
    for i in range(d):
        for j in range(i, d):
            v = np.bincount(lab_ok, q[:, i] * q[:, j], k) / safe
            cov[:, i, j] = v
            cov[:, j, i] = v
    return cen.reshape(k, d), cov, sizes


def _cov_stack(cov: ArrayLike) -> tuple[FloatArray, bool]:
    """(K, D, D) float array of ``cov`` ((K, D, D) or one (D, D)) and whether it was one."""
    c = np.asarray(cov, dtype=np.float64)
    return c.reshape(-1, c.shape[-2], c.shape[-1]), c.ndim == 2


def pca_eccentricity(cov: ArrayLike, axes: str = "largest") -> FloatArray:
    """Eccentricity ``e = lambda1 / lambda2`` of covariance matrices (Munjer et al. 2025, eq. 4).

    ``axes="largest"``: ``lambda1 >= lambda2`` are the two largest eigenvalues of each (D, D)
    matrix in ``cov`` (shape (K, D, D) or (D, D)); ``axes="major_minor"``: the largest over the
    smallest (for D = 3, the elongation of a curved sheet against its thickness; see
    docs/algorithms/cloud.md, "EB-LiDAR on 16-beam frames"). ``inf`` where the denominator is 0.

    Examples
    --------
    >>> float(pca_eccentricity(np.diag([4.0, 1.0, 0.5])))
    4.0
    """
    c, single = _cov_stack(cov)
    if axes not in ("largest", "major_minor"):
        raise InputError(f"axes must be 'largest' or 'major_minor', got {axes!r}.")
    w = np.linalg.eigvalsh(c)  # ascending
    l1, l2 = w[:, -1], (w[:, -2] if axes == "largest" else w[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.where(l2 > 0, l1 / np.where(l2 > 0, l2, 1.0), np.inf)
    return e[0] if single else e


def major_axis_tilt_deg(cov: ArrayLike) -> FloatArray:
    """Angle (degrees, 0-90) between the principal axis of 3D covariance matrices (the
    eigenvector of the largest eigenvalue) and the vertical z axis.

    0 for a vertical stem, 90 for a cluster elongated horizontally (a ring arc, a ground strip).
    Used for Munjer et al. (2025)'s "vertically elongated clusters" (abstract, §1), which
    eq. (4) alone does not test; see :class:`stemmap.cloud.munjer.MunjerConfig`.

    Examples
    --------
    >>> float(major_axis_tilt_deg(np.diag([1.0, 0.5, 4.0])))
    0.0
    """
    c, single = _cov_stack(cov)
    if c.shape[-1] != 3:
        raise InputError(f"major_axis_tilt_deg needs 3 x 3 covariances, got {c.shape[-2:]}.")
    _, vec = np.linalg.eigh(c)  # ascending: last column = principal axis
    t = np.degrees(np.arccos(np.clip(np.abs(vec[:, 2, -1]), 0.0, 1.0)))
    return t[0] if single else t


def arc_coverage_deg(points: ArrayLike, center: ArrayLike) -> float:
    """Angular extent (degrees) of points around a centre: 360 minus the largest empty gap.

    A full ring gives ~360, a single-side view of a trunk about 180 or less.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if p.shape[0] < 2:
        return 0.0
    c = np.asarray(center, dtype=np.float64).reshape(2)
    a = np.sort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))
    gaps = np.diff(np.concatenate((a, a[:1] + 2 * np.pi)))
    return float(np.degrees(2 * np.pi - gaps.max()))
