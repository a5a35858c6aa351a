"""Detector configuration: :class:`DetectorConfig` and what each of its fields means. The
checks of the field values and the building of a preset's values are
:mod:`stemmap.scan._config_checks`; the published presets (:data:`PRESETS`), what each takes
from its paper (:data:`PRESET_NOTES`) and :data:`ARC_OPTIONS` are :mod:`stemmap.scan._presets`,
re-exported here.

Split from :mod:`stemmap.scan.detect` (which re-exports every name here): the parameters and
their provenance are one concept, the pipeline that reads them another.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

from stemmap.errors import ConfigError as ConfigError  # re-exported (tests import it here)
from stemmap.scan._config_checks import check_fields, preset_values
from stemmap.scan._presets import ARC_OPTIONS, PRESET_NOTES, PRESETS

__all__ = ["ARC_OPTIONS", "EDGE_WINDOW_MIN", "PRESETS", "PRESET_NOTES", "DetectorConfig"]

#: The least share of the footprint in an edge return's range window with ``edge_hit_window``
#: (``DetectorConfig.edge_window_share``): 1/25, one sub-ray of the simulator's and the
#: real-geometry benchmark's footprints; a thinner sliver's mean range differs from it by less
#: than a millimetre at a trunk edge (0.25-degree footprint).
EDGE_WINDOW_MIN = 0.04


@dataclass(frozen=True)
class DetectorConfig:
    """Parameters of :class:`ScanTrunkDetector` (SI units; angles in degrees where named ``_deg``).

    Parameters
    ----------
    name : str
        Preset name (recorded in the output ``source``).
    range_min, range_max : float or None, metres
        Range gate; ``None`` uses the scan's own ``range_min`` / ``range_max``.
    fov_deg : (float, float) or None
        Field-of-view window ``(lo, hi)``, degrees counter-clockwise from the sensor x axis.
    tilt : {"none", "eq1", "rotation"}
        Tilt compensation when roll/pitch are passed: Zheng eq. 1 or the exact rotation.
    median_filter : bool
        Three-neighbour median filter (Xue 2018 §2.2).
    segmentation : {"range_jump", "euclidean"}
        Zheng eq. 2 or the Euclidean adjacent-point distance.
    max_jump : float, metres
        Range jump (Zheng: 0.2 m) or Euclidean distance threshold.
    range_factor : float, >= 0
        Euclidean only: add ``range_factor * r * dtheta`` per beam to the threshold (ours).
    max_skip : int
        Missing beams bridged inside a segment.
    occlusion_margin : float, metres
        A neighbouring return this much nearer marks a segment end as occluded.
    point_curvature_min : float or None, metres
        Drop returns whose single-point curvature (Zheng eq. 3) is below this (outward spikes).
    radius_median : float or None, metres
        Radius median filter (visual-lidar §2.3: 0.5 m).
    split_merged : bool
        Returns removed by the radius median filter form new segments instead of being
        discarded (ours), so the second of two merged trunks is still detected.
    min_points, max_points : int
        Returns per segment (visual-lidar: >= 40 at 0.12 deg).
    min_points_partial : int
        Returns needed by a segment with an occluded or truncated end (ours): a few returns
        cut off by an occluder are as often a clump of bush stems as a trunk. The effective
        minimum is the larger of the two.
    mixed_end_min_points : int
        Footprint-averaging scanners (``beam_divergence_deg`` > 0, ``beam_footprint_deg`` 0)
        only: a candidate with fewer than ``min_points`` returns but at least this many (>= 3)
        is kept when the beam beyond one of its ends is a mixed return lying behind it
        (:func:`~stemmap.scan._mixed_end.mixed_ends`: more than ``occlusion_margin``
        farther than the end return, and the beam after it returned nothing or lies farther
        still): that beam's footprint held the rest of the trunk's outline, blended with
        what lies behind, and segmentation cut it off (ours, issue 11, Dec 6: FORTLS's
        noise-free averaging trunks left with 3 clean returns). 0 = off. Numpy path.
    residual_floor : float, in [0, 1)
        "ours" fits without a first-echo footprint correction: a candidate whose own residual
        scale bounds its noise below the ``sigma`` the fit weighted by (the upper confidence
        bound at this level over its ``n - 3`` degrees of freedom) is fitted again weighted by
        that bound, at least the scan's measured noise; the tests keep ``sigma``
        (:func:`~stemmap.scan._segment_fits.residual_floor_refit`; ours, issue 11, Dec 6: the
        1 cm floor on noise-free scans). 0 = off. Numpy path.
    outline_floor_points : int
        Fits without a first-echo footprint correction (``beam_footprint_deg`` 0; a first-echo
        fit reads its floor from the data with ``fit_noise_floor``): the range-noise floor
        ``sigma`` read from the data instead of assumed (issue 11: "estimate
        the range noise and bark roughness from the data instead of assuming 1 cm";
        docs/algorithms/scan-detection.md, "The outline floor read from the batch"): the
        residuals of the interior returns of every candidate of the batch that passed its fit
        tests with at least this many returns (>= 6), pooled, give a robust residual scale
        (biweight); less the measured range noise in quadrature it is the outline term (bark,
        ellipse), and every scan's floor becomes ``min(sigma, max(outline_floor_min,
        sqrt(noise^2 + outline^2)))`` (:mod:`stemmap.scan._outline_floor`). A few-return
        candidate cannot show its own outline; the batch's well-sampled trunks can: on
        noise-free perfect circles the floor falls to ``outline_floor_min``, on real bark it
        stays near the bark's. ``sigma`` where the batch has too few residuals. 0 = off. Numpy
        path (a first pass at ``sigma`` reads the floor, then the whole pipeline runs with it).
    outline_floor_min : float, metres, > 0
        The lowest floor ``outline_floor_points`` sets (the trace's 3 mm: "The two FORTLS rows
        left against textbook Kasa", part 3).
    min_width, max_width : float, metres
        Edge-beam chord width (Xue eq. 12); visual-lidar: <= 0.55 m.
    min_depth : float, metres
        Sagitta towards the sensor (Zheng §3.2 criterion 4).
    min_curvature, max_curvature : float, 1/m
        Cluster curvature bounds (Zheng §3.2 criterion 1).
    reject_straight : bool
        Reject segments whose line residual is pure noise (walls, fences; ours).
    straight_ratio : float
        See :func:`stemmap.scan.features.is_straight`.
    straight_test : {"chi2", "ratio"}
        Chi-square test of a line against ``sigma`` or the residual/width ratio.
    straight_min_points : int
        Apply the straightness test only to segments with at least this many returns: 4-7
        returns of a small or far trunk are as consistent with a line as with an arc.
    straight_depth_sigmas : float, > 0
        A segment whose sagitta (towards the sensor) exceeds this many range-noise sigmas is
        never straight (ours, issue 11): a near trunk's arc of 10-20 returns can have a line
        RMS within the chi-square bound (TreeLS plot: 13-16 cm stems at 1.1-1.5 m) while
        bulging 4 sigma towards the sensor, which a wall does not. ``inf`` = off.
    straight_curvature : bool
        A segment whose bend towards the sensor is significant is never straight (ours,
        issue 11, Dec 5): the drop of the residual sum of squares when a parabola replaces
        the best line (:func:`~stemmap.scan.features.line_bulge_gain`, one degree of
        freedom) exceeds ``z_0.99^2 sigma^2`` (one-sided: a 1 % rate). The chi-square test
        spreads the bend of a small trunk under range noise over the line's ``n - 2``
        degrees of freedom, the sagitta exemption (``straight_depth_sigmas``) reads it from
        one return; this reads it from every return in one degree (at 3 cm of noise the
        real slices' 13-25 cm trunks at 1.5-9 m with 8-20 returns passed as straight). A
        wall with independent errors is exempted at the test's 1 % rate (and still meets
        the circle fit's radius tests); a bend away from the sensor (a hollow, an inside
        corner) never exempts. Numpy path only. False = off (every preset).
    occluded_blend_sigmas : float, > 0
        An averaging scanner's (``beam_divergence_deg`` > 0, no ``beam_footprint_deg``)
        segment loses the end return of an occluded end when it lies nearer than the next
        return inward by more than this many range-noise sigmas: the beam straddling the
        occluder's silhouette returns a blend of the two ranges, in front of the trunk
        (ours, issue 11, Dec 5; :mod:`stemmap.scan._occluded_blend`). Numpy path only.
        ``inf`` = off (every preset).
    drop_partial : bool
        Drop segments with an occluded or truncated end.
    fit_method : str
        Circle fit registered in :data:`stemmap.scan.circle.FIT_METHODS`.
    sigma : float, metres
        Range noise of the sensor (fit weighting, covariance floor, straightness test).
    sigma_rel : float, >= 0
        Range-proportional part of the noise (triangulation scanners such as RPLIDAR are
        specified in % of range): each segment uses ``sigma + sigma_rel * mean range``.
    min_radius, max_radius : float, metres
        Plausible fitted trunk radius.
    max_radius_width_ratio : float
        Reject fits whose radius exceeds this multiple of the chord width (a near-flat arc).
    max_rms_sigma : float
        Reject fits whose RMS orthogonal residual exceeds this multiple of ``sigma``: the
        outline is not a circle (rocks, polygons, bushes; ours).
    beam_footprint_deg : float, degrees
        Footprint of a nearest-return (first-echo) sensor; returns are moved to the footprint
        side nearest the trunk apex before fitting (:func:`~stemmap.scan.features.
        footprint_correct`). 0 for averaging sensors and the simulator.
    beam_divergence_deg : float, degrees
        Full footprint width of an averaging sensor (one that reports the mean range of what
        its footprint hits, i.e. mixed pixels at edges; SICK LMS2xx class: ~0.25 deg). The
        ``ours`` fit models the edge returns as footprint averages, and (with
        ``neighbour_silhouette``) the beams beyond each segment end narrow or pin the tangent
        (:func:`~stemmap.scan.features.edge_silhouette`). 0 = thin beams. Ignored when
        ``beam_footprint_deg`` > 0 (a first-echo sensor does not average its footprint).
    neighbour_silhouette : bool
        Derive the ``ours`` silhouette prior of each end from the neighbouring beams (needs
        ``beam_divergence_deg`` > 0).
    edge_hit_min, edge_hit_max : float in [0, 1]
        The averaging sensor's return threshold (share of the footprint that must hit for a
        beam to return) assumed to lie in ``[edge_hit_min, edge_hit_max]`` (ours, Dec 4).
        Where the beam next to a segment end returned nothing (the threshold decided where
        the returns stop; :func:`~stemmap.scan.features.edge_silhouette`) the tangent then
        lies uniformly in ``(edge + (lo - 1/2) w, edge + step + (hi - 1/2) w]`` (``w`` the
        footprint, :func:`~stemmap.scan.features.edge_default_prior`). Off by default: every
        other setting breaks the simulated DBH target (docs/algorithms/scan-detection.md,
        "Averaging scanners: the return threshold"). 0.5 / 0.5 (default): a beam
        returns when half its footprint hits, the tangent uniformly between the edge beam and
        the next. A scanner that returns when any part of its footprint hits is 0 / 0; an
        unknown threshold ``0 / 0.5`` (the prior widened by half a footprint). Needs
        ``fit_method="ours"``, ``neighbour_silhouette`` and ``beam_divergence_deg`` > 0.
    edge_hit_window : bool
        The range model of the two edge returns follows the assumed threshold too (ours,
        Dec 5): a footprint the circle covers by less than half is averaged over the part it
        covers (at least ``edge_hit_min``, and :data:`EDGE_WINDOW_MIN`), not over half a
        footprint whose rest lies past the tangent, which reads a thin sliver's nearer range
        as a wider circle. Off by default; a no-op at ``edge_hit_min`` 0.5
        (docs/algorithms/scan-detection.md, "The averaging edge bias against textbook Kasa").
    fit_residuals : {"range", "orthogonal"}
        Noise model of the ``ours`` fit: range noise along each beam (default) or orthogonal
        distances (the fit before the edge model).
    sigma_from_data : bool
        Estimate each segment's noise + bark roughness from its returns
        (:func:`~stemmap.scan.plausibility.range_roughness`) and use ``max(sigma, estimate)``
        for the fit's robust scale, the RMS test and the covariance (ours, issue 11): real bark
        is rougher than a sensor's range noise.
    roughness_max_factor : float, >= 1
        With ``sigma_from_data``: the estimate is capped at this multiple of the configured
        sigma (a bush or a clump of branches is rougher still and must keep failing the RMS
        test).
    sigma_from_scan : bool
        Estimate the sensor's range noise of every scan from all its returns
        (:func:`~stemmap.scan.plausibility.scan_noise`: robust scale of the second differences
        of adjacent ranges on continuous surfaces) and use ``max(sigma, estimate)`` wherever
        the detector reads the range noise (straightness, corner and gap thresholds, the fit's
        scale, the RMS test; ours, issue 11). Unlike ``sigma_from_data`` one rough trunk does
        not raise it: walls, ground, bushes and every trunk of the scan vote together. On in the
        ``stemmap`` preset (chosen leave-one-dataset-out on the real slices;
        scan-detection-history.md, eighth round), off in the paper presets and in a bare
        ``DetectorConfig()``.
    scan_noise_jump : float, metres, > 0
        With ``sigma_from_scan``: largest range step between adjacent beams that counts as one
        continuous surface.
    scan_noise_pool : bool
        With ``sigma_from_scan``: the scans of a batch with too few continuous beam triples
        for a noise estimate of their own share one, from the union of their triples under
        the same rules (:func:`~stemmap.scan.plausibility.scan_noise` ``pool``; ours, issue
        11, sixteenth round). Scans with their own estimate keep it. Off in every preset (the
        leave-one-dataset-out chooses it for 1 of 5 held-out datasets;
        scan-detection-history.md, sixteenth round). A scan's result then depends on the
        other scans of its batch when it lacks an estimate.
    scan_noise_batch : float, 0 or >= 1
        With ``sigma_from_scan``: a scan still without its own noise estimate (too few
        continuous beam triples, or one surface holding most of them) takes the estimate over
        the triples of every scan of the batch together where that is at least
        ``scan_noise_batch x sigma`` (:func:`~stemmap.scan.plausibility.scan_noise`
        ``batch_min``; ours, issue 11, Dec 4, "Range noise on sparse scans"): a breast-height
        scan of a few trunks at 0.5-1 deg holds 0-15 interior triples, a batch of them
        together hundreds. The floor keeps a single rough trunk seen from many sides (its
        bark) from passing as noise: the batch speaks only for a scanner clearly noisier than
        configured. ``stemmap detect`` runs batches of 2000 scans: the estimate is then that
        of the stretch of the stream around the scan. A scan's result depends on the other
        scans of its batch when it lacks an estimate. 0 = off (every preset): at 2.5 no
        no-noise or 1 cm configuration of the real-geometry benchmark changes and the 3 cm
        ones gain recall, but the leave-one-dataset-out prefers it to the default for one
        held-out dataset of five; on simulated 3 cm drives it scores as the true ``sigma``
        does (scan-detection.md, "Range noise on sparse scans").
    batch_noise_scale : "mad" or "biweight"
        The scale statistic of the range-noise estimate over every scan's interior triples
        (the batch's estimate that ``fit_noise_floor``, ``step_noise_pool="batch"`` and
        ``scan_noise_batch`` give a scan without an estimate of its own;
        :func:`~stemmap.scan.plausibility.scan_noise` ``batch_scale``): 1.4826 MAD, or the
        biweight midvariance (:func:`~stemmap.scan.plausibility.biweight_scale`; ours, issue
        11, Dec 5, "The batch's noise from few triples"), as robust and with about three
        quarters of the MAD's sampling spread: a single-tree batch at 1 deg holds 12-21
        triples, where the MAD read 1.44 cm for 3 cm of noise (TreeLS pine; the biweight 2.38).
        The scans' own estimates keep the MAD. "mad" in every preset: with the run test of
        ``stub_runs_snoop`` it is the leave-one-dataset-out choice for three of five held-out
        datasets (grid 74) and fixes that row, but grid 74 keeps the run test's no-noise
        rows that bar it as a default; alone it changes no real row materially.
    scan_noise_surface : float, metres, >= 0
        With ``sigma_from_scan``: the surfaces' own share of the estimate (their shape and
        roughness, which a noise-free scan measures), taken out in quadrature. Default 6 mm:
        the largest median estimate on noise-free virtual scans of the real plots at
        0.25-0.5 deg (0.57 cm, TreeLS plot, averaging 0.25 deg; benchmarks/scan_noise.py;
        scan-detection-history.md, seventh round).
    rms_robust : bool
        The RMS test reads ``1.4826 x median |residual|`` instead of the RMS
        (:func:`~stemmap.scan.plausibility.robust_residual_scale`): a few returns off the
        circle (branch stub, mixed pixel, bark ridge) do not reject a trunk (ours, issue 11).
    rms_dof : bool
        The RMS test reads the residual scale over the fit's ``n - 3`` degrees of freedom,
        ``sqrt(sum residual^2 / (n - 3))`` (``sqrt(n / (n - 3))`` x the RMS over the n returns),
        instead of the RMS (ours, issue 11, Dec 5): the circle's three parameters absorb three
        dimensions of the residuals, so the plain RMS of a 4-return fit reads half the noise
        that made it (``E[sum residual^2] = (n - 3) sigma^2``) and ``max_rms_sigma`` 2 lets its
        residual scale reach 4 sigma (5 returns 3.2, 8: 2.5, 30: 2.1). False: the plain RMS.
    bark_roughness : float, >= 0
        RMS of a real trunk's outline about its best circle as a fraction of the radius (bark
        ridges, elliptic and irregular stems). The RMS test bound becomes ``max_rms_sigma x
        sqrt(sigma^2 + (bark_roughness x radius)^2)``: the outline of a large rough trunk is
        not rejected for being rougher than the sensor (ours, issue 11). 0 = the sensor's
        noise only.
    lobe_roughness : float, >= 0
        A candidate that fails the RMS test passes it after all when its outline is a smooth
        lobed one (ours, issue 11, twelfth round): RMS <= ``max_rms_sigma x sqrt(sigma^2 +
        (lobe_roughness x radius)^2)`` *and* the residuals' high-frequency scale
        (:func:`~stemmap.scan.plausibility.residual_smoothness`: robust scale of their second
        differences along the arc) <= ``lobe_smooth_sigmas x sigma``. A lobed or elliptic
        trunk deviates from its circle slowly along the arc, a bush or a clump of twigs from
        one return to the next. 0 = off (the RMS test alone).
    lobe_smooth_sigmas : float, > 0
        With ``lobe_roughness``: the largest high-frequency residual scale, in range-noise
        sigmas.
    rms_noise_from_fit : float, 0 or >= 1
        On a scan without its own noise estimate (``sigma_from_scan`` found too few continuous
        surfaces: one tree, a sparse stand), a candidate that fails the RMS test passes it
        after all when its residuals are white noise of its own scale (ours, issue 11, twelfth
        round): ``s`` = the fit residuals' high-frequency scale
        (:func:`~stemmap.scan.plausibility.residual_smoothness`, free of the outline's
        curvature and lobes, unlike ``sigma_from_data``'s range roughness) in ``(sigma,
        rms_noise_from_fit x sigma]``, RMS <= ``rms_own_sigmas x sqrt(s^2 + (bark_roughness
        x radius)^2)`` and a silhouette no wider than ``2 radius + 2 max_rms_sigma x s``
        (:func:`~stemmap.scan.plausibility.own_noise`). The fit, the straightness test and
        the covariance keep ``sigma``. 0 = off.
    rms_own_sigmas : float, > 0
        With ``rms_noise_from_fit``: the largest RMS in units of the candidate's own noise.
    lobe_harmonics : int, 0 or >= 2
        A candidate that fails the RMS test is fitted again with a lobed outline (ours, issue
        11, fifteenth round; :mod:`stemmap.scan._lobed`): the radius around the centre as
        ``r0 + sum_{k=2..lobe_harmonics} a_k cos k theta + b_k sin k theta`` (a polar Fourier
        descriptor, Zahn & Roskies 1972; the stem cross-section's radius function of Matérn
        1956), fitted jointly with the centre with a Gaussian prior of std ``lobe_prior x
        radius`` on each coefficient. It passes when the RMS about the lobed outline passes
        the RMS test, its lobe amplitude (RMS of the lobe profile / r0) is <= ``lobe_max``
        and its silhouette is no wider than the outline's; it is then reported with the
        lobed fit's centre and area-equivalent radius. Candidates of fewer than
        :data:`~stemmap.scan._lobed.LOBED_MIN_POINTS` returns are not re-fitted. 0 = off.
    lobe_prior : float, > 0
        With ``lobe_harmonics``: the prior std of each harmonic coefficient as a fraction of
        the radius (measured on the real rings of the shared datasets,
        ``benchmarks/lobed_outlines.py``).
    lobe_max : float, > 0
        With ``lobe_harmonics``: the largest lobe amplitude (RMS of the fitted lobe profile /
        r0) of a trunk.
    split_corners : bool
        Cut a segment that is not a convex arc (sagitta below ``max(min_depth, 0)``) at every
        concave corner deeper than ``corner_depth``, a convex one at corners deeper than
        ``corner_depth_convex`` (ours, issue 11): the visible outline of
        touching convex objects (a trunk and a branch, bush or second stem) is convex
        everywhere except at the junctions, so a trunk merged with a branch in one segment is
        cut there (:func:`~stemmap.scan.segment.concave_corners`). The dents of rough bark on a
        trunk's own (convex) arc are not junctions: hence the separate convex threshold.
    corner_depth : float, metres, > 0
        How far behind the chord of its ``corner_span``-th neighbours a return must lie to be
        a concave corner (larger than the bark roughness and range noise).
    corner_span : int, >= 1
        Neighbour offset (returns) of the chord of the corner test.
    corner_depth_convex : float, metres, > 0
        The corner depth in a segment that *is* a convex arc (a trunk with a thin stem or a
        branch merged at its silhouette still bulges towards the sensor); ``inf`` = never cut
        a convex segment.
    corner_sigmas : float, >= 0
        A corner is also at least this many range-noise sigmas (``sigma + sigma_rel x mean
        range``) deep: the concave depth of a return from its neighbours' chord has a noise
        std of ~1.2 sigma (span >= 2), so 5 sigma makes a false cut on a smooth arc rare
        (~1e-4 per return) whatever the sensor.
    gap_splits : int, >= 0
        Passes of cutting every segment that is not a convex arc (sagitta below
        ``max(min_depth, 0)``) at its largest gap between consecutive returns (ours, issue 11;
        :func:`~stemmap.scan.segment.split_largest_gap`): a trunk and a stem, bush or branch
        beside it that the range-adaptive segmentation merged. The pieces go through the
        segment filters like any segment; a cut end is occluded only when the return across
        it is nearer by more than ``occlusion_margin``. 0 = off.
    gap_ratio : float, >= 0
        A segment is cut at its largest gap (``gap_splits``, and ``refit_pieces`` with
        ``refit_split="gap"``) only if that gap exceeds this multiple of the segment's median
        gap: a junction of two objects is a gap, the returns along one surface are evenly
        spaced.
    gap_sigmas : float, >= 0
        ... and by more than this many range-noise sigmas (``sigma + sigma_rel x mean range``,
        per segment) above the median gap: noise alone makes no cut.
    refit_pieces : bool
        Cut a candidate that fails only the RMS test into pieces (``refit_split``) and fit
        every piece with ``min_points`` returns that passes the segment filters once more
        (ours, issue 11; :func:`~stemmap.scan._refit.refit_pieces`): a trunk with a stem,
        branch fillet or bush beside it in one segment is rejected as a whole although most of
        its returns lie on a circle. With ``refit_split="corners"`` the compiled path runs it
        too (:mod:`stemmap.scan._fast_candidates`, the same results); the other splits run
        on the numpy path only.
    refit_sigmas : float, > 0
        Outlier threshold of ``refit_pieces`` in robust residual scales (1.4826 MAD).
    refit_split : {"gap", "outliers", "outlier_ends", "corners"}
        How ``refit_pieces`` cuts a failed candidate: at its largest gap between consecutive
        returns (two objects side by side, :func:`~stemmap.scan.segment.split_largest_gap`),
        at its outlier returns, or at the runs of outliers at either end only (a branch
        fillet or stub at the silhouette, never the dents inside a rough arc); ``"corners"``:
        at its concave corners (the ``split_corners`` rule and thresholds), a candidate
        rejected as not convex (``depth``) as well as one that failed the RMS test
        (:func:`~stemmap.scan._refit.split_refit`).
    refit_validate : bool
        With ``refit_pieces``: the pieces of a candidate are accepted only together, when
        exactly one piece passes every test and no other piece that passed the segment
        filters (a circle-like piece) fails its fit (:func:`~stemmap.scan._refit.
        validate_pieces`); with ``refit_split="corners"`` also only when no return of the
        candidate lies more than 3 sigma inside the piece's circle. Otherwise the candidate
        keeps its verdict. Off: each passing piece counts on its own.
    arc_refit : bool
        Fit the largest consistent arc of a candidate rejected as not convex (``depth``) as a
        candidate of its own (ours, issue 11; :func:`~stemmap.scan._arcs.consensus_arcs`): a
        circle grown from a short convex seed window, adding neighbouring returns while each
        lies within ``arc_sigmas`` robust residual scales (at least ``arc_floor_sigmas`` noise
        sigmas) of the circle so far; only an arc that reaches one end of the segment, with
        ``min_points_partial`` returns and a quarter of the segment's, tested without the
        bark allowance -- a trunk whose
        segment runs on into a branch, fillet or stem. Compiled
        (:mod:`stemmap.scan._fast_arcs`) since the fourteenth round; on in the ``stemmap``
        preset since the fifteenth (with ``arc_tangent_sigmas`` 3 and ``arc_chi2``), off in
        the paper presets.
    arc_sigmas : float, > 0
        Consensus threshold of ``arc_refit`` in robust residual scales (1.4826 MAD).
    arc_floor_sigmas : float, > 0
        ... but never below this many range-noise sigmas (``sigma + sigma_rel x range``).
    arc_replace : float, > 1
        With ``arc_refit``, an *accepted* candidate is replaced by its largest consistent arc
        when the arc passes every test and the candidate's fit RMS exceeds this multiple of
        the arc's fit RMS and the range noise (a fillet or stub at one end pulled the fit; on
        lidR, accepted trunks with one branch return at an end were 5-10 cm too wide), and
        (since the review of the fifteenth round) the candidate's residuals fail the upper
        1 % chi-square test at the range noise, ``n x RMS^2 > chi2_0.99(n - 3) x sigma^2``:
        a fit whose residuals are the noise keeps its returns. Since Dec 5 (benchmark seed
        6) a candidate also keeps them when its outline goes on past the arc's cut on its own
        circle: a return across the cut lies more than 3 sigma (with the bark allowance) in
        front of the arc circle's tangent range and the candidate's circle explains both the
        arc's returns and the dropped ones within the upper 1 % chi-square points
        (:func:`stemmap.scan._fast_arcs.continues_outline`). inf = off.
    arc_short_steps : bool
        With ``arc_refit``: an arc of ``min_points`` to ``min_points_partial - 1`` returns
        counts too when a range step larger than ``max_jump`` separates it from the rest of
        its segment at every cut end (ours, issue 11, fifth round: a 4-return stem merged with
        a stem or branch at another range by the range-adaptive threshold; the short runs at
        the end of a wall or bush continue at the same range). The piece is then tested as any
        candidate (partial where the return across a cut is nearer by more than
        ``occlusion_margin``). False: every arc needs ``min_points_partial`` returns. On in
        the ``stemmap`` preset since the sixteenth round.
    arc_tangent_sigmas : float, > 0
        With ``arc_refit``: an arc passes only when none of its returns lies farther than its
        circle's tangent range ``sqrt(d^2 - r^2)`` (centre at range d) by more than this many
        ``sqrt(sigma^2 + (bark_roughness x r)^2)`` (ours, issue 11, fifteenth round): a first
        return of a convex trunk comes from its visible half, never from behind its tangent
        points; an arc whose circle passes through a return farther away is a face of a
        longer outline (the simulator's lobed rocks at 19 m: a return 10-12 cm behind).
        inf = off.
    arc_chi2 : bool
        With ``arc_refit``: an arc passes only when its residuals are the range noise, the
        upper 1 % chi-square test ``n x RMS^2 / sigma^2 <= chi2_0.99(n - 3)`` over its n
        returns (ours, issue 11, fifteenth round): the arc holds the returns that lie on one
        circle within the noise, so its RMS test (``max_rms_sigma``, no bark allowance)
        counts the fit's degrees of freedom. False: the RMS test only.
    behind_sigmas : float, >= 0
        Drop a fitted candidate's end returns that lie farther than the tangent range
        ``sqrt(d^2 - r^2)`` of the circle fitted without them (nothing on a trunk is farther
        from the sensor than its tangent points) by more than this many noise scales
        ``sqrt(sigma^2 + (bark_roughness r)^2)``, end by end, down to ``max(min_points,
        min_points_partial)`` returns, and fit the rest again (ours, issue 11, thirteenth
        round; :func:`~stemmap.scan._behind.trim_behind`): a branch or stub behind the
        stem's silhouette joined to the trunk's segment. Numpy path only. inf = off.
    stub_sigmas : float, >= 0
        Drop an accepted candidate's end returns that lie *outside* the circle fitted without
        them (that end taken as occluded) by more than this many standard deviations of the
        deletion residual (noise scale ``sqrt(sigma^2 + (bark_roughness r)^2)`` and the
        circle's own uncertainty at the end), when that circle passes every fit test and the
        upper 1 % chi-square test; end by end, down to ``max(min_points,
        min_points_partial)`` returns; the rest is fitted again (ours, issue 11, seventeenth
        round; :func:`~stemmap.scan._stubs.outward_ends`): a branch stub on the stem's flank
        joined to its arc. First-echo or thin-beam fits only (``beam_footprint_deg`` > 0 or
        ``beam_divergence_deg`` 0: an averaging sensor's edge return is a mixed pixel,
        outside the circle by construction). Numpy path. inf = off.
    edge_protrusion : float, metres, >= 0
        First-echo fits (``beam_footprint_deg`` > 0, ``fit_method`` "ours") only: the height
        of the bark flakes, twigs, needles and stubs that stand out of a real stem's mean
        circle (ours, issue 11, Dec 4; :func:`~stemmap.scan.features.first_echo_edge_prior`).
        A first-echo beam returns from whatever is nearest in its footprint, so at the
        silhouette the last beam that returns may be one that caught only a protrusion: the
        mean circle's tangent then lies up to ``edge_protrusion / range`` radians inside the
        edge beam's footprint, and each end's tangent prior is widened inward by that much.
        0 = the outline is the circle (the tangent anywhere in the edge footprint).
    stub_runs : bool
        With a finite ``stub_sigmas``, first-echo fits: the deletion unit of the stub test is
        a run of end returns, not one return (ours, issue 11, Dec 5, "lidR view by view";
        :func:`~stemmap.scan._stub_runs.trim_runs`): at each end the smallest run of m
        returns whose rest (more than half of the returns) passes every test and the
        chi-square test, and all of which lie outside the rest's circle by more than
        ``stub_sigmas`` deletion deviations, goes; the
        new end is occluded where the run lay in front of the stem. A branch leaving the
        flank over several beams. Numpy path. False = one return at a time.
    stub_runs_snoop : bool
        With ``stub_runs``: the run test as data snooping (Baarda 1968; ours, issue 11, Dec
        5, "Runs by data snooping"; :func:`~stemmap.scan._stub_runs.misfit`): it reads the
        range noise measured on the data (``fit_noise_floor``'s scale, not capped by the
        tests' sigma) and looks for a run only in a candidate whose own circle fails the
        upper 1 % chi-square test against that noise (the global test before the local
        ones); a trimmed end is also occluded where the return beyond it lies nearer than
        the rest circle's tangent range though its beam misses the circle. On a scan with
        centimetres of noise and no estimate of its own the tests' 1 cm sigma made noisy
        end returns look like runs. False = every accepted candidate is searched against
        the fit's noise. Numpy path.
    stub_runs_worst : bool
        With ``stub_runs``: data snooping one observation at a time first (Baarda 1968;
        ours, issue 11, Dec 5, "The run test on clean needles";
        :func:`~stemmap.scan._stub_runs.worst_return`): of a candidate whose circle fails
        the run test's global chi-square test, the return with the largest standardised
        residual (w-statistic ``|e| / (s sqrt(q))``, ``q`` its redundancy number) is found;
        where it is not an end return and the candidate without it passes the same test,
        the misfit lies there and a run may go only at the end on its side of the arc's
        middle. Needles in front of a clean stem inside the arc failed the test, and the
        stem's own returns at the other end went as a run (TreeLS pine 0.25 deg nearest, no
        noise: 1.49 -> 3.04 cm with grid 69 / 79, 1.93 with the option; lidR's gains kept).
        False = both ends of every candidate that fails the global test. Numpy path.
    max_dbh_sd : float, metres, > 0
        First-echo fits (``beam_footprint_deg`` > 0, ``fit_method`` "ours"), numpy path: a
        candidate whose circle fit's own diameter standard deviation ``2 sqrt(C_rr)`` (the
        inverse Gauss-Newton Hessian of the fit at the tests' noise, with the silhouette
        tangents; :mod:`stemmap.scan._circle_ours`) exceeds this is rejected with the reason
        ``"precision"`` (ours, issue 11, Dec 5, "Noisy first-echo rows"). At centimetres of
        range noise the ranges of a few returns on a 10-30 cm stem carry little diameter
        information (Cramer-Rao bound of a range-only fit at 3 cm noise: 4.5-26 cm of DBH
        with 3-9 returns); once the RMS test reads the true noise (``scan_noise_batch``) such
        candidates pass it. inf = off (every preset): at 3 cm the LOO chooses it for no
        held-out dataset and it lowers every training set's score (the covariance is not a
        calibrated precision on first-echo scans).
    dbh_sd_noise : bool
        First-echo fits (``beam_footprint_deg`` > 0, ``fit_method`` "ours"), numpy path: the
        diameter standard deviation reported with each detection (``covs``' radius row and
        column) is scaled by ``k = max(1, n_meas / s, s_res / s)``: ``s`` the noise the fit
        weighted its returns by, ``n_meas`` the range noise measured on the data
        (:func:`~stemmap.scan._segment_fits.fit_sigma` not capped by the tests' sigma) and
        ``s_res`` the fit's own residual scale over every return of the candidate (its RMS
        over ``n - 3`` degrees of freedom, the returns the robust loss set aside included).
        The fit's covariance is the inverse Hessian at ``s``, which is capped at the tests'
        configured 1 cm on a scan without a noise estimate of its own: at 3 cm of noise it
        stated a third of the error (ours, issue 11, Dec 5, docs/algorithms/
        scan-detection.md, "First-echo DBH standard error"). Only the reported covariance
        changes: positions, diameters and every test are the same. The ``stemmap`` preset
        turns it on; False = the fit's own covariance.
    dbh_sd_outline : float, metres, >= 0
        With ``dbh_sd_noise``'s scanners: a per-view diameter error the returns cannot show
        (a real trunk's outline is not the circle fitted to the side seen), added in
        quadrature to the reported diameter standard deviation, ``C_rr += (b / 2)^2``. The
        ``stemmap`` preset's value is chosen leave-one-dataset-out on the real slices
        (same section). 0 = none.
    centre_sd_along, centre_sd_across : float, >= 0 (a gain; metres)
        First-echo ``ours`` fits, numpy path: the centre block of the reported covariance
        is scaled by ``dbh_sd_noise``'s factor, the outline's radius error moves the centre
        along the line of sight by ``centre_sd_along`` times it, and an error of std
        ``centre_sd_across`` is added across it (:mod:`stemmap.scan._centre_cov`; ours,
        issue 11, Dec 6, "First-echo centre covariance"). Detections unchanged. 0, 0 = off.
    centre_sd_footprint, centre_sd_across_averaging : float, >= 0 (a share; metres)
        Averaging ``ours`` fits (``beam_divergence_deg`` > 0, no ``beam_footprint_deg``),
        both paths: the reported centre covariance gains, along the line of sight, the
        outline's radius error carried as for a first echo (``centre_sd_along`` times
        ``dbh_sd_outline / 2``) and ``centre_sd_footprint`` times the footprint's width at
        the trunk (range times ``beam_divergence_deg``) in quadrature, and an error of std
        ``centre_sd_across_averaging`` across it: the averaged edge returns' radius error
        grows with the footprint and moves the centre along the line of sight
        (:func:`stemmap.scan._centre_cov.averaging_centre_covs`; ours, issue 11, Dec 6,
        docs/algorithms/scan-detection.md, "Averaging centre covariance"). The radius and
        the centre-radius entries and every detection are unchanged. 0, 0 = off.
    dbh_sd_footprint : float, >= 0 (a share)
        Averaging ``ours`` fits, both paths: the reported radius variance gains the outline's
        ``(dbh_sd_outline / 2)^2`` and the square of ``dbh_sd_footprint`` times the
        footprint's width at the trunk (range times ``beam_divergence_deg``), and the
        centre-radius covariance the product of each with its centre term along the line of
        sight (``centre_sd_along`` / ``centre_sd_footprint``: the same errors move the radius
        and the centre; a rank-two addition, still a covariance): the averaged edge returns'
        radius error grows with the footprint and the fit's own diameter std does not
        (:func:`stemmap.scan._centre_cov.averaging_centre_covs`; ours, issue 11, Dec 6,
        docs/algorithms/scan-detection.md, "Averaging DBH standard error"). Only the
        reported covariance changes. 0 = off (the fit's own diameter std).
    dbh_sd_jackknife : float, >= 0
        First-echo ``ours`` fits, numpy path: the reported radius std is raised to this
        factor times the delete-a-group jackknife std of the radius where that is larger
        (:mod:`stemmap.scan._dbh_jackknife`; ours, issue 11, Dec 6, "Junction merges on
        lidR"). Only the reported covariance changes. 0 = off (every preset).
    stub_runs_inner : bool
        With ``stub_runs``: the run test's inner explanation (ours, issue 11, Dec 5,
        "Needles inside the arc"; :func:`~stemmap.scan._inner_runs.inner_runs`): of a
        candidate that the run test searches, the smallest run of consecutive returns that
        holds neither end return, lies outside the circle of the rest by more than
        ``stub_sigmas`` deletion deviations and leaves a rest that passes every test and the
        global chi-square test is found; where one is, the misfit is needles or a twig in
        front of the bark (a stem cannot return from in front of itself): that run is not
        fitted and no end run goes (the ends are the stem's). TreeLS pine 0.25 deg nearest,
        no noise: the silhouette return went for needles on two inner beams (grid 80: 1.93
        cm, with the option 1.43). False = only end runs. Numpy path.
    cut_ends : bool
        First-echo or thin-beam fits (``beam_footprint_deg`` > 0 or ``beam_divergence_deg``
        0): at each end of an accepted piece (corner split, step split, largest consistent
        arc) where it was cut from its candidate, the end return goes and the end is occluded
        when the piece fitted again passes every test (ours, issue 11, Dec 5, "The branch root
        at the arc end"; :func:`~stemmap.scan._cut_ends.trim_cut_ends`). At a cut the stem
        meets another surface (a branch root, a fillet, a touching stem): the last beam's
        footprint holds both, its first echo is the junction's and the footprint correction
        misplaces it, and the stem's silhouette on that side was never seen. Numpy path.
        False = the pieces keep their cut-end returns.
    fit_noise_floor : float, metres, >= 0
        First-echo fits (``beam_footprint_deg`` > 0, ``fit_method`` "ours") only: the circle
        fits weight the returns by the range noise measured on the data instead of the
        tests' sigma (ours, issue 11, Dec 5, "lidR view by view";
        :func:`~stemmap.scan._segment_fits.fit_sigma`): the scan's own estimate
        (:func:`~stemmap.scan.plausibility.scan_noise`), or the estimate over every scan of
        the batch where it has none (``batch_min`` 0), combined with the footprint's share
        (the segment's median absolute range step between adjacent returns over sqrt(12)), at
        least ``fit_noise_floor`` and at most the segment's sigma. The plausibility tests
        keep the segment's sigma (the configured floor, for bark and outlines); only the
        fit's Huber scale, its 4-sigma outlier rejection and the weight of the returns
        against the silhouette tangents change. A stem whose scans hold millimetres of range
        noise then follows its returns rather than one edge return on a stub or twig. 0 =
        off (the fit uses the tests' sigma). Numpy path (as every first-echo fit).
    split_search : bool
        Cut a candidate rejected as not convex (``depth``) or by the RMS test, whose
        validated corner split (if on) gave no trunk, where the Bayesian information
        criterion over one, two and three pieces of ``min_points`` returns or more, scored
        from running Kasa (1976) moments, says; accept a piece as the corner split's pieces
        are accepted, and only if no return of the candidate was seen through its circle
        (ours, issue 11, fifteenth round; :func:`~stemmap.scan._split_search.search_refit`):
        a trunk merged with a branch or stub where the junction is no concave corner. Its
        pieces pass the tests of an arc of ``arc_refit`` (no bark allowance in the RMS test,
        ``arc_tangent_sigmas``, ``arc_chi2``; :func:`~stemmap.scan._arcs.piece_passes`), and
        only candidates rejected as not convex are cut unless ``split_search_convex``
        (sixteenth round). Numpy path only; off in every preset.
    split_search_convex : bool
        With ``split_search``: also cut candidates that are convex towards the sensor as a
        whole and fail only the RMS test (the fifteenth round's rule). One convex outline
        that is no circle is a lumpy object (the simulator's rocks and bushes: 34 of the 35
        false pieces of the seed-1 drives) as often as a trunk with a stub beside it (lidR);
        one scan does not tell them apart (scan-detection-history.md, sixteenth round).
    step_split : bool
        Cut a candidate that fails the RMS test, whose corner split (if on) gave no trunk, at
        its largest range step (when above 3 sqrt(2) noise sigmas) and judge the two pieces as
        the arcs of ``arc_refit``, a cut end occluded only by a return across it nearer by
        ``occlusion_margin`` (ours, issue 11, seventeenth round;
        :func:`~stemmap.scan._step_split.step_refit`): a 4-return stem whose segment runs on
        into a branch behind its silhouette; a step that isolates one return in front (a
        twig) drops it instead, the rest judged whole. Compiled since Dec 5
        (:mod:`~stemmap.scan._fast_step_split`; with ``step_twigs``: numpy path only).
    step_noise_pool : bool
        With ``step_split`` and ``sigma_from_scan``: the step threshold's noise sigma of a
        scan without a range-noise estimate of its own (too few continuous beam triples) is
        the batch's pooled estimate (:func:`~stemmap.scan.plausibility.scan_noise` with
        ``pool``), for the threshold only (the fits and tests keep the scan's sigma; ours,
        issue 11, Dec 4, "step split, fold by fold"). A cut needs a step the noise does not
        make, and the configured sigma is a guess: on the single TreeLS pine at 0.25 deg with
        3 cm noise, a 4-return circle of radius 2.6 cm was cut from a 16-return trunk at an 11 cm
        noise step read against 1 cm. ``"batch"``: the estimate over the interior triples of
        *every* scan of the batch instead (``scan_noise`` ``batch_min=0``, no floor; the union
        is dominated by the scans with many triples, whose second differences hold the least
        bark curvature: issue 11, Dec 5, "step split, fold by fold"), for every scan without
        an estimate of its own. Compiled with ``step_split``.
    step_twigs : bool
        With ``step_split``: drop *every* one-return dip in front of a candidate that fails the
        RMS test (:func:`~stemmap.scan._step_split.front_dips`: a return nearer than both its
        neighbours by more than the step threshold; at a segment end, nearer than its one
        neighbour with no nearer return beyond the end), not only the one at its largest step,
        and judge the rest whole with the same tests (ours, issue 11, Dec 5, "twigs on several
        beams"): a stem seen through twigs on several of its beams. Changes no row of the
        real slices and adds clutter pieces on the simulator (a negative result kept as an
        option). Numpy path only.
    """

    name: str = "custom"
    range_min: float | None = None
    range_max: float | None = None
    fov_deg: tuple[float, float] | None = None
    tilt: Literal["none", "eq1", "rotation"] = "rotation"
    median_filter: bool = False
    segmentation: Literal["range_jump", "euclidean"] = "range_jump"
    max_jump: float = 0.2
    range_factor: float = 0.0
    max_skip: int = 0
    occlusion_margin: float = 0.2
    point_curvature_min: float | None = None
    radius_median: float | None = None
    split_merged: bool = False
    min_points: int = 3
    min_points_partial: int = 3
    mixed_end_min_points: int = 0
    residual_floor: float = 0.0
    outline_floor_points: int = 0
    outline_floor_min: float = 0.003
    max_points: int | None = None
    min_width: float = 0.0
    max_width: float = math.inf
    min_depth: float = -math.inf
    min_curvature: float = -math.inf
    max_curvature: float = math.inf
    reject_straight: bool = False
    straight_ratio: float = 0.05
    straight_test: Literal["chi2", "ratio"] = "chi2"
    straight_min_points: int = 3
    straight_depth_sigmas: float = math.inf
    straight_curvature: bool = False
    occluded_blend_sigmas: float = math.inf
    drop_partial: bool = False
    fit_method: str = "kasa"
    sigma: float = 0.01
    sigma_rel: float = 0.0
    min_radius: float = 0.0
    max_radius: float = math.inf
    max_radius_width_ratio: float = math.inf
    max_rms_sigma: float = math.inf
    beam_footprint_deg: float = 0.0
    beam_divergence_deg: float = 0.0
    neighbour_silhouette: bool = True
    edge_hit_min: float = 0.5
    edge_hit_max: float = 0.5
    edge_hit_window: bool = False
    fit_residuals: Literal["range", "orthogonal"] = "range"
    sigma_from_data: bool = False
    roughness_max_factor: float = 3.0
    rms_robust: bool = False
    rms_dof: bool = False
    sigma_from_scan: bool = False
    scan_noise_jump: float = 0.2
    scan_noise_surface: float = 0.006
    scan_noise_pool: bool = False
    scan_noise_batch: float = 0.0
    batch_noise_scale: Literal["mad", "biweight"] = "mad"
    bark_roughness: float = 0.0
    lobe_roughness: float = 0.0
    lobe_smooth_sigmas: float = 2.0
    rms_noise_from_fit: float = 0.0
    rms_own_sigmas: float = 1.5
    lobe_harmonics: int = 0
    lobe_prior: float = 0.045
    lobe_max: float = 0.1
    split_corners: bool = False
    corner_depth: float = 0.03
    corner_span: int = 2
    corner_depth_convex: float = math.inf
    corner_sigmas: float = 5.0
    gap_splits: int = 0
    gap_ratio: float = 0.0
    gap_sigmas: float = 0.0
    refit_pieces: bool = False
    refit_sigmas: float = 3.0
    refit_split: Literal["gap", "outliers", "outlier_ends", "corners"] = "gap"
    refit_validate: bool = False
    arc_refit: bool = False
    arc_sigmas: float = 3.0
    arc_floor_sigmas: float = 1.0
    arc_replace: float = math.inf
    arc_short_steps: bool = False
    arc_tangent_sigmas: float = math.inf
    arc_chi2: bool = False
    behind_sigmas: float = math.inf
    stub_sigmas: float = math.inf
    edge_protrusion: float = 0.0
    fit_noise_floor: float = 0.0
    stub_runs: bool = False
    stub_runs_snoop: bool = False
    stub_runs_worst: bool = False
    stub_runs_inner: bool = False
    cut_ends: bool = False
    max_dbh_sd: float = math.inf
    dbh_sd_noise: bool = False
    dbh_sd_outline: float = 0.0
    centre_sd_along: float = 0.0
    centre_sd_across: float = 0.0
    centre_sd_footprint: float = 0.0
    centre_sd_across_averaging: float = 0.0
    dbh_sd_footprint: float = 0.0
    dbh_sd_jackknife: float = 0.0
    split_search: bool = False
    split_search_convex: bool = False
    step_split: bool = False
    step_noise_pool: bool | Literal["batch"] = False
    step_twigs: bool = False

    def __post_init__(self) -> None:
        check_fields(self)

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> DetectorConfig:
        """The named preset (see :data:`PRESETS`), with optional field overrides."""
        return cls(**preset_values(name, overrides, {f.name for f in fields(cls)}))

    def edge_window_share(self) -> float:
        """The least share of the footprint in an averaging edge return's range window: 0.5
        (the default edge model), or with ``edge_hit_window`` the assumed threshold's lower
        end ``edge_hit_min``, at least :data:`EDGE_WINDOW_MIN` (a window of nothing has no
        mean range)."""
        if not self.edge_hit_window:
            return 0.5
        return max(self.edge_hit_min, EDGE_WINDOW_MIN)

    def scan_noise_batch_min(self) -> float:
        """The smallest batch noise estimate a scan without its own takes, metres
        (``scan_noise_batch x sigma``; ``inf`` when off)."""
        if not (self.sigma_from_scan and self.scan_noise_batch > 0.0):
            return math.inf
        return self.scan_noise_batch * self.sigma

    def to_dict(self) -> dict[str, Any]:
        """All parameters as plain values (for benchmark/CLI output)."""
        d = asdict(self)
        if d["fov_deg"] is not None:
            d["fov_deg"] = list(d["fov_deg"])
        return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in d.items()}
