"""End returns outside a candidate's own circle (``stub_sigmas``, issue 11, seventeenth round):
a branch stub on the stem's flank, joined to the stem's arc, is cut off and the stem keeps the
fit of its own returns; a stem without one is left as it was."""

import math

import numpy as np
import pytest
from tests.scan.test_arcs import TRUNK, _scan
from tests.scan.test_stub_runs import GRID_67

from stemmap.errors import ConfigError
from stemmap.scan._stubs import first_echo
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

ON = {"stub_sigmas": 2.0}
# the test scans are thin beams: the fit without the averaging edge model (a first-echo fit)
THIN = {"beam_divergence_deg": 0.0}


def _stub(angle_deg, radius):
    """A branch stub of ``radius`` centred on the 30 cm trunk's outline, ``angle_deg`` from
    the direction trunk -> sensor (90: at the silhouette edge)."""
    phi = math.pi - math.radians(angle_deg)
    return (TRUNK[0] + TRUNK[2] * math.cos(phi), TRUNK[1] + TRUNK[2] * math.sin(phi), radius)


def _detect(circles, noise=0.0, seed=0, **overrides):
    # on the preset before grid 80 (grid 67), where the stub test was off
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **{**GRID_67, **THIN, **overrides}))
    return det.detect_batch(_scan(circles, noise, seed))


STUBS = [(75, 0.03), (80, 0.03), (80, 0.04), (85, 0.04)]


@pytest.mark.parametrize("stub", STUBS)
def test_a_flank_stub_pulls_the_default_fit(stub):
    obs = _detect([TRUNK, _stub(*stub)])
    assert len(obs) == 1
    # the stub's return (outside the circle, nearer than its tangent range) is fitted with
    # the trunk: the radius 2.3-3.2 cm too large
    assert obs.radii[0] > TRUNK[2] + 0.02
    assert obs.n_points[0] == _detect([TRUNK]).n_points[0] + 1


@pytest.mark.parametrize("stub", STUBS)
def test_the_stub_is_cut_off_and_the_trunk_keeps_its_own_fit(stub):
    plain = _detect([TRUNK])
    obs = _detect([TRUNK, _stub(*stub)], **ON)
    assert len(obs) == 1
    assert obs.radii[0] == pytest.approx(TRUNK[2], abs=0.005)
    # exactly the trunk's own returns remain: the same fit as without the stub
    assert obs.n_points[0] == plain.n_points[0]
    assert obs.radii[0] == pytest.approx(plain.radii[0], abs=1e-9)
    np.testing.assert_allclose(obs.centers, plain.centers, rtol=0, atol=1e-9)


@pytest.mark.parametrize("trunk", [TRUNK, (3.0, 0.0, 0.15), (2.0, 0.3, 0.10), (8.0, 0.5, 0.25)])
def test_a_clean_arc_is_left_as_it_was(trunk):
    # noise-free: every return on the circle, nothing outside it
    off, on = _detect([trunk]), _detect([trunk], **ON)
    np.testing.assert_array_equal(on.n_points, off.n_points)
    np.testing.assert_array_equal(on.radii, off.radii)
    # 1 cm range noise: the test allows for the noise and for the circle's own uncertainty
    # where it is extrapolated to the end, so a noisy edge return stays (seeds 0-5)
    for seed in range(6):
        off = _detect([trunk], noise=0.01, seed=seed)
        on = _detect([trunk], noise=0.01, seed=seed, **ON)
        np.testing.assert_array_equal(on.n_points, off.n_points)
        np.testing.assert_allclose(on.radii, off.radii, rtol=0, atol=1e-12)


def test_the_averaging_edge_model_keeps_its_mixed_pixels():
    # the preset's averaging edge model (beam_divergence_deg 0.25): an edge return is a mixed
    # pixel, outside the circle by construction; the option leaves such fits (and the
    # compiled path) alone
    cfg = DetectorConfig.preset("stemmap", **ON)
    assert not first_echo(cfg)
    assert ScanTrunkDetector(cfg)._compiled(None, None)
    batch = _scan([TRUNK, _stub(80, 0.04)])
    a = ScanTrunkDetector(DetectorConfig.preset("stemmap")).detect_batch(batch)
    b = ScanTrunkDetector(cfg).detect_batch(batch)
    np.testing.assert_array_equal(a.radii, b.radii)


def test_the_option_runs_on_the_numpy_path_and_is_validated():
    on = DetectorConfig.preset("stemmap", **{**GRID_67, **THIN, **ON})
    assert first_echo(on)
    assert first_echo(DetectorConfig.preset("stemmap", beam_footprint_deg=0.5))
    assert not ScanTrunkDetector(on)._compiled(None, None)
    assert ScanTrunkDetector(DetectorConfig.preset("stemmap", **GRID_67, **THIN))._compiled(
        None, None
    )
    for bad in (-1.0, math.nan):
        with pytest.raises(ConfigError, match="stub_sigmas"):
            DetectorConfig.preset("stemmap", stub_sigmas=bad)
