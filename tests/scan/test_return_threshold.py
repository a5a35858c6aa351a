"""The averaging scanner's return threshold (Dec 4): the virtual SICK-class scanner of
``stemmap.eval.real_slices.virtual_scans`` (``min_hit_fraction``, ``beam_profile``) and the
detector's assumed threshold interval (``DetectorConfig.edge_hit_min`` / ``edge_hit_max``,
``stemmap.scan.features.edge_default_prior``)."""

import math

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.real_slices import virtual_scans
from stemmap.scan.config import ConfigError, DetectorConfig
from stemmap.scan.detect import ScanTrunkDetector
from stemmap.scan.features import edge_default_prior
from stemmap.types import ScanBatch

RES = 0.25  # degrees: one beam step = the 0.25-degree footprint
R, D = 0.15, 3.0
_PHI = np.linspace(0.0, 2.0 * math.pi, 20000, endpoint=False)
DISC = np.column_stack((D + R * np.cos(_PHI), R * np.sin(_PHI)))
LABELS = np.zeros(DISC.shape[0], dtype=np.int64)
# 200 vantage points within 0.5 m of the origin: every phase of the beams against the disc
VANTAGES = np.random.default_rng(0).uniform(-0.5, 0.5, (200, 2))


def _excess(**kw):
    """Mean apparent angular width of the disc minus its true silhouette, in footprints."""
    r, hit = virtual_scans(
        DISC,
        LABELS,
        VANTAGES,
        resolution_deg=RES,
        model="averaging",
        centers=[[D, 0.0]],
        **kw,
    )
    assert np.array_equal(np.isfinite(r), hit == 0)  # no return, no trunk: no partial credit
    d = np.hypot(D - VANTAGES[:, 0], VANTAGES[:, 1])
    true = 2.0 * np.degrees(np.arcsin(R / d))
    return float(np.mean(np.isfinite(r).sum(axis=1) * RES - true) / 0.25)


def test_the_default_is_any_sub_ray_of_twenty_five():
    # every benchmark number before Dec 4 was measured with "any sub-ray" (of 5 until Dec 5,
    # of 25 since: sim-eval.md, "Mixed pixels: one footprint model"): the default must be it
    a = virtual_scans(DISC, LABELS, VANTAGES[:5], resolution_deg=0.5, model="averaging")
    b = virtual_scans(
        DISC,
        LABELS,
        VANTAGES[:5],
        resolution_deg=0.5,
        model="averaging",
        min_hit_fraction=0.0,
        beam_profile="uniform",
        sub_rays=25,
    )
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


@pytest.mark.parametrize("n_sub", [5, 20])
@pytest.mark.parametrize("q", [0.0, 0.25, 0.5, 0.75, 1.0])
def test_apparent_width_is_the_silhouette_plus_one_minus_twice_the_threshold(q, n_sub):
    # A beam returns when at least ceil(q n) of its n sub-rays hit, and a sub-ray hits when the
    # disc touches any part of its sub-cell: it returns when the covered share of the
    # footprint exceeds q_eff = (ceil(q n) - 1) / n (0 for any sub-ray), so the disc looks
    # wider than its silhouette by (1 - 2 q_eff) footprints on average over beam phases.
    # Tolerance 0.1 footprint: the mean over 200 vantage points of a width quantised to one
    # beam has a standard error of ~0.03 (0.1 = 3 of them); the point discs of the sampled
    # surface (20 000 points) move it by ~0.04 (measured: 0.965 for any sub-ray).
    q_eff = 0.0 if q == 0 else (math.ceil(q * n_sub - 1e-9) - 1) / n_sub
    assert _excess(min_hit_fraction=q, sub_rays=n_sub) == pytest.approx(1 - 2 * q_eff, abs=0.1)


@pytest.mark.parametrize("profile", ["uniform", "gaussian"])
def test_the_apparent_width_falls_as_the_threshold_rises(profile):
    w = [_excess(min_hit_fraction=q, sub_rays=20, beam_profile=profile) for q in (0, 0.25, 0.5)]
    assert w[0] > w[1] + 0.15 > w[2] + 0.3
    # any sub-ray: the footprint's full width is added whatever its energy profile
    assert w[0] == pytest.approx(1.0, abs=0.1)


def test_a_gaussian_beam_at_half_its_energy_returns_where_its_axis_is_on_the_disc():
    # the profile is symmetric: half the energy hits when the silhouette edge crosses the axis,
    # so the apparent width is the silhouette's (+ up to one sub-ray of partial credit)
    assert 0.0 <= _excess(min_hit_fraction=0.5, sub_rays=40, beam_profile="gaussian") < 0.15


def test_threshold_arguments_are_checked():
    with pytest.raises(InputError):
        virtual_scans(DISC, LABELS, VANTAGES[:1], resolution_deg=RES, min_hit_fraction=1.5)
    with pytest.raises(InputError):
        virtual_scans(DISC, LABELS, VANTAGES[:1], resolution_deg=RES, beam_profile="flat")


@pytest.mark.parametrize("h", [0.125, 0.25, 0.5])
def test_edge_prior_covers_exactly_the_tangents_every_threshold_allows(h):
    # footprint w = 2 h beams; threshold q: the edge beam (axis 0) returned, the next (axis 1)
    # did not, so the tangent T is in (0 + (q - 1/2) w, 1 + (q - 1/2) w]
    for lo, hi in ((0.5, 0.5), (0.0, 0.0), (0.0, 0.5), (0.2, 0.7)):
        off, std = edge_default_prior(h, lo, hi)
        half = 0.5 * math.sqrt(12.0) * std  # the uniform interval the prior stands for
        w = 2.0 * h
        assert off - half == pytest.approx((lo - 0.5) * w)
        assert off + half == pytest.approx(1.0 + (hi - 0.5) * w)
    assert edge_default_prior(h, 0.5, 0.5) == pytest.approx((0.5, 1 / math.sqrt(12.0)))


def test_config_checks_the_threshold_interval():
    with pytest.raises(ConfigError):
        DetectorConfig.preset("stemmap", edge_hit_min=0.6, edge_hit_max=0.5)
    with pytest.raises(ConfigError):
        DetectorConfig.preset("stemmap", edge_hit_min=-0.1)


def _disc_bias(min_hit_fraction, edge):
    """Mean DBH error (cm) of the stemmap preset (averaging edge model, 0.25 deg footprint)
    over virtual noise-free 0.5-degree scans of perfect 30 cm discs at 3-7 m."""
    rng = np.random.default_rng(5)
    errs = []
    for d in (3.0, 5.0, 7.0):
        disc = np.column_stack((d + R * np.cos(_PHI), R * np.sin(_PHI)))
        vp = rng.uniform(-0.3, 0.3, (40, 2))
        r, _ = virtual_scans(
            disc,
            LABELS,
            vp,
            resolution_deg=0.5,
            model="averaging",
            centers=[[d, 0.0]],
            min_hit_fraction=min_hit_fraction,
            sub_rays=20,
        )
        batch = ScanBatch(
            ranges=r,
            times=np.arange(r.shape[0], dtype=np.float64),
            angle_min=-math.pi,
            angle_increment=math.radians(0.5),
            range_max=30.0,
        )
        cfg = DetectorConfig.preset("stemmap", edge_hit_min=edge[0], edge_hit_max=edge[1])
        obs = ScanTrunkDetector(cfg).detect_batch(batch)
        assert len(obs) >= 0.95 * r.shape[0]
        errs.append(200.0 * obs.radii - 2 * 100.0 * R)
    return float(np.mean(np.concatenate(errs)))


def test_the_assumed_threshold_moves_the_dbh_as_the_scanner_s_does():
    # The tangent prior of the fit assumes where a beam stops returning; on a scanner with
    # that threshold the diameter of a perfect disc is (nearly) unbiased and on the other it
    # is off by a large part of the footprint's width at the range (0.25 deg x 5 m = 2.2 cm).
    # An interval [0, 0.5] lies between the two on both scanners (centred).
    half_on_any = _disc_bias(0.0, (0.5, 0.5))
    any_on_any = _disc_bias(0.0, (0.0, 0.0))
    half_on_half = _disc_bias(0.5, (0.5, 0.5))
    any_on_half = _disc_bias(0.5, (0.0, 0.0))
    unk_on_any = _disc_bias(0.0, (0.0, 0.5))
    unk_on_half = _disc_bias(0.5, (0.0, 0.5))
    assert abs(any_on_any) < 0.5 and abs(half_on_half) < 0.5
    assert half_on_any > any_on_any + 0.5
    assert any_on_half < half_on_half - 0.5
    assert any_on_any < unk_on_any < half_on_any
    assert any_on_half < unk_on_half < half_on_half


def _disc_errors(min_hit_fraction, dist, diam, overrides, n=40):
    """DBH errors (cm) of the stemmap preset with ``overrides`` on virtual noise-free 0.25-degree
    averaging scans (20 sub-rays) of a perfect disc from ``n`` vantage points, every beam phase."""
    rng = np.random.default_rng(7)
    r_disc = diam / 2.0
    disc = np.column_stack((dist + r_disc * np.cos(_PHI), r_disc * np.sin(_PHI)))
    vp = np.column_stack((rng.uniform(-0.05, 0.05, n), rng.uniform(-0.1, 0.1, n)))
    r, _ = virtual_scans(
        disc,
        LABELS,
        vp,
        resolution_deg=RES,
        model="averaging",
        centers=[[dist, 0.0]],
        min_hit_fraction=min_hit_fraction,
        sub_rays=20,
    )
    batch = ScanBatch(
        ranges=r,
        times=np.arange(r.shape[0], dtype=np.float64),
        angle_min=-math.pi,
        angle_increment=math.radians(RES),
        range_max=30.0,
    )
    obs = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides)).detect_batch(batch)
    assert len(obs) == n  # one detection per scan, the disc
    return 200.0 * obs.radii - 100.0 * diam


def test_the_edge_range_window_takes_the_rest_of_the_bias_off_a_low_threshold():
    # edge_hit_window (Dec 5): with an assumed threshold below half, the tangent prior moves
    # the silhouette, but a half-footprint range window still reads an edge sliver's nearer
    # range as a wider circle. On an any-hit scanner at 10 m (40 and 60 cm discs, where the
    # edge slivers weigh most: docs/algorithms/scan-detection.md, "The averaging edge bias
    # against textbook Kasa", measured +0.6 to +1.5 cm without the window, within 0.6 cm with
    # it) the window must cut the mean error, by at least 0.5 cm for the interval [0, 0.5].
    def bias(edge, window):
        kw = {"edge_hit_min": edge[0], "edge_hit_max": edge[1], "edge_hit_window": window}
        e = np.concatenate([_disc_errors(0.0, 10.0, diam, kw) for diam in (0.4, 0.6)])
        return float(np.mean(e))

    assert abs(bias((0.0, 0.0), True)) < abs(bias((0.0, 0.0), False))
    assert abs(bias((0.0, 0.5), True)) < abs(bias((0.0, 0.5), False)) - 0.5


def test_the_edge_range_window_is_a_no_op_at_the_half_threshold():
    # the preset assumes half the footprint: the window is the half footprint already
    a = _disc_errors(0.0, 8.0, 0.4, {}, n=20)
    b = _disc_errors(0.0, 8.0, 0.4, {"edge_hit_window": True}, n=20)
    np.testing.assert_array_equal(a, b)


def test_scene_scans_keeps_the_return_rule_with_a_ground_background():
    """``_real_scanning.scene_scans(background="ground")`` used to replace the return rule's
    arguments with the ground's: every threshold scanned as any-of-5. With the ground the
    rule must still narrow the disc as it does without."""
    from _real_scanning import ReturnRule, scene_scans
    from stemmap.eval.real_slices import RealSlice

    sl = RealSlice("disc", DISC, LABELS, [{"x": D, "y": 0.0, "diameter": 2 * R}], [], ground=None)
    vp = VANTAGES[:40]
    width = {}
    for bg in ("none", "ground"):
        for q in (0.0, 1.0):
            r, _ = scene_scans(
                sl, vp, "averaging", RES, bg, 0, return_rule=ReturnRule(q, "uniform", 20)
            )
            near = np.isfinite(r) & (r < D + 1.0)  # the disc, not the ground beyond it
            width[bg, q] = near.sum(axis=1).mean()
    for bg in ("none", "ground"):
        # any-hit vs full footprint: (1 - 2 q_eff) footprints, ~1.9 beams of 0.25 deg apart
        assert width[bg, 0.0] - width[bg, 1.0] > 1.5, width
    assert abs(width["ground", 1.0] - width["none", 1.0]) < 0.3, width
