"""The averaging (SICK-class) scanners' centre covariance (``centre_sd_footprint``,
``centre_sd_across_averaging``; issue 11, Dec 6, "Averaging centre covariance" in
docs/algorithms/scan-detection.md).

The reported centre variance along the line of sight gains the outline's radius error carried
as for a first echo and a share of the footprint's width at the trunk, and a term across it;
the radius entries and every detection stay as they were. The scene: the 20 cm disc of
``test_max_dbh_sd`` seen by the virtual averaging scanner from 2.5 and 9 m, 3 cm of noise."""

import math

import numpy as np
import pytest
from tests.scan.test_max_dbh_sd import _batch

from stemmap.errors import ConfigError
from stemmap.scan._centre_cov import averaging_centre_covs, averaging_report
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

F, C = 1.0, 0.007  # a footprint share and an across std (m)
# the radius terms (dbh_sd_footprint, on in the preset) off in both: the centre alone here
# (the radius: test_dbh_sd_averaging.py)
ON = {"centre_sd_footprint": F, "centre_sd_across_averaging": C, "dbh_sd_footprint": 0.0}
OFF = {"centre_sd_footprint": 0.0, "centre_sd_across_averaging": 0.0, "dbh_sd_footprint": 0.0}
FIELDS = ("centers", "radii", "n_points", "arc_deg", "widths", "quality", "index", "times")


def _det(**extra) -> ScanTrunkDetector:
    return ScanTrunkDetector(DetectorConfig.preset("stemmap", **extra))


def _quad(covs: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.einsum("ki,kij,kj->k", x, covs[:, :2, :2], x)


def _sight(centers: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = np.hypot(centers[:, 0], centers[:, 1])
    u = centers / d[:, None]
    return u, np.column_stack((-u[:, 1], u[:, 0])), d


def test_off_in_the_dataclass_and_bad_values_refused():
    plain = DetectorConfig()
    assert plain.centre_sd_footprint == 0.0 and plain.centre_sd_across_averaging == 0.0
    for name in ("centre_sd_footprint", "centre_sd_across_averaging"):
        with pytest.raises(ConfigError, match=name):
            DetectorConfig(**{name: -0.1})
        with pytest.raises(ConfigError, match=name):
            DetectorConfig(**{name: float("nan")})


def test_averaging_centre_covs_add_along_and_across_and_leave_the_radius():
    rng = np.random.default_rng(5)
    a = rng.normal(size=(6, 3, 3))
    covs = 1e-4 * (a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3))
    centers = rng.normal(size=(6, 2)) * 6.0
    outline, f, theta, c = 0.0085, 0.9, math.radians(0.25), 0.006
    out = averaging_centre_covs(covs, centers, outline, f, theta, c)
    u, w, d = _sight(centers)
    # along: the outline's share and f times the footprint's width at the trunk, in quadrature
    assert np.allclose(_quad(out, u), _quad(covs, u) + outline**2 + (f * theta * d) ** 2)
    assert np.allclose(_quad(out, w), _quad(covs, w) + c * c)
    assert np.allclose(np.einsum("ki,kij,kj->k", u, out[:, :2, :2], w), _quad_uw(covs, u, w))
    assert np.array_equal(out[:, 2, :], covs[:, 2, :])  # radius row and column as they were
    assert np.array_equal(out[:, :, 2], covs[:, :, 2])
    assert np.all(np.linalg.eigvalsh(out) > 0)  # still a covariance
    assert np.array_equal(averaging_centre_covs(covs, centers, 0.0, 0.0, theta, 0.0), covs)


def _quad_uw(m: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.einsum("ki,kij,kj->k", u, m[:, :2, :2], w)


@pytest.mark.parametrize("numpy_path", [False, True])
def test_the_along_sd_grows_as_configured_and_the_detections_stay(numpy_path):
    # numpy_path: a finite behind_sigmas takes the numpy pipeline (same option on and off)
    path = {"behind_sigmas": 3.0} if numpy_path else {}
    cfg = DetectorConfig.preset("stemmap", **path)
    assert ScanTrunkDetector(cfg)._compiled(None, None) is not numpy_path
    theta = math.radians(cfg.beam_divergence_deg)
    outline = 0.5 * cfg.centre_sd_along * cfg.dbh_sd_outline
    added = {}
    for dist in (2.5, 9.0):
        batch, _ = _batch(dist, "averaging")
        on = _det(**path, **ON).detect_batch(batch)
        off = _det(**path, **OFF).detect_batch(batch)
        assert len(on) == len(off) > 0
        for f in FIELDS:
            assert np.array_equal(getattr(on, f), getattr(off, f)), f
        assert np.array_equal(on.covs[:, 2, :], off.covs[:, 2, :])  # the DBH std as before
        u, w, d = _sight(on.centers)
        grow = _quad(on.covs, u) - _quad(off.covs, u)
        assert np.allclose(grow, outline**2 + (F * theta * d) ** 2, rtol=1e-9, atol=1e-15)
        assert np.allclose(_quad(on.covs, w) - _quad(off.covs, w), C * C, rtol=1e-9)
        added[dist] = float(np.median(np.sqrt(grow)))
    # the footprint's share grows with range: 1.1 / 3.9 cm of the footprint at 2.5 / 9 m
    assert added[9.0] > 1.5 * added[2.5]


def test_the_preset_turns_it_on_and_off_returns_the_fit_covariance_itself():
    preset = DetectorConfig.preset("stemmap", dbh_sd_footprint=0.0)
    assert preset.centre_sd_footprint == pytest.approx(0.7)
    assert preset.centre_sd_across_averaging == pytest.approx(0.006)
    rng = np.random.default_rng(2)
    centers = rng.normal(size=(4, 2)) * 5.0
    covs = np.tile(1e-4 * np.eye(3), (4, 1, 1))
    off = DetectorConfig.preset("stemmap", **OFF)
    assert averaging_report(off, centers, covs) is covs  # off: the fit's own, untouched
    assert averaging_report(preset, centers, covs) is not covs
    first = DetectorConfig.preset("stemmap", beam_footprint_deg=0.25)
    assert averaging_report(first, centers, covs) is covs  # first echo: its own terms


def test_a_first_echo_scanner_is_not_touched():
    # a first-echo scanner reads its own terms (centre_sd_along / _across), not these
    near, _ = _batch(2.5)
    foot = {"beam_footprint_deg": 0.25}
    a = _det(**foot, **ON).detect_batch(near)
    b = _det(**foot, **OFF).detect_batch(near)
    assert len(a) > 0 and np.array_equal(a.covs, b.covs)
