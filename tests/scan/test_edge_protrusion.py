"""A first-echo edge return that caught a bark flake (``edge_protrusion``, issue 11, Dec 4).

A first-echo beam returns from whatever is nearest in its footprint: at a real stem's
silhouette the last beam that returns may have caught only a flake, twig or stub standing out
of the mean circle, and the fit's tangent prior (the tangent anywhere in the edge footprint)
then widens the stem by up to a beam. These tests scan a 30 cm disc with the benchmark's own
first-echo virtual scanner (:func:`stemmap.eval.real_slices.virtual_scans`, 0.5 deg) from 24
bearings a fraction of a beam apart, with and without a 2 cm flake at one silhouette."""

import functools
import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.eval.real_slices import noisy_batch, virtual_scans
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.features import first_echo_edge_prior
from stemmap.scan.segment import build_segments, extract_points, range_jump_breaks

R = 0.15  # trunk radius, m
STEP = 0.5  # degrees


def _scan(d: float, bearing: float, flake: float):
    """A noise-free first-echo scan of the disc seen from ``d`` m along ``bearing`` (radians,
    from the trunk), a flake of ``flake`` m (1 cm wide) on the outline at one tangent point."""
    a = np.linspace(-math.pi, math.pi, 2000, endpoint=False)
    xy = np.column_stack((R * np.cos(a), R * np.sin(a)))
    lab = np.zeros(a.size, dtype=np.int64)
    if flake > 0:
        phi = bearing + math.acos(R / d) + np.radians(np.linspace(-1.0, 1.0, 9))
        rad = R + np.linspace(0.002, flake, 15)
        f = np.array([[r * math.cos(p), r * math.sin(p)] for p in phi for r in rad])
        xy = np.vstack((xy, f))
        lab = np.concatenate((lab, np.full(f.shape[0], -1)))  # not the trunk's reference
    sensor = np.array([d * math.cos(bearing), d * math.sin(bearing)])
    return first_echo_scan(xy, lab, sensor)[0], -sensor


def first_echo_scan(xy: np.ndarray, lab: np.ndarray, sensor: np.ndarray):
    """The benchmark's noise-free first-echo scan (0.5 deg) of points ``xy`` (labels
    ``lab``: 0 the trunk centred at the origin, -1 anything else) from ``sensor``: the batch
    and each beam's hit label."""
    ranges, hit = virtual_scans(
        xy - sensor,
        lab,
        np.zeros((1, 2)),
        resolution_deg=STEP,
        model="nearest",
        centers=-sensor[None, :],
    )
    return noisy_batch(ranges, STEP, 0.0, np.random.default_rng(0)), hit


@functools.cache
def _errors(d: float, flake: float, edge_protrusion: float = 0.0) -> np.ndarray:
    """DBH error (cm) of the first-echo ``stemmap`` fit over 24 bearings within 7 beams, the
    fit at the tests' sigma (``fit_noise_floor`` 0: the preset of Dec 4, which this option was
    measured on; with the preset's 3 mm since Dec 5 the flaked stem reads +0.46 / +0.52 cm on
    average at 3 / 6 m, the clean one -0.10 / -0.29 cm, measured)."""
    cfg = DetectorConfig.preset(
        "stemmap", beam_footprint_deg=STEP, edge_protrusion=edge_protrusion, fit_noise_floor=0.0
    )
    det = ScanTrunkDetector(cfg)
    out = []
    for k in range(24):
        batch, centre = _scan(d, 0.3 + k * math.radians(STEP) * 7.3 / 24, flake)
        obs = det.detect_batch(batch)
        assert len(obs) == 1
        assert np.hypot(*(obs.centers[0] - centre)) < 0.05
        out.append(200.0 * (obs.radii[0] - R))
    out_a = np.array(out)
    out_a.flags.writeable = False  # cached
    return out_a


@pytest.mark.parametrize("d", [3.0, 6.0])
def test_a_flake_at_the_silhouette_widens_the_default_fit_and_the_option_takes_it_back(d):
    plain = _errors(d, 0.0)
    flake = _errors(d, 0.02)
    # the flake's beam returns: the default reads the stem wider (+1.4 cm at 3 m, +0.7 cm at
    # 6 m on average, against -0.4 / -0.7 cm without the flake)
    assert flake.mean() > plain.mean() + 1.0
    on = _errors(d, 0.02, edge_protrusion=0.02)
    # with the tangent allowed 2 cm inside the edge footprint the flake's pull is gone
    # (measured -0.01 / -0.16 cm)
    assert abs(on.mean()) < 0.3
    assert flake.mean() - on.mean() > 0.75


@pytest.mark.parametrize("d", [3.0, 6.0])
def test_on_a_clean_circle_the_option_costs_a_bounded_negative_bias(d):
    # what the option pays where the outline is the circle (FORTLS's synthetic rings): the
    # tangent prior reaches inside the edge footprint, so the mean can only move down, by
    # less than the flake it allows for (measured -0.14 cm at 3 m, -0.46 cm at 6 m)
    off = _errors(d, 0.0)
    on = _errors(d, 0.0, edge_protrusion=0.02)
    assert on.mean() <= off.mean() + 1e-9
    assert on.mean() > off.mean() - 0.6


def test_the_prior_spans_the_edge_footprint_and_reaches_the_protrusion_inside():
    ranges = np.full((1, 720), np.inf)
    ranges[0, 100:106] = [3.0, 2.97, 2.96, 2.96, 2.97, 3.0]
    ranges[0, 300:305] = 6.0
    ang = -math.pi + math.radians(STEP) * np.arange(720)
    pts = extract_points(np.where(np.isfinite(ranges), ranges, np.nan), ang, math.radians(STEP))
    segs = build_segments(pts, range_jump_breaks(pts, 0.2))
    assert len(segs) == 2
    assert np.all(np.isnan(first_echo_edge_prior(segs, 0.0)))
    prior = first_echo_edge_prior(segs, 0.02)
    width = prior[:, :, 1] * math.sqrt(12.0)  # uniform interval of that std
    lo = prior[:, :, 0] - width / 2.0
    hi = prior[:, :, 0] + width / 2.0
    # outward end: the far side of the edge footprint (one beam spacing beyond the return)
    np.testing.assert_allclose(hi, 1.0, atol=1e-12)
    # inward: 2 cm at the edge return's range, in beam spacings
    s = 0.02 / (np.array([[3.0, 3.0], [6.0, 6.0]]) * math.radians(STEP))
    np.testing.assert_allclose(lo, -s, rtol=1e-12)
    with pytest.raises(ConfigError):
        first_echo_edge_prior(segs, -0.01)


def test_averaging_fits_and_the_compiled_path_are_left_alone():
    # the option is about first echoes: with the preset's averaging edge model (no footprint
    # correction) it changes nothing, and that detector stays on the compiled path
    cfg = DetectorConfig.preset("stemmap", edge_protrusion=0.02)
    assert ScanTrunkDetector(cfg)._compiled(None, None)
    batch, _ = _scan(4.0, 0.3, 0.02)
    a = ScanTrunkDetector(DetectorConfig.preset("stemmap")).detect_batch(batch)
    b = ScanTrunkDetector(cfg).detect_batch(batch)
    np.testing.assert_array_equal(a.radii, b.radii)
    np.testing.assert_array_equal(a.centers, b.centers)


@pytest.mark.parametrize("bad", [-0.01, math.inf, math.nan])
def test_the_protrusion_must_be_a_finite_height(bad):
    with pytest.raises(ConfigError, match="edge_protrusion"):
        DetectorConfig.preset("stemmap", edge_protrusion=bad)
