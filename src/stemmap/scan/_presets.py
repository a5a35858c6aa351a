"""The detector presets: each paper's published parameters (:data:`PRESETS`), what each preset
takes from its paper and what it had to choose (:data:`PRESET_NOTES`), and the largest-arc
setting of the ``stemmap`` preset (:data:`ARC_OPTIONS`).

Split from :mod:`stemmap.scan.config`, which re-exports every name here (:data:`PRESETS` and
:data:`PRESET_NOTES` also :mod:`stemmap.scan.detect` and :mod:`stemmap.scan`): the parameter
values and their provenance are one concept, the :class:`~stemmap.scan.config.DetectorConfig`
fields and their validation another. Each preset is a dict of field overrides of
``DetectorConfig()``; ``DetectorConfig.preset(name)`` builds it.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ARC_OPTIONS", "PRESETS", "PRESET_NOTES"]


#: The ``stemmap`` preset's largest-consistent-arc setting (issue 11: arcs since the fifteenth
#: round, with their tangent-range and chi-square tests; short arcs set off by a range step since
#: the sixteenth), also what ``stemmap detect --arcs`` adds to any other preset.
ARC_OPTIONS: dict[str, Any] = {
    "arc_refit": True,
    "arc_sigmas": 2.0,
    "arc_replace": 3.0,
    "arc_tangent_sigmas": 3.0,
    "arc_chi2": True,
    "arc_short_steps": True,
}

#: Published parameters of each paper; comments name the section. Values the paper does not
#: publish are listed in PRESET_NOTES.
PRESETS: dict[str, dict[str, Any]] = {
    "zheng2012": {
        # §2.1: LMS291, 0.25 deg, 100 deg scan (40-140 deg, 90 = forward), 8 m range
        "range_max": 8.0,
        "fov_deg": (-50.0, 50.0),
        "tilt": "eq1",  # eq. 1
        "segmentation": "range_jump",  # eq. 2
        "max_jump": 0.2,  # §3.2: Delta l_max = 0.2 m
        "max_skip": 0,
        "point_curvature_min": -0.1,  # eq. 3 criterion (2); value not published
        "min_points": 3,
        "max_width": 1.0,  # criterion (3); value not published
        "min_depth": 0.01,  # criterion (4); value not published
        "min_curvature": 1.0 / 0.6,  # criterion (1): radius <= 0.6 m; value not published
        "max_curvature": 1.0 / 0.03,  # radius >= 3 cm; value not published
        "fit_method": "fletcher_reeves",  # §3.3
        "sigma": 0.01,
    },
    "xue2018": {
        # §3.1: LMS 192, 0.5 deg, 8 m; §3.2.3 only 60-120 deg (camera overlap) is used
        "range_max": 8.0,
        "fov_deg": (-30.0, 30.0),
        "median_filter": True,  # §2.2
        "segmentation": "range_jump",  # edges by the change rate of the polar radius (§2.4.2)
        "max_jump": 0.2,  # threshold not published; Zheng's value
        "min_points": 3,
        "min_width": 0.05,  # W = [w_min, w_max] not published; their trunks are 130-185 mm
        "max_width": 0.5,
        "fit_method": "chord_width",  # eq. 12: the width is the diameter estimate
        "sigma": 0.01,
    },
    "visual_lidar2023": {
        # §2.2: 100 deg camera view, 5 m, width <= 0.55 m; §2.3: radius median 0.5 m, >= 40 pts
        "range_max": 5.0,
        "fov_deg": (-50.0, 50.0),
        "segmentation": "euclidean",
        "max_jump": 0.2,  # grouping distance not published
        "radius_median": 0.5,
        "min_points": 40,
        "max_width": 0.55,
        "fit_method": "kasa",  # §2.3: Kasa (1976)
        "sigma": 0.01,
    },
    "stemmap": {
        # ours: every value chosen on the simulator (docs/algorithms/scan-detection.md)
        "segmentation": "euclidean",
        "max_jump": 0.1,
        "range_factor": 3.0,
        "max_skip": 1,
        "occlusion_margin": 0.2,
        "radius_median": 0.8,
        "split_merged": True,
        "min_points": 4,
        "min_points_partial": 5,
        "max_width": 1.6,
        "min_depth": 0.0,
        "reject_straight": True,
        "straight_test": "chi2",
        "straight_min_points": 8,
        "fit_method": "ours",
        "sigma": 0.01,
        "min_radius": 0.02,
        "max_radius": 0.8,
        "max_radius_width_ratio": 0.8,
        "max_rms_sigma": 2.0,
        # SICK LMS2xx-class averaging scanner (docs/algorithms/scan-fits.md, "edge model")
        "beam_divergence_deg": 0.25,
        # sigma_from_data / rms_robust (issue 11) stay off: leave-one-dataset-out on the real
        # slices chose them off for every held-out dataset (scan-detection.md)
        # issue 11, second round: leave-one-dataset-out on the real slices over 18 scanner
        # models (benchmarks/real_geometry.py --loo --vantage 20; scan-detection-history.md)
        # among the settings that keep the simulated precision >= 0.95: 3 % relative bark
        # roughness in the RMS test, no concave-corner cuts (split_corners: lidR recall
        # 0.31 -> 0.69, but simulated precision in clutter 0.979 -> 0.947-0.967 on the demo drive)
        # third round (false alarms on the real slices in the objective; grid with largest-gap
        # cuts, re-fitted pieces and a sagitta exemption from the straightness test, same
        # simulated constraint): bark 3 % again and no straightness rejection of a segment
        # bulging > 3 sigma towards the sensor (best on all five datasets, chosen for 3 of 5
        # held out); gap_splits, refit_pieces stay off (scan-detection-history.md)
        # sixth round: sigma_from_scan (the scan's own noise estimate) stays off: chosen
        # leave-one-dataset-out for 4 of 5 held-out datasets, but the `stemmap demo` precision
        # falls to 0.938 (< 0.95) (scan-detection-history.md). Seventh round: run-end triples left
        # out of the estimate, demo precision 0.956 / 0.991 / 0.967 (seeds 1-3), chosen for
        # 3 of 5 held out, but 24.3-24.5 k scans/s (< 25 k): still off. Eighth round: the
        # compiled estimate counts its triples in one branch-free pass (the same value bit for
        # bit) and costs ~1.5 % of the batch instead of ~3.5 %; leave-one-out unchanged (3 of
        # 5 held out), demo precision 0.956 / 0.991 / 0.967 on seeds 1-3: on. Ninth round:
        # validated concave-corner splits (refit_pieces, refit_split="corners",
        # refit_validate; lidR recall 0.31 -> 0.69 not held out, demo precision 0.954 / 0.989
        # / 0.964) stay off: chosen for no held-out dataset, numpy path only (~0.47x speed).
        # Eleventh round: the split runs in the compiled path (same results), at 0.99-1.05x the
        # speed of the default without it (interleaved with main, benchmarks/scan_detection
        # speed); leave-one-dataset-out among the settings the compiled path runs chooses it
        # for 4 of 5 held-out datasets (not lidR, the one it helps): on. Twelfth round: the
        # relaxed RMS tests (rms_noise_from_fit: a candidate's own noise on scans without
        # their own estimate; lobe_roughness: smooth lobed outlines) stay off: chosen for 1 /
        # 0 of 5 held-out datasets (scan-detection-history.md). Fourteenth round: the largest
        # consistent arcs (arc_refit) run in the compiled path, but stay off: on this default
        # they take the demo precision to 0.949 (< 0.95); the best admitted LOO setting (the
        # arcs without sigma_from_scan and the corner split) loses most trunks of a noisier
        # scanner (simulated RPLIDAR orchard: 276 vs 1 593 detections) (scan-detection-history.md).
        # Fifteenth round: the lobed outline (lobe_harmonics) stays off: chosen for no
        # held-out dataset, aRchi's recall unchanged, numpy path only (scan-detection-history.md)
        # Fifteenth round: the same arcs on this default, passing only in front of their
        # circle's tangent range (arc_tangent_sigmas 3: a face of a lobed rock whose circle
        # runs through a return on its far side) and with residuals of the range noise
        # (arc_chi2: upper 1 % chi-square over n - 3 degrees of freedom): demo precision
        # 0.952 (>= 0.95), the LOO's best training score among the admitted settings within
        # 0.001; chosen held out among the compiled settings, the tangent test alone, for 4
        # of 5 datasets; speed within the shared machine's spread of the default: on.
        # Sixteenth round: arcs of min_points (4) returns count when a range step > max_jump
        # sets them off at every cut end (arc_short_steps: the TreeLS plot's 4-return stems
        # merged with a stem or twig 0.16-0.24 m nearer; plot recall 0.87 -> 0.90): chosen
        # held out for 4 of 5 datasets (all 5 among the compiled settings), demo precision
        # 0.951, speed 1.01x the default without it in one process: on.
        # Dec 5: the step split (step_split: a candidate that fails the RMS test cut at its
        # largest range step, the step read against every scan's noise where a scan has no
        # estimate of its own, step_noise_pool="batch"; LOO grid 59): the LOO chooses it (grid
        # 60 = 59 + averaging "edge any") for all five held-out datasets; the TreeLS plot held
        # out at 0.5 deg nearest, no noise 0.902 -> 0.951 (its target met); simulated
        # precision, mean over seeds 1-10 (benchmark / demo drive, one scored domain) 0.9589 /
        # 0.9801; compiled at 0.91-0.94x the speed without it: on
        "step_split": True,
        "step_noise_pool": "batch",
        # Dec 5 ("The fit's measured noise, the default"): first-echo fits (beam_footprint_deg
        # > 0) weight the returns by the measured range noise and the footprint's range step,
        # at least 3 mm (fit_noise_floor; LOO grid 67 = 59 + it): the LOO chooses it (with the
        # averaging "edge any", grid 65) for three of five held-out datasets; among the settings
        # that keep the half-footprint edge model it chooses grid 67 for four of five; held out
        # at 0.5 deg nearest, no noise, lidR recall 0.923 -> 1.00 (RMSE 4.63 -> 4.20 cm), FORTLS
        # RMSE 1.35 -> 0.71 cm; an averaging scanner (the default, the simulator) runs as before,
        # bit for bit (compiled path; the option acts on the numpy first-echo path only): on
        "fit_noise_floor": 0.003,
        # Dec 5 ("Grid 80 is the `stemmap` preset"): LOO grid 80 = 67 + the stub test by runs
        # of end returns (stub_sigmas 2, stub_runs) read as data snooping against the measured
        # noise (stub_runs_snoop), held to the side of an inner worst return that alone
        # explains the misfit (stub_runs_worst), a piece's cut-end return dropped (cut_ends),
        # and the batch's noise by the biweight (batch_noise_scale): the LOO chooses it for 4
        # of 5 held-out datasets (lidR: grid 72) and admits it on the simulator; per dataset,
        # 0.5 deg nearest, no noise, lidR 4.20 / +2.38 -> 1.75 / +0.92 cm, TreeLS pine 0.25
        # deg 1.49 -> 1.93 cm; the trims act on first-echo fits only (numpy path), so an
        # averaging scanner (the default, the simulator) runs the compiled path as before
        "stub_sigmas": 2.0,
        "stub_runs": True,
        "stub_runs_snoop": True,
        "stub_runs_worst": True,
        # Dec 5 ("Grid 85 is the `stemmap` preset"): LOO grid 85 = 80 + a run of inner returns
        # in front of the circle that explains the misfit is dropped and no end trimmed
        # (needles, a twig between the sensor and the bark): chosen for 3 of 5 held-out
        # datasets (TreeLS pine: 82, lidR: 44), TreeLS pine 0.25 deg 1.93 -> 1.43 cm, the plot
        # 0.5 deg 2.33 -> 2.17 cm, no lidR row moves; first-echo fits only
        "stub_runs_inner": True,
        "cut_ends": True,
        "batch_noise_scale": "biweight",
        "refit_pieces": True,
        "refit_split": "corners",
        "refit_validate": True,
        "bark_roughness": 0.03,
        "straight_depth_sigmas": 3.0,
        "sigma_from_scan": True,
        # Dec 5 (branch fecalib): the first-echo DBH std at the measured noise plus a 1.3 cm
        # outline term, chosen leave-one-dataset-out on the real-bark slices (held-out median
        # |z| 0.43-0.74 on the TreeLS plot / pine and lidR 0 cm, was 1.3-1.8); the reported
        # covariance only, every detection the same (scan-detection.md, "First-echo DBH
        # standard error")
        "dbh_sd_noise": True,
        "dbh_sd_outline": 0.013,
        # Dec 6 (branch centrecov): the first-echo centre covariance at the same noise, the
        # outline's radius error carried along the line of sight (gain 1.3) and 0.4 cm across
        # it, chosen leave-one-dataset-out on the real-bark slices (held-out median Mahalanobis
        # distance 0.93-1.59, was 1.8-3.6; 1.18 calibrated); the reported covariance only
        # (scan-detection.md, "First-echo centre covariance")
        "centre_sd_along": 1.3,
        "centre_sd_across": 0.004,
        # Dec 6 (branch avgcov): the averaging scanners' centre covariance: the same outline
        # term along the line of sight plus 0.7 of the footprint's width at the trunk, and 0.6
        # cm across it, chosen leave-one-dataset-out on the real-bark slices pooled over both
        # virtual SICK models (any sub-ray, q = 0.3) (held-out median Mahalanobis distance
        # 0.77-1.59 on the TreeLS plot and pine, was 2.1-3.8; 1.18 calibrated); the reported
        # covariance only (scan-detection.md, "Averaging centre covariance")
        "centre_sd_footprint": 0.7,
        "centre_sd_across_averaging": 0.006,
        # Dec 6 (branch avgdbhsd): the averaging scanners' DBH std: the outline's 1.3 cm and 0.6
        # of the footprint's width at the trunk on the radius, the centre-radius covariance of
        # the same two errors, chosen leave-one-dataset-out on the real-bark slices pooled over
        # both virtual SICK models (held-out median |z| of the DBH error 0.49-0.97 on the TreeLS
        # plot and pine, was 1.6-3.1); the reported covariance only (scan-detection.md,
        # "Averaging DBH standard error")
        "dbh_sd_footprint": 0.6,
        **ARC_OPTIONS,
    },
}

#: What each preset takes from its paper and what it had to choose.
PRESET_NOTES: dict[str, str] = {
    "zheng2012": (
        "Published: 8 m, 100 deg window, eq. 1 tilt, eq. 2 range jump 0.2 m, Fletcher-Reeves "
        "fit. Named but not published: curvature bounds, single-point curvature minimum, "
        "greatest width, smallest depth (we use radius 3-60 cm, -0.1 m, 1.0 m, 1 cm)."
    ),
    "xue2018": (
        "Published: 8 m, 0.5 deg, 60-120 deg used, 3-neighbour median, width by eq. 12. Not "
        "published: the edge threshold on the polar radius (we use 0.2 m) and W=[w_min,w_max] "
        "(we use 5-50 cm)."
    ),
    "visual_lidar2023": (
        "Published: 100 deg, 5 m, width 0.55 m, radius median 0.5 m, 40 points, Kasa fit. Not "
        "published: the grouping distance (we use 0.2 m). The 40-point minimum assumes their "
        "0.12 deg RPLIDAR S2; at 0.5 deg it removes almost every trunk."
    ),
    "stemmap": "Ours: adaptive Euclidean segmentation, straight-segment rejection, splitting "
    "radius median filter, optional concave-corner cuts, fit plausibility checks. "
    "Segmentation and "
    "filter values tuned on the simulator. Chosen leave-one-dataset-out on virtual 2D scans "
    "(18 scanner models, 0.25-1 deg, nearest-return and SICK-class averaging, 0-3 cm noise) "
    "of the five real breast-height slices with reference trunks (FORTLS, TreeLS pine plot / "
    "pine, lidR, aRchi tree 1; benchmarks/real_geometry.py --loo --vantage 20), never on the "
    "simulator: first round, the noise-scale and residual-test choices (sigma_from_data, "
    "roughness_max_factor, rms_robust off, max_rms_sigma 2, for every held-out dataset); "
    "second round (issue 11), among the settings that keep the simulated precision >= 0.95 "
    "(scan_detection seed 1 and the demo drive): bark_roughness 3 %, chosen for four of five "
    "held-out datasets (aRchi tree 1 at 0.5 deg nearest: recall 0.42 -> 0.53); the "
    "concave-corner cuts (split_corners) stay off: they take lidR from recall 0.31 to 0.69 but "
    "let cut pieces of clutter through (demo precision 0.979 -> 0.947-0.898). Third round, "
    "with false alarms on the real slices in the objective (F1): bark 3 % again, and a segment "
    "bulging > 3 sigma towards the sensor is never rejected as straight "
    "(straight_depth_sigmas 3: near small stems of the TreeLS plot); largest-gap cuts "
    "(gap_splits: TreeLS plot recall 0.82 -> 0.87) and re-fitted pieces (refit_pieces) stay "
    "off. Sixth to eighth rounds: sigma_from_scan on (each scan's own range-noise estimate "
    "from its interior continuous beam triples, used where it exceeds sigma): chosen for 3 of "
    "5 held-out datasets; with 3 cm of range noise it lifts the FORTLS recall at 0.25 deg "
    "nearest from 0.49 to 0.87 and the TreeLS plot's from 0.34 to 0.65; `stemmap demo` "
    "precision 0.956 / 0.991 / 0.967 on seeds 1-3; ~1.5 % of the compiled batch time. "
    "Eleventh round: validated concave-corner splits of rejected candidates on (refit_pieces, "
    "refit_split='corners', refit_validate): a trunk merged with a branch or stem in one "
    "segment is cut at the junction and kept when exactly one piece passes every test; "
    "compiled, at no measurable speed cost; chosen leave-one-dataset-out among the compiled "
    "settings for 4 of 5 held-out datasets (lidR recall 0.31 -> 0.69 not held out; demo "
    "precision 0.954 / 0.989 / 0.964). "
    "Fifteenth round: the largest consistent arc of a candidate (arc_refit, arc_sigmas 2, "
    "arc_replace 3) on: a trunk whose segment runs on into a branch or fillet is fitted on "
    "its own arc, which passes only when no return lies behind the circle's tangent range "
    "(arc_tangent_sigmas 3) and its residuals pass the upper 1 % chi-square test (arc_chi2); "
    "lidR at 0.5 deg nearest recall 0.69 -> 0.85, DBH RMSE 5.9 -> 4.8 cm, the TreeLS plot "
    "0.85 -> 0.87; demo precision 0.952. "
    "Sixteenth round: an arc of 4 returns counts when a range step larger than max_jump sets "
    "it off at every cut end (arc_short_steps): the TreeLS plot 0.87 -> 0.90; demo precision "
    "0.951. "
    "Dec 5: the step split on (step_split, step_noise_pool='batch'): a candidate that fails "
    "the RMS test is cut at its largest range step when the step exceeds 3 sqrt(2) sigmas of "
    "the range noise (every scan's pooled estimate where a scan has none of its own): a thin "
    "stem whose segment runs on into a branch behind it; chosen leave-one-dataset-out (with "
    "the averaging 'edge any', grid 60) for all five held-out datasets; the TreeLS plot held "
    "out at 0.5 deg nearest, no noise: recall 0.902 -> 0.951, DBH RMSE 2.25 cm, bias +0.63 cm "
    "(its target met); lidR 0.846 -> 0.923; simulated precision, mean over seeds 1-10 "
    "(benchmark / demo drive) 0.9589 / 0.9801 (0.9665 / 0.9833 without it); compiled at "
    "0.91-0.94x the speed without it. "
    "Dec 5: first-echo fits weighted by the measured noise (fit_noise_floor 3 mm; only with "
    "beam_footprint_deg > 0): each segment's fit weights its returns by the scan's own "
    "range-noise estimate (or the batch's) combined with the footprint's range step, at least "
    "3 mm and at most sigma, while the plausibility tests keep sigma: a stem whose returns "
    "scatter by millimetres follows them, not one edge return on a stub or twig; held out at "
    "0.5 deg nearest-return, no noise: lidR recall 0.923 -> 1.00, DBH RMSE 4.63 -> 4.20 cm, "
    "FORTLS 1.35 -> 0.71 cm (recall 0.985 -> 0.971), TreeLS plot 2.25 -> 2.35 cm, TreeLS pine "
    "1.45 -> 1.49 cm; the LOO's full choice adds the averaging 'edge any' (grid 65), which "
    "breaks the simulated DBH target (1.54 cm at <= 5 m over seeds 1-20), so only the "
    "first-echo half is the default (grid 67); averaging scanners and the simulator are "
    "unchanged bit for bit. "
    "Dec 5: LOO grid 80 (grid 67 + the stub test by runs of end returns, stub_sigmas 2 and "
    "stub_runs, read as data snooping against the measured noise, stub_runs_snoop, and held to "
    "the side of an inner worst return that alone explains the misfit, stub_runs_worst; a "
    "re-fitted piece's cut-end return dropped, cut_ends; the batch's range noise by the "
    "biweight midvariance, batch_noise_scale): a branch leaving a stem's flank over several "
    "beams, or the junction at a piece's cut end, no longer widens the first-echo fit; chosen "
    "leave-one-dataset-out for 4 of 5 held-out datasets (lidR held out: grid 72) and admitted "
    "on the simulator; per dataset at 0.5 deg nearest-return, no noise, lidR DBH RMSE 4.20 -> "
    "1.75 cm, bias +2.38 -> +0.92 cm (0.25 deg 3.91 -> 1.46 cm), TreeLS pine 0.25 deg 1.49 -> "
    "1.93 cm (a needle return on the trimmed end's side), the TreeLS plot 0.25 deg 1 cm 2.46 "
    "-> 2.64 cm; the trims act on first-echo fits only and the averaging rows and the "
    "simulator are grid 67's bit for bit. "
    "Dec 5: LOO grid 85 (grid 80 + stub_runs_inner: a run of inner returns that lies in front "
    "of the rest's circle and alone explains the misfit, needles or a twig between the sensor "
    "and the bark, is dropped and no end return trimmed): chosen for 3 of 5 held-out datasets "
    "(FORTLS, the TreeLS plot, aRchi; TreeLS pine: grid 82, lidR: grid 44); per dataset TreeLS "
    "pine 0.25 deg 1.93 -> 1.43 cm (grid 67: 1.49), the plot 0.5 deg 2.33 -> 2.17 cm, no lidR "
    "row moves; first-echo fits only, about 1.3x grid 80's CPU there. "
    "Dec 5: the first-echo DBH std (dbh_sd_noise, dbh_sd_outline 1.3 cm): the reported "
    "covariance at the measured noise, not the fit's capped 1 cm, plus an outline term chosen "
    "leave-one-dataset-out on the real-bark slices; held-out median |z| 0.43-0.74 on the "
    "TreeLS plot and pine at 0-3 cm (was 1.2-1.6); the detections are unchanged. "
    "Dec 6: the first-echo centre covariance (centre_sd_along 1.3, centre_sd_across 0.4 cm): "
    "the centre block at the same noise, the outline's radius error along the line of sight "
    "and a term across it, chosen leave-one-dataset-out; held-out median Mahalanobis distance "
    "0.93-1.59 on the real-bark slices (was 1.8-3.6; 1.18 calibrated), detections unchanged. "
    "Dec 6: the averaging scanners' centre covariance (centre_sd_footprint 0.7, "
    "centre_sd_across_averaging 0.6 cm): the same outline term along the line of sight plus "
    "0.7 of the footprint's width at the trunk, and a term across it, chosen "
    "leave-one-dataset-out on the real-bark slices with both virtual SICK models pooled; "
    "held-out median Mahalanobis distance 0.77-1.59 on the TreeLS plot and pine (was 2.1-3.8), "
    "detections unchanged. "
    "Dec 6: the averaging scanners' DBH std (dbh_sd_footprint 0.6): the outline's 1.3 cm and "
    "0.6 of the footprint's width at the trunk on the radius, with the centre-radius "
    "covariance of the same errors, chosen leave-one-dataset-out on the real-bark slices with "
    "both virtual SICK models pooled; held-out median |z| of the DBH error 0.49-0.97 on the "
    "TreeLS plot and pine (was 1.6-3.1), detections unchanged. "
    "For a first-echo "
    "(nearest-return) scanner set beam_footprint_deg to its footprint (stemmap detect "
    "--footprint): on the FORTLS slice at 0.5 deg this takes the DBH bias from +7 cm to "
    "+0.01 cm (first-round benchmark; -0.64 cm on the fixed one).",
    "ohman2007": "No preset: the paper publishes no laser segmentation parameters.",
}
