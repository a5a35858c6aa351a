"""The slice fits at a RANSAC tolerance and the ladder of tighter ones (docs/algorithms/cloud.md
"Ours" step 6 and the refits of step 8), with the choice between the stems they give:

* :class:`_SegmentFits`, :func:`_fit_slices`: the circle fit of every (cluster, slice) segment
  at one RANSAC tolerance (by default :func:`_ransac_tolerance` of the point spacing), and
  the per-slice plausibility test;
* :func:`_tighter_refits`: stems of the clusters the per-stem tests rejected, from their
  slices refitted at ever tighter tolerances (``StemConfig.tighter_refits``);
* :func:`_single_tree_stem`: a single candidate's stem, chosen over its first-round stem and
  every rung of the ladder by support (:func:`_stem_weight`) or by DBH error
  (:func:`_section_sd`, also the thin re-measure's rule).

Separate from :mod:`~stemmap.cloud.measure`, which runs the steps in order
(:func:`~stemmap.cloud.measure._stems_from_band`; together they passed 800 lines): these are
the fits and the choices between fits, each testable on its own with a stand-in per-stem
test or ladder, while the orchestration binds them to one band's slices, contexts and
configurations. :func:`~stemmap.cloud.measure._stems_from_band` calls them by
:mod:`~stemmap.cloud.measure`'s names (a tracer wrapping ``measure._single_tree_stem`` sees
every call); ``MIN_RANSAC_TOL`` and ``SINGLE_TREE_SHRINK`` are re-exported there. The
ladder's debug log (``ladder: kept ...``) is this module's logger,
``stemmap.cloud._ladder``."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from stemmap.cloud.config import StemConfig
from stemmap.cloud.slicefit import (
    _fit_segments,
    _opaque_core_refits,
    _segment_arcs,
    _segment_covariances,
)
from stemmap.cloud.slicestem import _SliceFits
from stemmap.types import FloatArray

__all__ = [
    "MIN_RANSAC_TOL",
    "SINGLE_TREE_SHRINK",
    "_MaybeStem",
    "_SegmentFits",
    "_Stem",
    "_fit_slices",
    "_ransac_tolerance",
    "_section_sd",
    "_single_tree_stem",
    "_stem_weight",
    "_stem_weight_of",
    "_tighter_refits",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _SegmentFits:
    """Step 6: the circle fit of every segment (cluster k, slice s: segment ``k * S + s``):
    centre (2,), radius, residual RMS, success, inliers, covariance (3, 3) over (cx, cy, r),
    arc coverage (degrees; 0 for a failed fit), and the segment's number of points."""

    centers: FloatArray
    radii: FloatArray
    rms: FloatArray
    ok: NDArray[np.bool_]
    n_in: NDArray[np.int64]
    cov: FloatArray
    arcs: FloatArray
    n_points: NDArray[np.int64]

    def plausible(self, cfg: StemConfig) -> NDArray[np.bool_]:
        """Step 7 without the residual test: enough inliers, radius in the DBH window, arc
        coverage of at least ``cfg.min_arc_deg``."""
        return np.asarray(
            self.ok
            & (self.n_in >= cfg.min_slice_points)
            & (self.radii >= cfg.min_diameter / 2)
            & (self.radii <= cfg.max_diameter / 2)
            & (self.arcs >= cfg.min_arc_deg),
            dtype=bool,
        )

    def per_cluster(
        self, passed: NDArray[np.bool_], kc: int, ns: int, cfg: StemConfig
    ) -> _SliceFits:
        """The fits as (cluster, slice) arrays for the per-stem tests."""
        return _SliceFits(
            passed=passed.reshape(kc, ns),
            fitted=(self.ok & (self.radii > 0)).reshape(kc, ns),
            centers=self.centers.reshape(kc, ns, 2),
            radii=self.radii.reshape(kc, ns),
            rms=self.rms.reshape(kc, ns),
            arcs=self.arcs.reshape(kc, ns),
            n_in=self.n_in.reshape(kc, ns),
            weights=(self.n_in / np.maximum(self.rms, 1e-4) ** 2).reshape(kc, ns),
            cov=self.cov.reshape(kc, ns, 3, 3),
            present=(self.n_points.reshape(kc, ns) >= cfg.min_slice_points).sum(axis=1),
        )


def _fit_slices(
    pts: FloatArray,
    seg: NDArray[np.int64],
    kseg: int,
    cfg: StemConfig,
    spacing: float,
    origins: FloatArray | None,
    ransac_tol: float | None = None,
) -> _SegmentFits:
    """Step 6: a robust circle fit (:func:`~stemmap.cloud.slicefit._fit_segments`: algebraic
    start, RANSAC (Fischler & Bolles 1981) where it explains the points badly, geometric fit
    with Huber loss and MAD trimming; along the rays when ``origins`` are given) of every
    segment with at least ``cfg.min_slice_points`` points, their covariances
    (:func:`~stemmap.cloud.slicefit._segment_covariances`) and arc coverage. The RANSAC
    tolerance is ``ransac_tol``, by default :func:`_ransac_tolerance` of the spacing."""
    seg_n = np.bincount(seg, minlength=kseg)
    fitmask = seg_n[seg] >= cfg.min_slice_points
    pts_f, seg_f = pts[fitmask], seg[fitmask]
    centers, radii, rms, ok, nin = _fit_segments(
        pts_f,
        seg_f,
        kseg,
        cfg.fit_method,
        ransac_tol=_ransac_tolerance(spacing) if ransac_tol is None else ransac_tol,
        radius_window=(cfg.min_diameter / 2, cfg.max_diameter / 2),
        ray_origins=None if origins is None else origins[fitmask],
        ransac_lo=cfg.ransac_lo,
        ransac_seed=cfg.ransac_seed,
        window=cfg.slice_fit_window,
        stub_trim=cfg.slice_stub_trim,
        stub_surface=cfg.slice_stub_surface,
    )
    if cfg.core_refits:
        (centers, radii, rms, ok, nin), n_core = _opaque_core_refits(
            pts_f,
            seg_f,
            (centers, radii, rms, ok, nin),
            cfg.fit_method,
            (cfg.min_diameter / 2, cfg.max_diameter / 2),
            cfg.min_slice_points,
            None if origins is None else origins[fitmask],
            ransac_lo=cfg.ransac_lo,
            ransac_seed=cfg.ransac_seed,
            window=cfg.slice_fit_window,
            stub_trim=cfg.slice_stub_trim,
            stub_surface=cfg.slice_stub_surface,
        )
        if n_core:
            log.debug("%d slice fit(s) refitted to the stem inside them", n_core)
    seg_cov = _segment_covariances(pts_f, seg_f, kseg, centers, radii, rms)
    arcs = np.zeros(kseg)
    if ok.any():
        good = ok[seg_f]
        arcs = _segment_arcs(pts_f[good], seg_f[good], kseg, np.where(ok[:, None], centers, 0))
    return _SegmentFits(centers, radii, rms, ok, nin, seg_cov, arcs, seg_n)


#: the smallest RANSAC inlier tolerance (m): bark roughness and range noise of a good TLS scan
MIN_RANSAC_TOL = 0.005


def _ransac_tolerance(spacing: float) -> float:
    """The first RANSAC inlier tolerance of a slice fit: half the point spacing, at least
    :data:`MIN_RANSAC_TOL`."""
    return max(0.5 * spacing, MIN_RANSAC_TOL)


def _tighter_refits(
    pts: FloatArray,
    seg: NDArray[np.int64],
    failed: NDArray[np.int64],
    shape: tuple[int, int],
    cfg: StemConfig,
    spacing: float,
    origins: FloatArray | None,
    rms_max: float,
    stem_of: Callable[[_SliceFits, int], tuple[tuple[float, ...], str] | None],
    first: float = 0.5,
    floor: float = MIN_RANSAC_TOL,
) -> dict[int, tuple[tuple[float, ...], str]]:
    """Stems of the clusters ``failed`` (rejected by the per-stem tests) from their slices
    refitted with ever tighter RANSAC tolerances: half the first one, halved again down to
    :data:`MIN_RANSAC_TOL`; a cluster is done at its first tolerance that gives a stem.

    The tolerance is a distance *across* the surface (range noise, bark roughness), the
    spacing one *along* it: a thinner cloud has a larger spacing but no noisier bark. On a
    tree whose band is mostly needles (treels spruce.laz: 90th-percentile spacing 45 mm as
    shipped, 66 / 100 / 153 mm at 50 / 20 / 10 %) half the spacing is an annulus 3-8 cm wide,
    and a circle through the branch whorls (r 0.3-0.7 m) holds more points in it than the
    12 cm stem: every slice fits a whorl, and no slice is left for the consistency tests or
    the guided refits. A slice passes step 7 as in the first round (``rms_max``, from the
    first round's noise floor). The first tolerance that gives a stem wins; ``stem_of``
    (fits, cluster) is the per-stem test (:func:`~stemmap.cloud.slicestem._slice_stem`),
    unchanged. Clusters that pass at the first tolerance never get here, so the stems found
    before are unchanged. The tolerance is not taken below ``floor``, the residual scale of
    the stems the cloud already gave (their median slice RMS): points scattered by more than
    that cannot be told from clutter with a tighter tolerance (the simulated mobile scan,
    3 cm range noise, stems' RMS ~2 cm: a 6 mm tolerance made a 6 cm stem of a shrub's
    clump). ``first``: the first tolerance as a fraction of the default one
    (:func:`_ransac_tolerance`; 1 when the slices themselves changed, see below).

    The caller runs it twice: with the band's slices, then -- for clusters still rejected, when
    the band's slices were thickened for a sparse cloud (:func:`~stemmap.cloud.band.
    _adapt_slices`) -- with the default 20 cm slices, since the needles' spacing that
    thickened them is not the stem's (treels spruce at 10 %: 0.4 m slices, the middle one
    1.2-1.6 m all whorl, leaving 2 of 3 slices on the stem).
    """
    kc, ns = shape
    out: dict[int, tuple[tuple[float, ...], str]] = {}
    todo = np.asarray(failed, dtype=np.int64)
    tol = first * _ransac_tolerance(spacing)
    while todo.size and tol >= max(floor, MIN_RANSAC_TOL) - 1e-12:
        sub = np.isin(seg // ns, todo)
        o_sub = None if origins is None else origins[sub]
        fits = _fit_slices(pts[sub], seg[sub], kc * ns, cfg, spacing, o_sub, tol)
        passed = fits.plausible(cfg) & (fits.rms <= np.maximum(rms_max, 0.02 * fits.radii))
        per = fits.per_cluster(passed, kc, ns, cfg)
        for c in todo:
            if per.passed[c].sum() >= min(2, cfg.min_slices):
                stem = stem_of(per, int(c))
                if stem is not None:
                    out[int(c)] = stem
        todo = np.array([c for c in todo if int(c) not in out], dtype=np.int64)
        tol /= 2
    return out


#: a stem row and the rule that gave its DBH
_Stem = tuple[tuple[float, ...], str]
_MaybeStem = TypeVar("_MaybeStem", bound="_Stem | None")

#: a single tree's refit replaces its stem only below this fraction of its diameter
SINGLE_TREE_SHRINK = 0.5


def _stem_weight(row: tuple[float, ...]) -> float:
    """A stem row's support: its inliers over its mean slice RMS squared (the slices' fit
    weights, :class:`~stemmap.cloud.slicestem._SliceFits`, pooled)."""
    return float(row[3]) / max(float(row[6]), 1e-4) ** 2


def _single_tree_stem(
    first_round: tuple[tuple[float, ...], str] | None,
    refit: Callable[[bool, float, float], tuple[tuple[float, ...], str] | None],
    tol0: float,
    thickened: bool,
    found_rms: float | None = None,
    error: Callable[[tuple[tuple[float, ...], str]], float] | None = None,
    agree_z: float = 2.0,
) -> tuple[tuple[float, ...], str] | None:
    """The stem of a cloud with a single candidate cluster: of its first-round stem
    (``first_round``, or None) and the stems its tighter refits give at every tolerance of
    the ladder (``refit(thin, first, tol)``: half of ``tol0``, halved down to
    :data:`MIN_RANSAC_TOL`, on the band's slices; and from ``tol0`` down on the default
    20 cm slices when the band's were ``thickened``), the first round's, unless a smaller
    one has more support (below).

    In a cloud of many stems the noise floor (the median slice RMS) comes from all of them
    and the residual test rejects circles through clutter; with one candidate it is that
    candidate's own median RMS, so the test passes whatever its slices fitted. On treels
    spruce.laz randomly thinned to 10 % (seed 3) the first round took three circles of
    r 31-72 cm through the branch whorls at RMS 61-97 mm as a 1.41 m stem, while the
    ladder's tighter tolerances fit its 12 cm bark at RMS 3-8 mm. The first tolerance that
    gives a stem (what :func:`_tighter_refits` stops at in a plot) is the loosest, the one
    clutter wins. Clutter makes circles larger and rougher, but a tighter tolerance also
    trims any fit to a lower RMS and carves a smaller, smoother arc out of rough bark (archi
    Tree_1, 54 cm, slice RMS 19 mm: 39-44 cm at 7 mm with twice the support). So the
    first-round stem (or without one, the first the ladder gives, as in a plot) is kept
    unless a smaller ladder stem has more support (:func:`_stem_weight`) and either is below
    :data:`SINGLE_TREE_SHRINK` (half) its diameter -- a circle of half the radius is not the
    same surface however rough its bark -- or was fitted at a tolerance not below the kept
    stem's RMS, where the support comparison is fair.

    ``found_rms`` (``StemConfig.ladder_found_rms``): the kept stem's RMS in that test, when the
    first-round stem was measured again on thin slices: the RMS of the slice fits it was
    found with. The re-measure's annulus fits about a known circle have an RMS that is no
    RANSAC residual (aRchi Tree_1 at 20 %, seed 0: 7.1 mm against 18.3 mm found), so a
    14.6 mm rung's 40.4 cm stem carved from its rough 54 cm bark passed as a fair
    comparison and won on support (docs/algorithms/cloud.md "aRchi Tree_1 at 20 %: where
    its DBH moves").

    ``error`` (``StemConfig.ladder_by = "error"``): a stem's DBH standard deviation with the
    section term (:func:`_section_sd`). A smaller ladder stem fitted below the kept stem's
    RMS may then also win on support when it is the better measurement of the same surface:
    its error smaller than the kept stem's, and the two DBHs within ``agree_z``
    (``StemConfig.ladder_agree_z``) standard deviations of their difference. treels spruce
    with 1 cm noise (seed 0) kept a line across a gap at 1.3 m (25.25 cm, ring + 1.88, sd
    2.6 cm) against a 6 mm rung that holds a slice there (23.67, sd 0.5). The error alone
    does not refuse a carved circle: its slices are a consistent inner surface, not scatter
    (Tree_1 at 20 %, seed 0: 40.4 cm at sd 1.2 cm against 53.6 at 1.5), but it is 13 cm from
    the kept stem, 7 sd of the difference (docs/algorithms/cloud.md "The single-tree ladder
    by its error")."""
    cands: list[tuple[tuple[float, ...], str]] = []
    tols: list[float] = []
    ladders = [(False, 0.5)] + ([(True, 1.0)] if thickened else [])
    for thin, f in ladders:
        while f * tol0 >= MIN_RANSAC_TOL - 1e-12:
            got = refit(thin, f, f * tol0)
            if got is not None:
                cands.append(got)
                tols.append(f * tol0)
            f /= 2
    incumbent = first_round if first_round is not None else (cands[0] if cands else None)
    if incumbent is None:
        return None
    d0, rms0 = incumbent[0][2], incumbent[0][6]
    if found_rms is not None and incumbent is first_round:
        rms0 = found_rms
    if error is not None:
        e0 = error(incumbent)
        log.debug("ladder: kept D %.4f rms %.4f sd %.4f", d0, rms0, e0)

    def fair(c: tuple[tuple[float, ...], str], t: float) -> bool:
        if t >= rms0 or error is None:
            return t >= rms0
        e = error(c)
        log.debug("ladder: rung %.4f D %.4f w %.0f sd %.4f", t, c[0][2], _stem_weight(c[0]), e)
        return e < e0 and abs(c[0][2] - d0) <= agree_z * math.hypot(e, e0)

    other = [
        c
        for c, t in zip(cands, tols, strict=True)
        if c[0][2] < SINGLE_TREE_SHRINK * d0 or (c[0][2] < d0 and fair(c, t))
    ]
    best = max(other, key=_stem_weight_of, default=None)
    if best is not None and _stem_weight(best[0]) > _stem_weight(incumbent[0]):
        return best
    return incumbent


def _section_sd(
    measure: Callable[[StemConfig], tuple[tuple[float, ...], str] | None], cfg: StemConfig
) -> float:
    """The DBH standard deviation of the stem ``measure(cfg)`` gives, with the section term
    at its model weight (``dbh_sd_scatter`` = 1: fit noise plus the kept slices' scatter
    about the stem's local profile, :func:`~stemmap.cloud.dbhsd.dbh_variance`), whatever the
    configured weight; inf when it gives no stem. What ``thin_remeasure_by = "error"``
    compares: the DBH is the same at every weight, only its stated error changes."""
    got = measure(replace(cfg, dbh_sd_scatter=1.0))
    return math.inf if got is None else float(got[0][9])


def _stem_weight_of(stem: tuple[tuple[float, ...], str]) -> float:
    return _stem_weight(stem[0])
