"""The taller-band fit of sparse stems (ours, option ``StemConfig.sparse_tall_fit``, default off;
docs/algorithms/cloud.md "Sparse plots: one ring stack over 0.5-3.0 m").

A trunk of a sparse cloud (a thinned export, a distant or partly hidden tree) may show 10-30
returns over the 1.2 m band: too few for a circle per slice (8 inliers), for the pooled
cylinder (16 points, 3 in each slice) or for the shared-axis fit's switching rule (3 slices
of 8). Below and above the band the same trunk goes on, and its returns there measure the
same ring stack. Here every cluster that no other path made a stem, and that is sparse (its
fullest band slice holds fewer than :data:`~stemmap.cloud.axisfit.AXIS_SPARSE_FACTOR` x
``min_slice_points`` points), is measured over :data:`TALL_RANGE` instead of the band:

1. a provisional axis from the cluster's own band returns (:func:`~stemmap.cloud.axisfit.
   _fit_axes`: leaning ring stack, taper prior, Huber weights, trimming);
2. the returns of the whole range -- the band as read (before the vertical filter, which
   removes sparse stems' returns) and the reach outside it -- within
   :func:`~stemmap.cloud.axisfit._reach_tolerance` of the provisional ring at their height
   are gathered, the stack is refitted, and gathered again about the refit
   (:data:`GATHER_ROUNDS` times): the axis and radius come from the stem's returns;
3. the fit is tested as the shared-axis fit's reach variant (:func:`~stemmap.cloud.axisfit.
   _axis_row`: radius window, RMS <= 1.5 noise floors, lean <= 10 deg, arc, >= 16 inliers,
   >= 3 inliers in the top bin and in 5 of the 6 bins of about 0.4 m over the range -- a
   trunk goes on above the band, a shrub does not -- every bin's median residual, taper,
   and the DBH standard error, the larger of the posterior's and the delete-one-bin
   jackknife's, <= 1.5 cm).

The stem's ``dbh_rule`` says where it was measured and why (:data:`RULE_TALL`); its radius
is the stack's at breast height. Clusters within a found stem's footprint are left alone, so
no stem another path found is changed.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.axisfit import (
    AXIS_RANGE,
    AXIS_SPARSE_FACTOR,
    _axis_residuals,
    _axis_row,
    _bins,
    _bins_needed,
    _fit_axes,
    _reach_tolerance,
)
from stemmap.cloud.config import StemConfig
from stemmap.cloud.pooled import POOL_MAX_LEAN
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: heights (m above the base) the sparse stems are measured over
TALL_RANGE = AXIS_RANGE
#: gather -> refit rounds after the provisional axis
GATHER_ROUNDS = 2
#: the ``dbh_rule`` of a stem measured here
RULE_TALL = (
    f"breast height, one ring stack over {TALL_RANGE[0]:.1f}-{TALL_RANGE[1]:.1f} m "
    "(sparse stem: too few band returns per slice)"
)


def _sparse_todo(
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    pts: FloatArray,
    kc: int,
    ns: int,
    cfg: StemConfig,
    found: FloatArray,
) -> NDArray[np.bool_]:
    """Clusters (of ``kc``) worth the taller-band fit: >= ``cfg.min_slice_points`` band
    points, fullest slice < :data:`AXIS_SPARSE_FACTOR` x ``cfg.min_slice_points``, and the
    centroid outside every found stem's disc grown by 10 cm (``found`` (M, 3): x, y, DBH)."""
    cnt = np.bincount(cid * ns + sli, minlength=kc * ns).reshape(kc, ns)
    n = cnt.sum(axis=1)
    ok = (n >= cfg.min_slice_points) & (cnt.max(axis=1) < AXIS_SPARSE_FACTOR * cfg.min_slice_points)
    if found.shape[0] and ok.any():
        w = np.maximum(n, 1)
        cen = np.column_stack(
            (
                np.bincount(cid, pts[:, 0], minlength=kc) / w,
                np.bincount(cid, pts[:, 1], minlength=kc) / w,
            )
        )
        d = np.hypot(*(cen[:, None, :] - found[None, :, :2]).transpose(2, 0, 1))
        ok &= ~np.any(d <= found[None, :, 2] / 2 + 0.1, axis=1)
    return np.asarray(ok, dtype=bool)


def _gather(
    t: FloatArray,
    tree: cKDTree,
    all_xy: FloatArray,
    all_h: FloatArray,
    cfg: StemConfig,
    noise_floor: float,
    wide: bool,
) -> NDArray[np.int64]:
    """Indices of the range's returns within the reach tolerance of ring stack ``t``: its
    band's own spread, plus (``wide``: ``t`` was fitted on the band alone) lean and taper
    error beyond the band; a stack fitted over the whole range has no such extrapolation."""
    lo_b, hi_b = cfg.band
    if not wide:
        lo_b, hi_b = TALL_RANGE
    lo, hi = TALL_RANGE
    far = max(lo_b - lo, hi - hi_b, 0.0)
    r = float(t[4])
    tol_far = float(_reach_tolerance(r, noise_floor, far))
    c_far = max(abs(cfg.breast_height - lo), abs(hi - cfg.breast_height))
    near = np.asarray(
        tree.query_ball_point(t[:2], r + POOL_MAX_LEAN * c_far + tol_far),
        dtype=np.int64,
    )
    if near.size == 0:
        return near
    h = all_h[near]
    dh = np.maximum(lo_b - h, h - hi_b).clip(min=0.0)
    d, _ = _axis_residuals(
        t[None, :], all_xy[near], h - cfg.breast_height, np.zeros(near.size, np.int64)
    )
    return np.sort(near[np.abs(d) <= _reach_tolerance(r, noise_floor, dh)])


def _sparse_tall_stems(
    pts: FloatArray,
    hts: FloatArray,
    cid: NDArray[np.int64],
    sli: NDArray[np.int64],
    todo: NDArray[np.bool_],
    cfg: StemConfig,
    ns: int,
    noise_floor: float,
    band_xy: FloatArray,
    band_h: FloatArray,
    reach: tuple[FloatArray, FloatArray] | None,
) -> list[tuple[float, ...]]:
    """Stems of the clusters ``todo`` (:func:`_sparse_todo`) from one ring stack each over
    :data:`TALL_RANGE` (module docstring). ``pts``, ``hts``, ``cid``, ``sli``: the clustered
    band points (after the vertical filter), their heights, cluster and slice (of ``ns``);
    ``band_xy``, ``band_h``: the band as read; ``reach``: (xy, heights) of the returns in
    the range outside the band, or None. Returns the band's stem rows."""
    if not todo.any():
        return []
    from scipy.spatial import cKDTree

    sel = todo[cid]
    _, ids0 = np.unique(cid[sel], return_inverse=True)
    first = _fit_axes(
        pts[sel], hts[sel] - cfg.breast_height, ids0.astype(np.int64), sli[sel], ns, noise_floor
    )
    lo, hi = TALL_RANGE
    inr = (band_h >= lo) & (band_h <= hi)
    xs, hs = [band_xy[inr]], [band_h[inr]]
    if reach is not None and reach[0].shape[0]:
        xs.append(reach[0])
        hs.append(reach[1])
    all_xy, all_h = np.vstack(xs), np.concatenate(hs)
    if all_xy.shape[0] == 0:
        return []
    tree = cKDTree(all_xy)
    bc, th_b = _bins(lo, hi)
    nb = bc.size
    rows: list[tuple[float, ...]] = []
    for j in np.flatnonzero(first.alive):
        t = first.params[j]
        fit = None
        for k in range(GATHER_ROUNDS):
            if not (np.all(np.isfinite(t)) and 0 < t[4] <= cfg.max_diameter / 2):
                fit = None
                break
            near = _gather(t, tree, all_xy, all_h, cfg, noise_floor, k == 0)
            if near.size < 2 * cfg.min_slice_points:
                fit = None
                break
            b = np.clip(((all_h[near] - lo) // th_b).astype(np.int64), 0, nb - 1)
            fit = _fit_axes(
                all_xy[near],
                all_h[near] - cfg.breast_height,
                np.zeros(near.size, np.int64),
                b,
                nb,
                noise_floor,
            )
            if not fit.alive[0]:
                fit = None
                break
            t = fit.params[0]
        if fit is None:
            continue
        cnt = np.bincount(fit.s_i, minlength=nb)
        row = _axis_row(fit, 0, cnt, cfg, bc, noise_floor, _bins_needed(nb))
        if row is not None and math.isfinite(row[2]):
            rows.append(row)
    return rows
