"""End returns behind a candidate's own circle (``behind_sigmas``, issue 11, thirteenth round):
a stub or branch behind the stem's silhouette, joined to the trunk's segment, is cut off and
the trunk is measured with its own radius; a trunk without one is left as it was."""

import math

import numpy as np
import pytest
from tests.scan.test_arcs import TRUNK, _scan

from stemmap.errors import ConfigError
from stemmap.scan._behind import tangent_range
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

ON = {"behind_sigmas": 2.0}
# a 6 cm stub just beyond the 30 cm trunk's silhouette edge, 8 cm deeper than the trunk's
# last return: the segmentation joins it (lidR's stub on the stem's flank,
# scan-detection-history.md, thirteenth round)
STUB = (5.10, 0.19, 0.03)


def _detect(circles, noise=0.0, seed=0, **overrides):
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides))
    return det.detect_batch(_scan(circles, noise, seed))


def test_tangent_range_is_where_the_sensor_grazes_the_circle():
    c = np.array([[5.0, 0.0], [0.0, -2.0], [0.1, 0.0]])
    t = tangent_range(c, np.array([3.0, 0.0, 0.5]))
    assert t[0] == pytest.approx(4.0)
    assert t[1] == pytest.approx(2.0)
    assert math.isnan(t[2])  # the sensor inside the circle


def test_a_stub_behind_the_silhouette_pulls_the_default_fit():
    obs = _detect([TRUNK, STUB])
    assert len(obs) == 1
    # the stub's return is fitted with the trunk: 2.4 cm too large a radius
    assert obs.radii[0] > TRUNK[2] + 0.02
    assert obs.n_points[0] == 8


@pytest.mark.parametrize(
    "stub", [STUB, (5.12, 0.18, 0.03), (5.15, 0.19, 0.04)], ids=["1 return", "deeper", "2 returns"]
)
def test_the_stub_is_cut_off_and_the_trunk_keeps_its_radius(stub):
    plain = _detect([TRUNK])
    obs = _detect([TRUNK, stub], **ON)
    assert len(obs) == 1
    assert obs.radii[0] == pytest.approx(TRUNK[2], abs=0.01)
    assert np.hypot(*(obs.centers[0] - TRUNK[:2])) < 0.01
    # exactly the trunk's own returns remain: the same fit as without the stub
    assert obs.n_points[0] == plain.n_points[0]
    assert obs.radii[0] == pytest.approx(plain.radii[0], abs=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_a_plain_trunk_is_left_as_it_was(seed):
    # the trunk's own edge returns lie nearer than its tangent points (noise aside): with 1 cm
    # of range noise and 2 sigma of margin nothing is trimmed on these draws
    off = _detect([TRUNK], noise=0.01, seed=seed)
    on = _detect([TRUNK], noise=0.01, seed=seed, **ON)
    assert len(on) == len(off)
    np.testing.assert_array_equal(on.n_points, off.n_points)
    np.testing.assert_allclose(on.radii, off.radii, rtol=0, atol=1e-9)


def test_a_stub_in_front_of_the_silhouette_is_not_cut():
    # the rule is one-sided: a return nearer than the tangent range may be the trunk's own
    # (the fillet of a branch coming towards the sensor is not trimmed by it)
    near = (4.95, 0.19, 0.03)
    assert np.array_equal(_detect([TRUNK, near]).radii, _detect([TRUNK, near], **ON).radii)


def test_the_option_runs_on_the_numpy_path_and_is_validated():
    assert not ScanTrunkDetector(DetectorConfig.preset("stemmap", **ON))._compiled(None, None)
    assert ScanTrunkDetector(DetectorConfig.preset("stemmap"))._compiled(None, None)
    for bad in (-1.0, math.nan):
        with pytest.raises(ConfigError, match="behind_sigmas"):
            DetectorConfig.preset("stemmap", behind_sigmas=bad)
