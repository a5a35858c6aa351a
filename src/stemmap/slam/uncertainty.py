"""Per-tree uncertainty and confidence for the stem map of any SLAM back-end (a post-step).

Every back-end returns tree positions and mean diameters, but they differ in what else they
know: the EKF has a covariance and per-observation diameter moments, iSAM2 a marginal
covariance but no diameter spread, FastSLAM per-particle landmark EKFs, Forestrix nothing.
:func:`annotate_uncertainty` fills the gaps the same way for all of them, from the run itself
(no ground truth):

1. **Association.** Every detection is placed in the map with the estimated trajectory
   (:func:`~stemmap.slam.base.observation_to_world`) and given to the nearest mapped tree within
   ``gate`` metres.
2. **Diameter and its std** (``diameter``, ``diameter_std``, m). Where the detections carry
   their own diameter standard deviation ``sd`` (``TreeFrames.diameter_std``, the scan fit's),
   the tree's diameter is their inverse-variance weighted mean, weights ``1 / (sd^2 + f^2)``
   (:func:`fused_diameters`, ``f`` = :data:`DIAMETER_FLOOR`): a far, few-return detection with
   a loose fit counts less than a near one (every back-end averages its detections with equal
   weights, e.g. the tree DB's eq. (2); on real drive-by passes the per-scan bias grows to
   +4-9 cm beyond 10 m). ``diameter_std`` is the standard error
   ``sqrt(s^2 (1 + (n - 1) rho) / n + b^2)`` with ``s`` the (weighted) sample standard
   deviation of the tree's per-detection diameters, ``n`` their (effective) number, ``rho``
   (:data:`DIAMETER_RHO`) the correlation of one trunk's per-scan diameter errors: the design
   effect of clustered samples (Kish 1965,
   "Survey Sampling", §5.4) -- scans of one trunk share part of their error (same side seen,
   same bark), which does not average out as 1 / sqrt(n) -- and ``b``
   (:data:`DIAMETER_BIAS`) the scale of the detector's per-trunk systematic error, which the
   spread of one trunk's scans cannot show (an independent variance component added in
   quadrature). NaN with fewer than 2 diameters.
3. **Position covariance** (``cov``), only where the back-end gave none (a fallback: every
   registered back-end now reports one; Forestrix's and the tree DB's come from
   :mod:`stemmap.slam.tree_covariance`): the covariance of the associated map-frame detections
   over ``n`` (no pose uncertainty: far too small, docs/algorithms/slam.md "Tree covariances of
   the tree DB and Forestrix").
4. **Confidence** (``confidence`` in [0, 1]): the posterior probability that the landmark is a
   real, repeatedly detectable object rather than a spurious landmark, from how often it was
   detected when it should have been (:func:`expected_detections`: in view, not occluded by a
   nearer mapped tree, within the range that holds 90 % of the run's detections) -- a mixture
   of real landmarks detected with a range-dependent probability and spurious ones detected
   with a constant lower one, fitted by EM to the whole map (:func:`detection_confidence`),
   with the per-frame evidence tempered by the measured run length of hits and misses
   (:func:`run_length_factor`) and by the overdispersion of real trees' detection rates
   (:func:`overdispersion`: without it one tree's evidence grew with its frame count, and
   real thin trunks seen 100-400 times got posteriors of 1e-9 to 1e-35 on the simulator,
   1e-130 on Victoria Park). The EM needs only per-(tree, range bin) counts of expected
   frames and hits and per-tree counts of runs (:class:`DetectionCounts`), which
   :func:`annotate_uncertainty` accumulates a block of frames at a time: its memory does not
   grow with the length of the drive (the (tree, frame) rows do: 1.5 million on a 10x Victoria
   Park replay).

Calibration on the simulator: benchmarks/uncertainty_calibration.py (docs/outputs.md).

**Fusing one pass's detections of a trunk into a position** (:func:`fused_positions`, a
function for callers that fuse detections by their own covariance; no back-end's output uses
it, but the tree DB's and Forestrix's tree covariance apply the same correlation within a pass,
:mod:`stemmap.slam.tree_covariance`): the information-weighted mean, with a covariance that
treats the detections' centre
errors as correlated within the pass (:data:`CENTRE_RHO`) -- the same design effect as the
diameter's (:func:`correlated_mean_covariance`, of which :func:`fused_diameters`' standard
error is the 1 x 1 case).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from stemmap.errors import ConfigError, InputError
from stemmap.types import FloatArray, StemMap

if TYPE_CHECKING:  # pragma: no cover
    from stemmap.slam.base import SlamProblem, SlamResult

__all__ = [
    "CENTRE_RHO",
    "DIAMETER_BIAS",
    "DIAMETER_FLOOR",
    "DIAMETER_RHO",
    "DetectionCounts",
    "MixtureFit",
    "UncertaintyReport",
    "annotate_uncertainty",
    "confidence_from_counts",
    "correlated_mean_covariance",
    "detection_confidence",
    "diameter_standard_errors",
    "expected_detections",
    "fused_diameters",
    "fused_positions",
    "overdispersion",
    "run_length_factor",
]


#: Intra-trunk correlation of per-frame diameter errors (module doc, item 2), set on REAL trunk
#: geometry: virtual drive-by 2D scans of every real breast-height slice of the shared datasets
#: (benchmarks/diameter_rho_real.py) give rho = 1 on every leave-one-dataset-out split -- a
#: trunk's per-scan errors are dominated by a shared bias (+4-5 cm for the SICK-class edge model
#: on real one-sided arcs, per-scan spread 1-1.5 cm MAD), so averaging n scans does not reduce
#: it and the standard error is the per-scan spread ``s``. On the simulator's ideal cylinders
#: this is conservative (benchmarks/uncertainty_calibration.py fitted 0.03 there).
DIAMETER_RHO = 1.0

#: Per-trunk systematic DBH error scale ``b`` (m) of the scan detector (module doc, item 2), set
#: on the same real passes as :data:`DIAMETER_RHO` (benchmarks/diameter_rho_real.py, the
#: default ``stemmap`` detector since the Dec 5 fix of the passes' detector): a pass's mean
#: error is a per-trunk bias the per-scan spread cannot show. A constant is the simplest form
#: that moves the held-out datasets towards a median |z| of 0.674. It depends on the scanner
#: model: for the SICK-class averaging scanner (the default detector's model, which ``stemmap
#: map`` and ``stemmap demo`` run on 2D scans) 0.053 m on all its passes (0.051-0.061
#: leave-one-dataset-out; held out 0.73 / 0.89 / 0.69 / 0.65 with 0.05 m against 0.88 / 1.18 /
#: 1.41 / 1.43 without it: aRchi Tree_1, lidR, TreeLS pine, pine_plot). For a first-echo
#: (nearest-return, ``--footprint``) scanner the fit gives 0 (rho = 1 alone is already
#: conservative there: held out 0.26-0.70), so such detections are mapped with ``bias=0``.
#: Conservative on the simulator's ideal cylinders (docs/outputs.md).
DIAMETER_BIAS = 0.05

#: Per-detection diameter error floor ``f`` (m) of :func:`fused_diameters`: the part of one
#: detection's DBH error that its fit covariance cannot show (bark, the edge model of a
#: one-sided arc), so that one very tight fit does not outweigh the rest. Chosen leave-one-
#: dataset-out on the real drive-by passes (benchmarks/map_dbh_fusion.py, docs/outputs.md "Map
#: DBH fusion"): the smallest floor of the grid whose map DBH RMSE on the simulator's demo
#: drives is no worse than unweighted (0.02 m in every fold; the real passes alone prefer
#: 0.001 m). Held out, the fused DBH RMSE falls on every real dataset (aRchi Tree_1 6.29 ->
#: 5.69 cm, lidR 6.61 -> 6.21, TreeLS pine 2.98 -> 2.74, pine_plot 4.35 -> 4.27).
DIAMETER_FLOOR = 0.02

#: Correlation of the centre errors of one trunk's detections in one pass (:func:`fused_positions`),
#: the position analogue of :data:`DIAMETER_RHO`: the detections of a trunk along a drive-by pass
#: see the same outline and bark, so their errors do not average out as ``1 / n``. Set on REAL
#: trunk geometry (benchmarks/centre_pass_fusion.py, first-echo 0.5 deg drive-by passes of every
#: real breast-height slice, seeds 0-4; docs/algorithms/scan-detection.md "Correlated detections
#: of a pass"): the value whose pooled median Mahalanobis distance of the fused positions is the
#: calibrated 1.177, with the whole detection covariance shared. Leave-one-dataset-out 1.0 / 0.5 /
#: 0.45 (TreeLS plot / pine / lidR held out), 0.5 on all three; held out, median d 0.73-0.90
#: (plot), 1.10-1.39 (pine), 1.94-2.18 (lidR) at 0-3 cm of range noise, against 2.2-8.2 for
#: independent detections (rho 0). Sharing only the outline's terms (``centre_sd_along`` /
#: ``centre_sd_across``) stays overconfident even at rho 1 (held out 1.34-4.03).
CENTRE_RHO = 0.5

#: Detections converted (and frames' rows counted, /64) per block in
#: :func:`annotate_uncertainty`: bounds its temporaries on a long drive.
CHUNK = 65536


@dataclass(frozen=True)
class MixtureFit:
    """Binomial mixture of :func:`detection_confidence`: per-tree ``confidence`` and the fitted
    ``p_detect`` (real), ``p_false`` (spurious), ``prior_real``, EM ``iterations``, the
    ``run_length`` factor and the ``overdispersion`` ``rho`` (:func:`overdispersion`)."""

    confidence: FloatArray
    p_detect: float
    p_false: float
    prior_real: float
    iterations: int
    run_length: float = 1.0
    overdispersion: float = 0.0


class DetectionCounts:
    """Sufficient statistics of (tree, range, hit) rows for :func:`detection_confidence`.

    Per tree and range bin (``bin_width`` m): ``trials`` (frames in which the tree was
    expected) and ``hits``; per tree the number of ``runs`` of equal outcomes in time order and
    the ``last`` outcome (-1 before the first row). Rows are added in time order with
    :meth:`add`, in as many chunks as wanted: the EM and the run-length factor need only these
    counts, so their memory is (trees x bins), whatever the length of the drive.
    """

    def __init__(self, n_trees: int, bin_width: float = 2.0) -> None:
        if bin_width <= 0:
            raise ConfigError(f"detection_confidence: bin_width must be > 0 m, got {bin_width}.")
        self.bin_width = float(bin_width)
        self.n_trees = int(n_trees)
        self.trials = np.zeros((self.n_trees, 0), dtype=np.int64)
        self.hits = np.zeros((self.n_trees, 0), dtype=np.int64)
        self.runs = np.zeros(self.n_trees, dtype=np.int64)
        self.last = np.full(self.n_trees, -1, dtype=np.int8)

    def add(self, tree_index: ArrayLike, ranges: ArrayLike, hit: ArrayLike) -> None:
        """Count rows that follow (in time) every row added before."""
        ti = np.asarray(tree_index, dtype=np.int64).reshape(-1)
        rr = np.asarray(ranges, dtype=np.float64).reshape(-1)
        y = np.asarray(hit, dtype=bool).reshape(-1)
        if not (ti.shape == rr.shape == y.shape):
            raise ConfigError(
                "detection_confidence: tree_index, ranges and hit must have one length."
            )
        if ti.size == 0:
            return
        bins = np.floor(rr / self.bin_width).astype(np.int64)
        nb = max(int(bins.max()) + 1, self.trials.shape[1])
        if nb > self.trials.shape[1]:
            pad = ((0, 0), (0, nb - self.trials.shape[1]))
            self.trials, self.hits = np.pad(self.trials, pad), np.pad(self.hits, pad)
        cell = ti * nb + bins
        size = self.n_trees * nb
        self.trials += np.bincount(cell, minlength=size).reshape(self.n_trees, nb)
        self.hits += np.bincount(cell[y], minlength=size).reshape(self.n_trees, nb)
        # runs: a tree's first row ever starts one; then every change of outcome
        order = np.argsort(ti, kind="stable")
        ts, ys = ti[order], y[order].astype(np.int8)
        first = np.ones(ts.size, dtype=bool)
        first[1:] = ts[1:] != ts[:-1]
        prev = np.empty_like(ys)
        prev[1:] = ys[:-1]
        prev[first] = self.last[ts[first]]
        self.runs += np.bincount(ts[prev != ys], minlength=self.n_trees)
        last = np.ones(ts.size, dtype=bool)
        last[:-1] = first[1:]
        self.last[ts[last]] = ys[last]

    def run_length(self) -> float:
        """:func:`run_length_factor` of the rows counted so far."""
        n = self.trials.sum(axis=1).astype(np.float64)
        h = self.hits.sum(axis=1).astype(np.float64)
        return _run_length(n, h, self.runs)


def detection_confidence(
    tree_index: ArrayLike,
    ranges: ArrayLike,
    hit: ArrayLike,
    n_trees: int,
    *,
    bin_width: float = 2.0,
    max_iter: int = 300,
    tol: float = 1e-9,
) -> MixtureFit:
    """Posterior probability of being real from per-frame hits and misses (module doc, item 4).

    One row per (tree, frame) in which the tree was expected in view: ``tree_index``, its
    ``range`` from the sensor and whether a detection was within the gate (``hit``). A real
    tree is detected with a probability ``p_d(range)`` that depends on the range (piecewise
    constant in ``bin_width`` bins: small trunks far away return few points); a spurious
    landmark with a constant ``p_f``. EM for this two-component mixture over trees
    (Dempster, Laird & Rubin 1977, §4.3): E-step responsibilities ``w_j`` from the Bernoulli
    log-likelihoods, M-step ``pi`` = mean ``w_j``, ``p_d`` per bin and ``p_f`` = the
    ``w``-weighted / ``(1 - w)``-weighted hit rates. ``p_f`` is capped below the lowest
    ``p_d`` so the components cannot swap. Start: ``w_j = 0.9``. The rows are reduced to
    :class:`DetectionCounts` first (:func:`confidence_from_counts`).

    Returns
    -------
    MixtureFit
        ``p_detect`` is the row-weighted mean of ``p_d(range)`` over the real component.
    """
    counts = DetectionCounts(n_trees, bin_width)
    counts.add(tree_index, ranges, hit)
    return confidence_from_counts(counts, max_iter=max_iter, tol=tol)


def confidence_from_counts(
    counts: DetectionCounts, *, max_iter: int = 300, tol: float = 1e-9
) -> MixtureFit:
    """:func:`detection_confidence` on the rows' counts (the same EM, summed per tree and bin
    instead of per row: equal up to the order of floating-point sums)."""
    eps = 1e-4
    n_trees = counts.n_trees
    nt = counts.trials.astype(np.float64)
    ht = counts.hits.astype(np.float64)
    mt = nt - ht
    n_j, h_j = nt.sum(axis=1), ht.sum(axis=1)
    has = n_j > 0
    w = np.full(n_trees, 0.9)
    if not np.any(has):
        return MixtureFit(w, math.nan, math.nan, 0.9, 0, 1.0)
    k_eff = counts.run_length()
    rho = 0.0
    prev = -math.inf
    it = 0
    pd_bin = np.full(nt.shape[1], 0.5)
    pf = 0.1
    pi = 0.9
    for it in range(1, max_iter + 1):  # noqa: B007 -- reported
        # M-step from the current responsibilities
        num = w @ ht
        den = w @ nt
        glob = float(num.sum() / max(den.sum(), eps))
        # bins with little weight borrow the pooled rate (1 pseudo-row of weight 5)
        pd_bin = np.clip((num + 5.0 * glob) / (den + 5.0), eps, 1 - eps)
        pf = float(np.sum((1 - w) * h_j) / max(float(np.sum((1 - w) * n_j)), eps))
        pf = float(np.clip(pf, eps, 0.9 * float(pd_bin.min())))
        pi = float(np.clip(w[has].mean(), eps, 1 - eps))
        # E-step, tempered per tree by the run length and the between-tree overdispersion
        rho = overdispersion(h_j, nt @ pd_bin, nt @ (pd_bin * (1 - pd_bin)), n_j, w, k_eff)
        temper = k_eff * (1.0 + np.maximum(n_j / k_eff - 1.0, 0.0) * rho)
        lr = (ht @ np.log(pd_bin) + mt @ np.log1p(-pd_bin)) / temper + math.log(pi)
        lf = (h_j * math.log(pf) + (n_j - h_j) * math.log1p(-pf)) / temper + math.log1p(-pi)
        top = np.maximum(lr, lf)
        ll = float(np.sum((top + np.log(np.exp(lr - top) + np.exp(lf - top)))[has]))
        w = np.where(has, 1.0 / (1.0 + np.exp(np.clip(lf - lr, -700, 700))), pi)
        if ll - prev < tol * max(1.0, abs(ll)):
            break
        prev = ll
    p_det = float(np.sum(w @ (nt * pd_bin)) / max(float(np.sum(w * n_j)), eps))
    return MixtureFit(w, p_det, pf, pi, it, k_eff, rho)


def overdispersion(
    hits: FloatArray,
    expected: FloatArray,
    var: FloatArray,
    n: FloatArray,
    w: FloatArray,
    k_eff: float = 1.0,
) -> float:
    """Intra-tree correlation ``rho`` of the detections of real trees (method of moments).

    Real trees do not share one detection rate: a thin trunk returns too few points beyond a
    shorter range than a thick one, a trunk behind an unmapped bush is missed for the whole
    pass. Their hit counts are then overdispersed against the binomial of the fitted
    ``p_d(range)``: with ``m = n / k_eff`` effective trials the Pearson statistic
    ``X_j = (h_j - E_j)^2 / (V_j k_eff)`` has expectation ``1 + (m_j - 1) rho`` (the
    beta-binomial variance, e.g. Williams 1982, Appl. Statist. 31, eq. 1). ``rho`` is the
    median of the per-tree moment estimates ``(X_j - 1) / (m_j - 1)``, weighted by each tree's
    responsibility ``w_j`` of being real, clipped to [0, 1]: the median, because a few real
    trees hidden for a whole pass (or spurious ones still weighted as real) would set a mean
    and temper every tree as much as them (on 6 simulated runs the weighted mean, 0.1-0.16,
    left spurious landmarks at confidence ~0.8; benchmarks/confidence_sim_scans.py and
    docs/outputs.md). Dividing a tree's log-likelihoods
    by its design effect ``1 + (m_j - 1) rho`` (Kish 1965, §5.4) bounds the evidence one tree
    can give at about ``1 / rho`` independent trials, instead of growing with its frame count
    (a real 12 cm trunk seen 187 times at half the rate of the thick ones got posterior 1e-32).
    """
    m = n / k_eff
    ok = (m > 1.0) & (var > 0)
    den = float(np.sum(w[ok] * (m[ok] - 1.0)))
    if den <= 0:
        return 0.0
    x = (hits[ok] - expected[ok]) ** 2 / (var[ok] * k_eff)
    rj = (x - 1.0) / (m[ok] - 1.0)
    o = np.argsort(rj)
    cw = np.cumsum(w[ok][o])
    med = rj[o][np.searchsorted(cw, 0.5 * cw[-1])]
    return float(np.clip(med, 0.0, 1.0))


def _run_length(n: FloatArray, hits: ArrayLike, runs: ArrayLike) -> float:
    """The run-length factor from per-tree rows ``n``, ``hits`` and observed ``runs``."""
    p = np.divide(np.asarray(hits, dtype=np.float64), n, out=np.zeros_like(n), where=n > 0)
    expected = np.where(n > 0, 1.0 + 2.0 * (n - 1.0) * p * (1.0 - p), 0.0)
    observed = float(np.sum(np.asarray(runs, dtype=np.float64)))
    return float(max(1.0, expected.sum() / max(observed, 1.0)))


def run_length_factor(tree_index: ArrayLike, hit: ArrayLike) -> float:
    """How many consecutive frames behave as one independent trial (>= 1).

    Hits and misses of one tree come in runs (a trunk hidden behind an unmapped bush is
    missed for many frames in a row), so per-frame Bernoulli log-likelihoods overstate the
    evidence. With the Wald-Wolfowitz expectation of the number of runs of ``n`` independent
    trials with hit rate ``p``, ``1 + 2 (n - 1) p (1 - p)``, the factor is the ratio of the
    expected to the observed number of runs, summed over trees; the log-likelihoods are
    divided by it (a tempered, composite likelihood). Rows of a tree must be in time order.
    """
    ti = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    y = np.asarray(hit, dtype=bool).reshape(-1)
    if ti.size < 2:
        return 1.0
    order = np.argsort(ti, kind="stable")
    ts, ys = ti[order], y[order]
    n = np.bincount(ts).astype(np.float64)
    change = (ts[1:] == ts[:-1]) & (ys[1:] != ys[:-1])
    runs = np.bincount(ts[1:][change], minlength=n.size) + (n > 0)
    return _run_length(n, np.bincount(ts, ys.astype(np.float64)), runs)


def expected_detections(
    trees_xy: ArrayLike,
    diameters: ArrayLike,
    sensor_poses: ArrayLike,
    frame_ptr: ArrayLike,
    detections_xy: ArrayLike,
    fov: Any,
    *,
    gate: float,
) -> tuple[NDArray[np.int64], FloatArray, NDArray[np.bool_]]:
    """Rows (tree, range, hit) for every frame in which a tree was expected: in the field of
    view and range window and not occluded by a nearer mapped tree
    (:func:`~stemmap.slam.negative.expected_visibility`); ``hit`` when a detection of that
    frame lies within ``gate`` of the tree (the same counting as
    :func:`~stemmap.slam.negative.negative_information`)."""
    from stemmap.slam.negative import expected_visibility

    xy = np.asarray(trees_xy, dtype=np.float64).reshape(-1, 2)
    radii = np.asarray(diameters, dtype=np.float64).reshape(-1) / 2.0
    sp = np.asarray(sensor_poses, dtype=np.float64).reshape(-1, 3)
    ptr = np.asarray(frame_ptr, dtype=np.int64).reshape(-1)
    det = np.asarray(detections_xy, dtype=np.float64).reshape(-1, 2)
    rows_t: list[NDArray[np.int64]] = []
    rows_r: list[FloatArray] = []
    rows_h: list[NDArray[np.bool_]] = []
    if xy.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool)
    index = cKDTree(xy)
    reach = fov.range_max + 2.0
    for f in range(sp.shape[0]):
        near = np.asarray(index.query_ball_point(sp[f, :2], reach), dtype=np.int64)
        if near.size == 0:
            continue
        in_view, occluded = expected_visibility(xy[near], radii[near], sp[f], fov)
        expect = in_view & ~occluded
        if not np.any(expect):
            continue
        cand = near[expect]
        z = det[ptr[f] : ptr[f + 1]]
        seen = np.zeros(cand.size, dtype=bool)
        if z.shape[0]:
            rel = xy[cand][:, None, :] - z[None, :, :]
            dd = np.hypot(rel[..., 0], rel[..., 1])
            seen = np.any(dd <= gate, axis=1)
        rows_t.append(cand)
        rows_r.append(np.hypot(*(xy[cand] - sp[f, :2]).T))
        rows_h.append(seen)
    if not rows_t:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool)
    return np.concatenate(rows_t), np.concatenate(rows_r), np.concatenate(rows_h)


def diameter_standard_errors(
    tree_index: ArrayLike,
    diameters: ArrayLike,
    n_trees: int,
    *,
    rho: float = 0.0,
    bias: float = 0.0,
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Per-tree diameter statistics of the associated detections, every detection counted the
    same (:func:`fused_diameters` without per-detection standard deviations).

    Returns
    -------
    se : ndarray (n_trees,), m
        ``sqrt(s^2 (1 + (n - 1) rho) / n + bias^2)`` (module doc, item 2); NaN where n < 2.
    spread : ndarray (n_trees,), m
        ``s``, the sample standard deviation of one detection's diameter; NaN where n < 2.
    n : ndarray (n_trees,), int
    """
    _, se, spread, n = fused_diameters(tree_index, diameters, n_trees, rho=rho, bias=bias)
    return se, spread, np.rint(n).astype(np.int64)


def fused_diameters(
    tree_index: ArrayLike,
    diameters: ArrayLike,
    n_trees: int,
    *,
    diameter_std: ArrayLike | None = None,
    floor: float = DIAMETER_FLOOR,
    rho: float = 0.0,
    bias: float = 0.0,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per-tree diameter fused from the associated detections, weighted by their own
    uncertainty, and its standard error (module doc, item 2).

    Detection ``i`` of a tree gets the inverse-variance weight ``w_i = 1 / (sd_i^2 + f^2)``
    (``sd_i`` its ``diameter_std``, the fit's; ``f`` = ``floor``, the error every detection has
    that its fit cannot show: bark, the edge model). The diameter is ``sum w d / sum w``; the
    spread ``s`` is the reliability-weighted sample standard deviation
    ``sqrt(sum w (d - mean)^2 / (V1 - V2 / V1))`` (``V1 = sum w``, ``V2 = sum w^2``), the
    effective number of detections ``n = V1^2 / V2``, and the standard error
    ``sqrt(s^2 (1 + (n - 1) rho) / n + bias^2)``. With equal weights (``diameter_std`` None or
    all NaN) these are the plain mean, sample standard deviation and count. A NaN ``sd_i``
    among finite ones counts as the median finite one.

    Returns
    -------
    diameter : ndarray (n_trees,), m (NaN without a diameter)
    se : ndarray (n_trees,), m (NaN with fewer than 2 diameters)
    spread : ndarray (n_trees,), m (NaN with fewer than 2 diameters)
    n_eff : ndarray (n_trees,) -- effective number of detections (0 without a diameter)
    """
    if not (0.0 <= rho <= 1.0):
        raise ConfigError(f"fused_diameters: rho must be in [0, 1], got {rho}.")
    if not (bias >= 0.0 and math.isfinite(bias)):
        raise ConfigError(f"fused_diameters: bias must be >= 0 m, got {bias}.")
    if not (floor > 0.0 and math.isfinite(floor)):
        raise ConfigError(f"fused_diameters: floor must be > 0 m, got {floor}.")
    idx = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    d = np.asarray(diameters, dtype=np.float64).reshape(-1)
    sd = (
        np.full(d.shape, np.nan)
        if diameter_std is None
        else np.asarray(diameter_std, dtype=np.float64).reshape(-1)
    )
    if sd.shape != d.shape or idx.shape != d.shape:
        raise ConfigError(
            f"fused_diameters: {idx.size} tree indices, {d.size} diameters, {sd.size} stds."
        )
    ok = (idx >= 0) & np.isfinite(d)
    idx, d, sd = idx[ok], d[ok], sd[ok]
    fin = np.isfinite(sd)
    if np.any(fin):
        sd = np.where(fin, sd, float(np.median(sd[fin])))
        w = 1.0 / (sd * sd + floor * floor)
    else:
        w = np.ones(d.shape)
    v1 = np.bincount(idx, w, minlength=n_trees)
    v2 = np.bincount(idx, w * w, minlength=n_trees)
    cnt = np.bincount(idx, minlength=n_trees)
    wd = np.bincount(idx, w * d, minlength=n_trees)
    mean = np.divide(wd, v1, out=np.full(n_trees, np.nan), where=v1 > 0)
    dev = d - mean[idx]
    ss = np.bincount(idx, w * dev * dev, minlength=n_trees)
    denom = v1 - np.divide(v2, v1, out=np.zeros(n_trees), where=v1 > 0)
    two = cnt > 1
    var = np.divide(ss, denom, out=np.full(n_trees, np.nan), where=two & (denom > 0))
    n_eff = np.divide(v1 * v1, v2, out=np.zeros(n_trees), where=v2 > 0)
    # every detection's error has the variance s^2, all of it shared with correlation rho:
    # s^2 (1 + (n - 1) rho) / n, the design effect (the 1 x 1 case of the positions' fusion)
    wn = w / np.where(v1 > 0, v1, 1.0)[idx]
    s2 = np.nan_to_num(var)[idx].reshape(-1, 1, 1)
    dvar = correlated_mean_covariance(
        idx, wn.reshape(-1, 1, 1), np.zeros_like(s2), s2, n_trees, rho=rho
    )[:, 0, 0]
    se = np.sqrt(np.where(np.isfinite(var), dvar, np.nan) + bias**2)
    return mean, np.where(two, se, np.nan), np.sqrt(var), n_eff


def correlated_mean_covariance(
    tree_index: ArrayLike,
    weights: ArrayLike,
    independent: ArrayLike,
    shared: ArrayLike,
    n_trees: int,
    *,
    rho: float,
) -> FloatArray:
    """Covariance (n_trees, d, d) of each tree's weighted sum ``sum_k W_k x_k`` of its
    detections' errors ``x_k = a_k + s_k``: ``a_k`` independent between detections (covariance
    ``independent[k]``), ``s_k`` the part they share (covariance ``shared[k]``), correlated
    between two detections of one tree as ``rho S_k^(1/2) S_l^(1/2)`` (``S^(1/2)`` the
    symmetric square root):

    ``sum_k W_k (A_k + (1 - rho) S_k) W_k^T + rho G G^T``, ``G = sum_k W_k S_k^(1/2)``.

    The joint covariance of the shared parts is ``D (R x I) D^T`` with ``D`` the block
    diagonal of the square roots and ``R`` the equicorrelation matrix (positive semi-definite
    for ``rho`` in [0, 1]), so the result is a covariance. ``rho`` = 0: every detection
    independent (``sum W C W^T``); ``rho`` = 1 and equal ``S`` with weights summing to ``I``:
    ``S`` itself, whatever ``n`` -- averaging removes none of a fully shared error. With equal
    scalar weights ``1 / n`` and equal ``S = s^2`` it is Kish's design effect
    ``s^2 (1 + (n - 1) rho) / n`` (:func:`fused_diameters`). Trees without a detection (and
    negative indices) give zeros.
    """
    if not (0.0 <= rho <= 1.0):
        raise ConfigError(f"correlated_mean_covariance: rho must be in [0, 1], got {rho}.")
    idx = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    S = np.asarray(shared, dtype=np.float64)
    d = S.shape[-1] if S.ndim == 3 else 0
    W = np.asarray(weights, dtype=np.float64).reshape(-1, d, d)
    A = np.asarray(independent, dtype=np.float64).reshape(-1, d, d)
    S = S.reshape(-1, d, d)
    if not (W.shape[0] == A.shape[0] == S.shape[0] == idx.shape[0]) or d == 0:
        raise InputError(
            f"correlated_mean_covariance: {idx.size} tree indices, {W.shape[0]} weights, "
            f"{A.shape[0]} independent and {S.shape[0]} shared (K, d, d) covariances."
        )
    ok = idx >= 0
    idx, W, A, S = idx[ok], W[ok], A[ok], S[ok]
    Wt = np.swapaxes(W, 1, 2)
    acc = np.zeros((n_trees, d, d))
    np.add.at(acc, idx, W @ (A + (1.0 - rho) * S) @ Wt)
    if rho > 0 and idx.size:
        if d == 1:
            root = np.sqrt(np.clip(S, 0.0, None))
        else:
            ev, V = np.linalg.eigh(0.5 * (S + np.swapaxes(S, 1, 2)))
            root = (V * np.sqrt(np.clip(ev, 0.0, None))[:, None, :]) @ np.swapaxes(V, 1, 2)
        G = np.zeros((n_trees, d, d))
        np.add.at(G, idx, W @ root)
        acc += rho * (G @ np.swapaxes(G, 1, 2))
    out: FloatArray = 0.5 * (acc + np.swapaxes(acc, 1, 2))
    return out


def fused_positions(
    tree_index: ArrayLike,
    xy: ArrayLike,
    covs: ArrayLike,
    n_trees: int,
    *,
    shared: ArrayLike | None = None,
    rho: float = CENTRE_RHO,
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """A tree's position fused from its detections of one pass (map frame) and its covariance.

    The position is the information-weighted mean ``P sum C_k^-1 x_k``,
    ``P = (sum C_k^-1)^-1`` (``C_k = covs[k]``, (K, 2, 2)), what a tree database or a landmark
    filter fusing detections by their covariance gives. Its covariance treats ``shared[k]``
    (default: all of ``C_k``; e.g. only the outline's terms of a first-echo detection) as
    correlated with ``rho`` between one tree's detections and the rest ``C_k - shared[k]`` as
    independent (:func:`correlated_mean_covariance`, weights ``W_k = P C_k^-1``): with
    ``rho`` 0 it is ``P``, detections independent; with ``rho`` 1 the shared part does not
    shrink with the number of detections. ``rho`` changes the covariance, never the position.
    The default :data:`CENTRE_RHO` is the correlation measured on real drive-by passes.

    Returns
    -------
    xy : ndarray (n_trees, 2) (NaN without a detection)
    cov : ndarray (n_trees, 2, 2) (NaN without a detection)
    n : ndarray (n_trees,), int -- detections fused
    """
    idx = np.asarray(tree_index, dtype=np.int64).reshape(-1)
    z = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    C = np.asarray(covs, dtype=np.float64).reshape(-1, 2, 2)
    S = C if shared is None else np.asarray(shared, np.float64).reshape(-1, 2, 2)
    if not (z.shape[0] == C.shape[0] == S.shape[0] == idx.shape[0]):
        raise InputError(
            f"fused_positions: {idx.size} tree indices, {z.shape[0]} positions, {C.shape[0]} "
            f"covariances and {S.shape[0]} shared covariances must agree."
        )
    ok = idx >= 0
    if np.any(idx[ok] >= n_trees):
        raise InputError(f"fused_positions: tree index >= n_trees {n_trees}.")
    if not (
        np.all(np.isfinite(z[ok])) and np.all(np.isfinite(C[ok])) and np.all(np.isfinite(S[ok]))
    ):
        raise InputError("fused_positions: positions and covariances must be finite.")
    info = np.linalg.inv(C[ok])
    n = np.bincount(idx[ok], minlength=n_trees).astype(np.int64)
    tot = np.zeros((n_trees, 2, 2))
    np.add.at(tot, idx[ok], info)
    has = n > 0
    P = np.full((n_trees, 2, 2), np.nan)
    P[has] = np.linalg.inv(tot[has])
    W = P[idx[ok]] @ info
    mean = np.full((n_trees, 2), np.nan)
    acc = np.zeros((n_trees, 2))
    np.add.at(acc, idx[ok], np.einsum("kij,kj->ki", W, z[ok]))
    mean[has] = acc[has]
    cov = correlated_mean_covariance(idx[ok], W, C[ok] - S[ok], S[ok], n_trees, rho=rho)
    cov[~has] = np.nan
    return mean, cov, n


@dataclass(frozen=True)
class UncertaintyReport:
    """What :func:`annotate_uncertainty` measured (goes to metrics.json)."""

    associated_fraction: float
    p_detect: float
    p_false: float
    prior_real: float
    expected_range_m: float
    gate_m: float
    run_length_frames: float
    overdispersion: float = 0.0
    diameter_rho: float = DIAMETER_RHO
    diameter_bias_m: float = DIAMETER_BIAS
    diameter_floor_m: float = DIAMETER_FLOOR
    diameter_weighted: bool = False

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def annotate_uncertainty(
    result: SlamResult,
    problem: SlamProblem,
    *,
    gate: float = 0.75,
    rho: float = DIAMETER_RHO,
    bias: float = DIAMETER_BIAS,
    floor: float = DIAMETER_FLOOR,
) -> tuple[StemMap, UncertaintyReport]:
    """The result's stem map with ``diameter_std``, missing covariances and ``confidence``
    filled in as the module doc describes. A back-end's finite covariance is kept;
    ``diameter_std`` and ``confidence`` are always recomputed, so that they mean the same for
    every back-end. Where the detections carry their own diameter standard deviation
    (``problem.frames.diameter_std``, the scan detector's fit), the tree's ``diameter`` is
    replaced by their inverse-variance weighted mean (:func:`fused_diameters`, ``floor``) and
    ``diameter_std`` uses the weighted spread; otherwise the back-end's diameter is kept and
    every detection counts the same."""
    from stemmap.slam.base import observation_to_world, sensor_poses
    from stemmap.slam.negative import SensorFov

    if gate <= 0:
        raise ConfigError(f"annotate_uncertainty: gate must be > 0 m, got {gate}.")
    sm = result.stem_map
    fr = problem.frames
    poses = result.trajectory.poses
    nt = len(sm)
    det = np.empty((fr.n_detections, 2))
    for a in range(0, det.shape[0], CHUNK):  # per-detection poses only a chunk at a time
        k = slice(a, a + CHUNK)
        det[k] = observation_to_world(
            poses[fr.frame_index[k]], fr.ranges[k], fr.bearings[k], problem.sensor_offset
        )
    idx = np.full(det.shape[0], -1, dtype=np.int64)
    if nt and det.shape[0]:
        dist, near = cKDTree(sm.xy).query(det, distance_upper_bound=gate)
        hit = np.isfinite(dist)
        idx[hit] = near[hit]
        del dist, near, hit
    weighted = fr.diameter_std is not None and bool(np.any(np.isfinite(fr.diameter_std)))
    dfused, dstd, _, _ = fused_diameters(
        idx,
        fr.diameters,
        nt,
        diameter_std=fr.diameter_std if weighted else None,
        floor=floor,
        rho=rho,
        bias=bias,
    )
    r_hi = float(np.quantile(fr.ranges, 0.9)) if fr.ranges.size else 20.0
    r_hi = min(r_hi, float(problem.max_range))
    fov = SensorFov(problem.fov[0], problem.fov[1], min(1.0, 0.5 * r_hi), r_hi)
    sp = sensor_poses(poses, problem.sensor_offset)
    # the (tree, frame) rows grow with the drive: counted a block of frames at a time
    counts = DetectionCounts(nt)
    diam = sm.diameters if nt else np.zeros(0)
    step = max(1, CHUNK // 64)
    for f0 in range(0, sp.shape[0], step):
        f1 = min(f0 + step, sp.shape[0])
        counts.add(
            *expected_detections(sm.xy, diam, sp[f0:f1], fr.ptr[f0 : f1 + 1], det, fov, gate=gate)
        )
    mix = confidence_from_counts(counts)
    trees = []
    for j, t in enumerate(sm.trees):
        cov = t.cov
        if not np.all(np.isfinite(cov)):
            cov = _mean_covariance(det[idx == j])
        dia = float(dfused[j]) if weighted and np.isfinite(dfused[j]) else t.diameter
        trees.append(
            replace(
                t,
                diameter=dia,
                cov=cov,
                diameter_std=float(dstd[j]),
                confidence=float(mix.confidence[j]),
            )
        )
    report = UncertaintyReport(
        associated_fraction=float(np.mean(idx >= 0)) if idx.size else math.nan,
        p_detect=mix.p_detect,
        p_false=mix.p_false,
        prior_real=mix.prior_real,
        expected_range_m=r_hi,
        gate_m=gate,
        run_length_frames=mix.run_length,
        overdispersion=mix.overdispersion,
        diameter_rho=rho,
        diameter_bias_m=bias,
        diameter_floor_m=floor,
        diameter_weighted=weighted,
    )
    # replace keeps every other field of the map (frame, CRS, iSAM2's joint information)
    return replace(sm, trees=tuple(trees)), report


def _mean_covariance(z: NDArray[np.float64]) -> FloatArray:
    """Covariance of the mean of ``z`` (K, 2); NaN with fewer than 2 points."""
    if z.shape[0] < 2:
        return np.full((2, 2), np.nan)
    c = np.cov(z.T) / z.shape[0]
    return np.asarray(0.5 * (c + c.T), dtype=np.float64)
