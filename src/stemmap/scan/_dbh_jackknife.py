"""The jackknife DBH standard error of a first-echo detection (``dbh_sd_jackknife``; issue 11,
Dec 6, "Junction merges on lidR" in docs/algorithms/scan-detection.md).

The covariance a circle fit reports is the inverse Hessian at its noise model: it is right
when the returns are one circle plus independent noise. When they are not -- a branch root or
a collar at the arc end (a junction), a lobed outline, a return the robust loss half sets
aside -- the fitted radius depends on *which* returns the arc holds far more than that
covariance says, and no residual statistic need show it (the circle bends through the foreign
return). The delete-a-group jackknife measures that dependence directly: the candidate's
returns, in beam order, are cut into ``G = min(n, groups)`` consecutive groups, the same fit is
run once without each group, and

    var_J(r) = (G' - 1) / G' * sum_g (r_(g) - mean r_(.))^2

over the ``G'`` refits that converged (Quenouille 1956; Tukey 1958; the delete-one form and
its upward bias, Efron & Stein 1981, "The jackknife estimate of variance", Ann. Statist. 9;
the delete-a-group form, Shao & Tu 1995, "The Jackknife and Bootstrap", sec. 2.3 / 5.2). It is
a variance estimate that does not assume the fit's model holds (a misspecification-robust
"sandwich"-type estimate). A group that holds an end return leaves that end occluded in its
refit: without its edge return the arc's silhouette is no longer known there (as
``cut_ends`` treats a trimmed end).

The reported radius variance becomes ``max(C_rr, c^2 var_J)`` (``c`` = ``dbh_sd_jackknife``):
only the radius diagonal can grow (the matrix stays positive semi-definite), positions,
diameters and every test are unchanged (the tests read the fit's own covariance before this
runs on the output candidates). On the real slices the plain jackknife (``c`` = 1) is 2-3x
wider than the errors (few-return first-echo arcs: an end left out takes its silhouette with
it); ``c`` is chosen leave-one-dataset-out as the outline term of ``dbh_sd_outline`` was.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from stemmap.scan._segment_fits import _fit_segments, fit_sigma
from stemmap.scan.segment import Segments

if TYPE_CHECKING:
    from stemmap.types import FloatArray

#: Largest number of consecutive groups of returns left out in turn (a candidate with fewer
#: returns is the delete-one jackknife).
JACKKNIFE_GROUPS = 10
#: Least returns a refit keeps (a circle has three parameters).
_MIN_KEEP = 3


def group_ids(counts: np.ndarray, groups: int = JACKKNIFE_GROUPS) -> np.ndarray:
    """Group of every return (flattened, segment after segment): return ``i`` of a segment of
    ``n`` returns is in group ``floor(i G / n)``, ``G = min(n, groups)`` (consecutive runs)."""
    n = counts.astype(np.int64)
    g = np.minimum(n, groups)
    seg = np.repeat(np.arange(n.size), n)
    start = np.cumsum(n) - n
    i = np.arange(int(n.sum())) - start[seg]
    out: np.ndarray = (i * g[seg]) // np.maximum(n[seg], 1)
    return out


def jackknife_radius_var(
    segs: Segments,
    sigma: FloatArray,
    method: str = "ours",
    residuals: str = "range",
    groups: int = JACKKNIFE_GROUPS,
) -> FloatArray:
    """Delete-a-group jackknife variance of each segment's fitted radius (module docstring),
    m^2; NaN where fewer than three refits converged. ``sigma`` (K,): the noise the fit
    weights the returns by; the refits are the fit of a first-echo scanner (no averaging edge
    model, no silhouette prior)."""
    k = len(segs)
    n = segs.counts
    gid = group_ids(n, groups)
    lab = segs.labels
    left = n[None, :] - np.stack([np.bincount(lab[gid == g], minlength=k) for g in range(groups)])
    run = (np.arange(groups)[:, None] < np.minimum(n, groups)[None, :]) & (left >= _MIN_KEEP)
    gg, jj = np.nonzero(run)  # every refit: group gg[i] left out of segment jj[i]
    radii = np.full((groups, k), np.nan)
    if gg.size == 0:
        return np.full(k, np.nan)
    # one batch of every refit (a point per kept return of each (group, segment) pair)
    pair_of_point = np.repeat(np.arange(gg.size), n[jj])
    offs = np.arange(pair_of_point.size) - np.repeat(np.cumsum(n[jj]) - n[jj], n[jj])
    idx = segs.start[jj][pair_of_point] + offs
    keep = gid[idx] != gg[pair_of_point]
    idx = idx[keep]
    counts = left[gg, jj]
    stop = np.cumsum(counts)
    first = gid[segs.start[jj]] == gg  # the left-out group holds an end return: occluded
    last = gid[segs.stop[jj] - 1] == gg
    sub = Segments(
        segs.points.take(idx),
        stop - counts,
        stop,
        segs.scan[jj],
        segs.occluded_start[jj] | first,
        segs.occluded_end[jj] | last,
        segs.truncated_start[jj],
        segs.truncated_end[jj],
    )
    _, r, _, ok = _fit_segments(sub, method, sigma[jj], residuals=residuals)
    radii[gg, jj] = np.where(ok, r, np.nan)
    m = np.sum(np.isfinite(radii), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nanmean(np.where(np.isfinite(radii), radii, np.nan), axis=0)
        ss = np.nansum((radii - mean) ** 2, axis=0)
        var: FloatArray = np.where(m >= 3, (m - 1) / np.maximum(m, 1) * ss, np.nan)
    return var


def jackknife_covs(cfg: Any, segs: Segments, covs: FloatArray, sigma: FloatArray) -> FloatArray:
    """``covs`` (K, 3, 3) of the output candidates ``segs`` with ``C_rr`` raised to ``c^2``
    times the jackknife variance of the radius where that is larger (``c`` =
    ``dbh_sd_jackknife``; first-echo
    ``ours`` fits of ``cfg``, a :class:`~stemmap.scan.config.DetectorConfig`; others
    unchanged). ``sigma`` (K,): the tests' noise of each candidate; the refits weight by the
    fit's own noise (``fit_noise_floor``), as the fit did."""
    if not (cfg.dbh_sd_jackknife > 0 and cfg.beam_footprint_deg > 0 and cfg.fit_method == "ours"):
        return covs
    if len(segs) == 0:
        return covs
    f_sigma = fit_sigma(cfg.fit_noise_floor, segs, sigma)
    var = jackknife_radius_var(segs, sigma if f_sigma is None else f_sigma, "ours",
                               cfg.fit_residuals)  # fmt: skip
    out = covs.copy()
    var = cfg.dbh_sd_jackknife**2 * var
    out[:, 2, 2] = np.where(np.isfinite(var), np.fmax(out[:, 2, 2], var), out[:, 2, 2])
    return out
