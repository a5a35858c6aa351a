"""The compiled detector pipeline (stemmap.scan._detect_fast) against the step-by-step numpy
pipeline of named functions it replaces on the hot path.

The kernel evaluates the same expressions in the same order and replicates numpy's pairwise
summation, so on this machine the two agree bit for bit; the tolerance below (1e-9 relative,
1e-15 absolute for covariance entries near zero) only leaves room for a platform whose numpy
and numba math libraries round differently. Detections must match exactly (same scans, same
number of returns).
"""

import dataclasses
import math

import numpy as np
import pytest
from tests.scan.test_stub_runs import GRID_67

from stemmap.scan import _detect_fast
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.sim.forest import add_clutter, random_stand
from stemmap.sim.scanner import scanner_preset, simulate_scans
from stemmap.types import ScanBatch, StemObservations

FIELDS = ("centers", "radii", "covs", "arc_deg", "widths", "quality", "times")


@pytest.fixture(scope="module")
def stand():
    rng = np.random.default_rng(11)
    st = random_stand(45, (30.0, 30.0), dbh_mean=0.3, dbh_std=0.1, dbh_min=0.08, rng=rng)
    return add_clutter(st, n_bushes=4, n_branches=4, n_walls=1, n_fences=1, n_rocks=3, rng=rng)


def _poses(n):
    t = np.linspace(0.0, 1.0, n)
    return np.column_stack((3.0 + 24.0 * t, 4.0 + 20.0 * t, 0.7 + 3.0 * t))


def _scans(stand, **model):
    base = scanner_preset("sick_lms", range_max=30.0)
    batch, _, _ = simulate_scans(stand, _poses(40), dataclasses.replace(base, **model), rng=3)
    return batch


def _both(det, batch):
    args = (
        batch.ranges,
        batch.times,
        batch.angle_min,
        batch.angle_increment,
        batch.range_min,
        batch.range_max,
        batch.frame,
    )
    return det._run_compiled(*args), det._run_numpy(*args, None, None)


def assert_same(fast: StemObservations, ref: StemObservations) -> None:
    assert len(fast) == len(ref)
    np.testing.assert_array_equal(fast.index, ref.index)
    np.testing.assert_array_equal(fast.n_points, ref.n_points)
    assert fast.source == ref.source and fast.frame == ref.frame
    for name in FIELDS:
        np.testing.assert_allclose(
            getattr(fast, name), getattr(ref, name), rtol=1e-9, atol=1e-15, err_msg=name
        )


#: The fifteenth round's arc tests off (on in the stemmap preset since).
_NO_ARC_TESTS = {"arc_tangent_sigmas": math.inf, "arc_chi2": False}
CONFIGS = {
    "stemmap": {},
    "no_split": {"split_merged": False},
    # a thin beam is a first echo: the preset's first-echo trims (stub runs, inner runs, cut
    # ends) act there and only the numpy path runs them (test_thin_beams_run_numpy_with_trims),
    # so the two pipelines are compared on the rest of the chain
    "thin_beams": {
        "beam_divergence_deg": 0.0,
        **{k: v for k, v in GRID_67.items() if k != "batch_noise_scale"},
    },
    "orthogonal": {"fit_residuals": "orthogonal", "neighbour_silhouette": False},
    "estimated_sigma": {"sigma": 0.0, "straight_test": "ratio", "max_rms_sigma": math.inf},
    "relative_sigma": {"sigma": 0.005, "sigma_rel": 0.002},
    # issue 11: sigma raised to the measured roughness, robust residual-scale RMS test
    "data_sigma_robust": {"sigma_from_data": True, "roughness_max_factor": 3.0, "rms_robust": True},
    "data_sigma": {"sigma_from_data": True, "roughness_max_factor": 2.0, "sigma": 0.005},
    # issue 11: sigma raised to the scan's own noise estimate (alone, with corners and gaps)
    "scan_sigma": {"sigma_from_scan": True, "sigma": 0.002},
    "scan_sigma_corners_gaps": {
        "sigma_from_scan": True,
        "sigma": 0.003,
        "split_corners": True,
        "gap_splits": 2,
        "gap_sigmas": 2.0,
        "min_depth": 0.01,
    },
    # issue 11: concave-corner cuts (with and without the splitting median filter), bark term
    "corners_bark": {
        "split_corners": True,
        "corner_depth": 0.02,
        "corner_depth_convex": 0.04,
        "bark_roughness": 0.08,
    },
    "corners_fine": {
        "split_corners": True,
        "split_merged": False,
        "corner_span": 1,
        "corner_depth": 0.01,
        "bark_roughness": 0.03,
    },
    # issue 11, third round: largest-gap cuts of non-convex segments (alone, with corners)
    "gaps": {"gap_splits": 2, "min_depth": 0.01},
    "straight_depth": {"straight_depth_sigmas": 1.5, "straight_min_points": 5},
    "gaps_noise_floor": {"gap_splits": 2, "gap_ratio": 1.5, "gap_sigmas": 2.0, "min_depth": 0.01},
    "gaps_corners": {
        "gap_splits": 3,
        "split_corners": True,
        "corner_depth": 0.015,
        "corner_depth_convex": 0.04,
        "occlusion_margin": 0.05,
    },
    "zheng_like": {
        "segmentation": "range_jump",
        "max_jump": 0.2,
        "max_skip": 0,
        "point_curvature_min": -0.1,
        "radius_median": None,
        "fov_deg": (-50.0, 50.0),
        "range_max": 8.0,
        "median_filter": True,
    },
    "strict": {"max_points": 40, "drop_partial": True, "min_depth": 0.01, "min_width": 0.05},
    # issue 11: validated corner split of rejected candidates (compiled since the tenth round;
    # the real merges: test_detect_fast_real.py), and unvalidated with convex cuts
    "corner_split": {
        "refit_pieces": True,
        "refit_split": "corners",
        "refit_validate": True,
        "corner_depth": 0.015,
        "corner_depth_convex": 0.03,
    },
    "corner_split_all_pieces": {
        "refit_pieces": True,
        "refit_split": "corners",
        "corner_depth": 0.01,
        "corner_depth_convex": 0.03,
        "min_depth": 0.01,
    },
    # issue 11: the largest consistent arc of a non-convex candidate (compiled since the
    # fourteenth round; the real trunks merged with branches: test_detect_fast_real.py), with
    # and without the corner split, replacing accepted fits, short stepped arcs
    # (the tangent and chi-square tests off unless named: on in the preset since the fifteenth)
    "arcs": {
        "arc_refit": True,
        "arc_sigmas": 2.0,
        "arc_replace": math.inf,
        "refit_pieces": False,
        **_NO_ARC_TESTS,
    },
    "arcs_replace": {"arc_refit": True, "arc_sigmas": 2.0, "arc_replace": 3.0, **_NO_ARC_TESTS},
    "arcs_replace_loose": {
        **_NO_ARC_TESTS,
        "arc_refit": True,
        "arc_sigmas": 3.0,
        "arc_floor_sigmas": 2.0,
        "arc_replace": 1.2,
        "arc_short_steps": True,
        "bark_roughness": 0.08,
    },
    # fifteenth round: the arcs pass only in front of their tangent range and with residuals
    # of the noise (the grid setting, and a tight tangent bound that rejects more)
    "arcs_consistent": {
        "arc_refit": True,
        "arc_sigmas": 2.0,
        "arc_replace": 3.0,
        "arc_tangent_sigmas": 3.0,
        "arc_chi2": True,
    },
    "arcs_tangent_tight": {
        "arc_refit": True,
        "arc_sigmas": 3.0,
        "arc_replace": math.inf,
        "arc_tangent_sigmas": 0.5,
        "arc_chi2": False,
    },
}
# sixteenth round: the current default's arcs with short stepped arcs (arc_short_steps)
CONFIGS["arcs_consistent_short_steps"] = {**CONFIGS["arcs_consistent"], "arc_short_steps": True}

# Dec 4: the averaging scanner's return threshold assumed anywhere in [0, 0.5] / any hit
CONFIGS["edge_hit_unknown"] = {"edge_hit_min": 0.0, "edge_hit_max": 0.5}
CONFIGS["edge_hit_any"] = {"edge_hit_min": 0.0, "edge_hit_max": 0.0}
# Dec 5: ... with the edge returns' range window following the assumed threshold
CONFIGS["edge_hit_any_window"] = {**CONFIGS["edge_hit_any"], "edge_hit_window": True}
CONFIGS["edge_hit_unknown_window"] = {**CONFIGS["edge_hit_unknown"], "edge_hit_window": True}


# Dec 5: the step split (compiled since: _fast_step_split) with the step read against the
# configured sigma, the sparse scans' pooled noise and every scan's (grid 59, the preset's
# since Dec 5: the "default" config runs it too; the off case is "step_split_off")
STEP = {"step_split": True, "step_noise_pool": False, "arc_short_steps": True}
CONFIGS["step_split"] = STEP
CONFIGS["step_split_off"] = {"step_split": False}
CONFIGS["step_split_pool"] = {**STEP, "step_noise_pool": True}
CONFIGS["step_split_batch"] = {**STEP, "step_noise_pool": "batch"}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_compiled_pipeline_equals_numpy_pipeline(stand, name):
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **CONFIGS[name]))
    fast, ref = _both(det, _scans(stand))
    assert len(ref) > 20  # the comparison covers real detections
    assert_same(fast, ref)


def test_compiled_pipeline_on_360_degree_scans_with_dropouts(stand):
    inc = math.radians(0.5)
    batch = _scans(stand, angle_min=-math.pi, angle_max=math.pi - inc, dropout=0.02)
    det = ScanTrunkDetector("stemmap")
    fast, ref = _both(det, batch)
    assert len(ref) > 40
    assert_same(fast, ref)


def test_compiled_pipeline_with_reversed_beam_order(stand):
    batch = _scans(stand)
    last = batch.angle_min + batch.angle_increment * (batch.n_beams - 1)
    rev = ScanBatch(
        batch.ranges[:, ::-1].copy(),
        batch.times,
        last,
        -batch.angle_increment,
        batch.range_min,
        batch.range_max,
    )
    for det in (
        ScanTrunkDetector("stemmap"),
        ScanTrunkDetector.from_preset(
            "stemmap", split_corners=True, corner_depth=0.015, corner_depth_convex=0.03
        ),
        ScanTrunkDetector.from_preset("stemmap", gap_splits=2, min_depth=0.01),
    ):
        fast, ref = _both(det, rev)
        assert len(ref) > 20
        assert_same(fast, ref)
        # and the same trunks as the forward scans (fit ends swap with the bearing order)
        fwd, _ = _both(det, batch)
        assert len(fwd) == len(fast)


def test_public_api_uses_the_compiled_path_and_single_equals_batch(stand):
    batch = _scans(stand)
    det = ScanTrunkDetector("stemmap")
    assert det._compiled(None, None)
    assert not ScanTrunkDetector(DetectorConfig.preset("stemmap", fit_method="kasa"))._compiled(
        None, None
    )
    assert not det._compiled(0.01, None)  # tilt compensation runs the numpy pipeline
    for numpy_only in ({"refit_split": "gap"}, {"rms_noise_from_fit": 3.0}):
        assert not ScanTrunkDetector(DetectorConfig.preset("stemmap", **numpy_only))._compiled(
            None, None
        )
    whole = det.detect_batch(batch)
    _, ref = _both(det, batch)
    assert_same(whole, ref)
    for s in (0, 7, 23):
        one = det.detect(batch[s])
        sel = whole.select(whole.index == s)
        np.testing.assert_array_equal(one.radii, sel.radii)


def test_kernel_parameter_names_are_unique():
    assert len(set(_detect_fast.PARAM_NAMES)) == _detect_fast.N_PARAMS


def test_pairwise_sum_equals_numpy_reduceat():
    rng = np.random.default_rng(5)
    x = rng.normal(size=5000) * 1e3
    starts = np.r_[0, np.sort(rng.choice(np.arange(1, 5000), 60, replace=False))]
    stops = np.r_[starts[1:], 5000]
    ref = np.add.reduceat(x, starts)
    mine = np.array([_detect_fast._seg_sum(x, a, b) for a, b in zip(starts, stops, strict=True)])
    np.testing.assert_array_equal(mine, ref)  # same summation order, bit for bit


def test_algebraic_floor_is_the_kasa_minimum_and_bounds_every_circle() -> None:
    """The pre-fit reject rests on two facts: ``_algebraic_floor`` is the least-squares minimum
    of ``sum (|p - c|^2 - r^2)^2`` over all circles (checked against numpy's lstsq), so no
    circle scores below it; and ``(d - r)^2 = (d^2 - r^2)^2 / (d + r)^2``, so the orthogonal
    cost of a circle with every ``d_i + r <= M`` is at least floor / M^2."""
    rng = np.random.default_rng(5)
    for trial in range(200):
        n = int(rng.integers(4, 40))
        if trial % 2:  # noisy arcs (trunk-like)
            c = rng.uniform(-5, 5, 2)
            r = rng.uniform(0.05, 0.5)
            t = rng.uniform(0, rng.uniform(0.5, 3.0), n)
            p = c + (r + rng.normal(0, 0.01, n))[:, None] * np.c_[np.cos(t), np.sin(t)]
        else:  # clutter-like blobs
            p = rng.uniform(-1, 1, (n, 2)) * rng.uniform(0.05, 1.0) + rng.uniform(-5, 5, 2)
        px, py = np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1])
        floor = _detect_fast._algebraic_floor(px, py, 0, n)
        A = np.c_[px, py, np.ones(n)]
        z = px**2 + py**2
        sol, *_ = np.linalg.lstsq(A, z, rcond=None)
        ref = float(np.sum((A @ sol - z) ** 2))
        assert floor == pytest.approx(ref, rel=1e-6, abs=1e-15)
        for _ in range(5):  # any circle: algebraic cost >= floor, orthogonal >= floor / M^2
            cc = rng.uniform(-6, 6, 2)
            rr = rng.uniform(0.01, 2.0)
            d = np.hypot(px - cc[0], py - cc[1])
            assert np.sum((d**2 - rr**2) ** 2) >= floor * (1 - 1e-9)
            m = float(np.max(d + rr))
            assert np.sum((d - rr) ** 2) >= floor / m**2 * (1 - 1e-9)


def test_inplace_median_equals_numpy_median():
    # the scan-noise estimate's quickselect must return np.median exactly (odd and even counts,
    # ties), or the compiled path would drift from the numpy reference
    rng = np.random.default_rng(0)
    for t in range(2000):
        m = int(rng.integers(1, 80))
        v = rng.normal(size=m)
        if t % 3 == 0:
            v = np.round(v, 1)  # ties
        assert _detect_fast._median_inplace(v.copy(), m) == np.median(v)


def test_kernel_codes_and_parameter_positions_match_their_names():
    # the kernels read reason codes and parameters by position (numba has no name lookup)
    from stemmap.scan import _fast_candidates as fc
    from stemmap.scan.plausibility import REASONS

    codes = {"depth": fc._DEPTH, "fit_failed": fc._FIT_FAILED, "radius": fc._RADIUS}
    codes |= {"radius_width_ratio": fc._RATIO, "centre_in_front": fc._CENTRE, "rms": fc._RMS}
    for name, code in codes.items():
        assert REASONS[code] == name
    assert fc._PREFIT < 0  # never a REASONS code
    used = {
        "wrap": 3, "occlusion_margin": 10, "min_points": 16, "min_points_partial": 17,
        "max_points": 18, "min_width": 19, "max_width": 20, "min_depth": 21,
        "min_curvature": 22, "max_curvature": 23, "reject_straight": 24, "straight_chi2": 25,
        "straight_ratio": 26, "straight_min_points": 27, "drop_partial": 28, "sigma": 29,
        "sigma_rel": 30, "fit_sigma_given": 31, "min_radius": 32, "max_radius": 33,
        "max_radius_width_ratio": 34, "max_rms_sigma": 35, "divergence": 36,
        "use_silhouette": 37, "range_model": 38, "angle_increment": 39, "sigma_from_data": 40,
        "roughness_max_factor": 41, "rms_robust": 42, "bark_roughness": 43, "corner_span": 45,
        "corner_depth": 46, "corner_depth_convex": 47, "corner_sigmas": 48,
        "straight_depth_sigmas": 52, "refit_corners": 56, "refit_validate": 57,
    }  # fmt: skip
    for name, i in used.items():
        assert _detect_fast.PARAM_INDEX[name] == i, name


def test_squared_corner_pretest_never_misses_a_corner():
    # the split's pre-test may say "maybe" wrongly, never "no" where segment_corners finds one
    from stemmap.scan._corners import may_have_corner, segment_corners

    rng = np.random.default_rng(3)
    hits = 0
    for _ in range(3000):
        n = int(rng.integers(3, 30))
        t = np.linspace(-1.0, 1.0, n)
        # an arc or a notched outline 2-8 m away, cm-scale noise
        y = rng.uniform(2.0, 8.0) + rng.choice([-1.0, 1.0]) * 0.05 * np.abs(t)
        x = rng.uniform(0.2, 1.0) * t
        y = y + rng.normal(0.0, rng.uniform(0.0, 0.02), n)
        px, py = np.ascontiguousarray(x), np.ascontiguousarray(y)
        span = int(rng.integers(1, 3))
        thr = float(rng.uniform(0.005, 0.04))
        d, corner = np.empty(n), np.empty(n, dtype=bool)
        found = segment_corners(px, py, 0, n, span, thr, d, corner)
        hits += found > 0
        assert may_have_corner(px, py, 0, n, span, thr) or found == 0
    assert hits > 100  # corners were present in the draws


@pytest.mark.parametrize("pool", [True, "batch"])
def test_compiled_step_split_equals_numpy_at_3_cm_noise(stand, pool):
    # 3 cm range noise: candidates fail the RMS test and their largest steps are read
    # against the (pooled) noise; the step split must change detections (path exercised)
    batch = _scans(stand, range_noise=0.03)
    cfg = DetectorConfig.preset("stemmap", **{**STEP, "step_noise_pool": pool})
    det = ScanTrunkDetector(cfg)
    assert det._compiled(None, None)
    fast, ref = _both(det, batch)
    assert_same(fast, ref)
    plain = _both(ScanTrunkDetector(dataclasses.replace(cfg, step_split=False)), batch)[1]
    assert len(ref) > len(plain)


def test_thin_beams_run_numpy_with_trims():
    """The preset's first-echo trims exist only on the numpy path: a thin beam with them must
    not dispatch to the compiled kernel (which would skip them), and without them it does."""
    trims = ScanTrunkDetector(DetectorConfig.preset("stemmap", beam_divergence_deg=0.0))
    assert not trims._compiled(None, None)
    assert ScanTrunkDetector(DetectorConfig.preset("stemmap", **CONFIGS["thin_beams"]))._compiled(
        None, None
    )
