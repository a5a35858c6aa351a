"""The first-echo DBH standard error (``dbh_sd_noise``, ``dbh_sd_outline``; issue 11, Dec 5,
"First-echo DBH standard error" in docs/algorithms/scan-detection.md).

The reported covariance of a first-echo ``ours`` fit has its radius row and column scaled to
the range noise present (the measured noise or the fit's own residual scale, where either
exceeds the noise the fit weighted its returns by) and an outline term added to ``C_rr``; the
detections themselves (positions, diameters, returns, quality) do not change. The scene: the
20 cm disc of ``test_max_dbh_sd`` (the benchmark's first-echo virtual scanner, 0.25 deg, 40
bearings, one scan each, so no scan has a noise estimate of its own and the tests read the
configured 1 cm) with 3 cm of range noise."""

import math
from dataclasses import replace

import numpy as np
import pytest
from tests.scan.test_max_dbh_sd import STEP, V, _batch, _on_disc

from stemmap.errors import ConfigError
from stemmap.eval.real_slices import noisy_batch
from stemmap.scan._segment_fits import reported_covs
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

OFF = {
    "dbh_sd_noise": False,
    "dbh_sd_outline": 0.0,
    "centre_sd_along": 0.0,
    "centre_sd_across": 0.0,
}


def _det(model: str = "nearest", **extra) -> ScanTrunkDetector:
    foot = {"beam_footprint_deg": STEP} if model == "nearest" else {}
    return ScanTrunkDetector(DetectorConfig.preset("stemmap", **foot, **extra))


def test_the_preset_turns_it_on_and_the_dataclass_leaves_it_off():
    preset = DetectorConfig.preset("stemmap")
    assert preset.dbh_sd_noise and preset.dbh_sd_outline == pytest.approx(0.013)
    plain = DetectorConfig()
    assert not plain.dbh_sd_noise and plain.dbh_sd_outline == 0.0
    with pytest.raises(ConfigError, match="dbh_sd_outline"):
        DetectorConfig(dbh_sd_outline=-0.01)


def test_reported_covs_scale_the_radius_and_add_the_outline():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 3, 3))
    covs = 1e-4 * (a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3))
    fit = np.array([0.01, 0.01, 0.01, 0.01])
    meas = np.array([0.03, 0.005, 0.01, np.nan])  # k = 3, 1 (never below), 1, 1
    rms = np.zeros(4)
    n = np.full(4, 8)
    out = reported_covs(covs, fit, meas, rms, n, 0.02)
    k = np.array([3.0, 1.0, 1.0, 1.0])
    assert np.allclose(out[:, :2, :2], covs[:, :2, :2])  # the centre's block is the fit's
    assert np.allclose(out[:, 2, :2], k[:, None] * covs[:, 2, :2])
    assert np.allclose(out[:, 2, 2], k * k * covs[:, 2, 2] + 0.01**2)
    assert np.all(np.linalg.eigvalsh(out) > 0)  # still a covariance
    # the residual scale over n - 3 degrees of freedom: RMS 2 cm of 8 returns -> 2.53 cm
    res = reported_covs(covs[:1], fit[:1], fit[:1], np.array([0.02]), n[:1], 0.0)
    assert res[0, 2, 2] == pytest.approx(covs[0, 2, 2] * (2.0 * math.sqrt(8 / 5)) ** 2)


def test_the_detections_are_the_same_and_only_the_std_changes():
    batch, _ = _batch(2.5)
    # the centre's options off (test_centre_cov_first_echo.py): the DBH options alone
    on = _det(centre_sd_along=0.0, centre_sd_across=0.0).detect_batch(batch)
    off = _det(**OFF).detect_batch(batch)
    assert len(on) == len(off) > 0
    for f in ("centers", "radii", "n_points", "arc_deg", "widths", "quality", "index"):
        assert np.array_equal(getattr(on, f), getattr(off, f)), f
    assert np.array_equal(on.covs[:, :2, :2], off.covs[:, :2, :2])
    # the reported DBH std never falls below the fit's own, plus at least the outline term
    assert np.all(on.covs[:, 2, 2] >= off.covs[:, 2, 2] + 0.25 * 0.013**2 - 1e-12)


def _redraw(noisy: np.ndarray, seed: int) -> np.ndarray:
    """Another 3 cm noise draw of the scene (the noise-free ranges are ``_batch``'s without
    its draw: re-scanned here)."""
    from stemmap.eval.real_slices import virtual_scans

    a = np.linspace(-math.pi, math.pi, 3000, endpoint=False)
    xy = np.column_stack((0.1 * np.cos(a), 0.1 * np.sin(a)))
    b = np.linspace(0.0, 2.0 * math.pi, V, endpoint=False)
    vp = 2.5 * np.column_stack((np.cos(b), np.sin(b)))
    ranges, _ = virtual_scans(
        xy, np.zeros(a.size, dtype=np.int64), vp, resolution_deg=STEP, model="nearest",
        centers=np.zeros((1, 2)),
    )  # fmt: skip
    return noisy_batch(ranges, STEP, 0.03, np.random.default_rng(100 + seed)).ranges


def test_at_3_cm_the_std_states_the_error():
    # the fit weights the returns by the tests' 1 cm (no scan has an estimate of its own) and
    # its covariance stated a third of the error (measured: median |z| 1.64 at 0.25 deg over
    # 2.5 / 5 / 9 m, benchmarks/first_echo_dbh_z.py --disc); scaled to the batch's measured
    # ~3 cm the disc's median |z| is 0.57-0.82 per step (0.674 calibrated), here 2.5 m only
    batch, rel = _batch(2.5)
    z = {}
    for name, extra in (("off", OFF), ("noise", {"dbh_sd_outline": 0.0})):
        err, sd = [], []
        for seed in range(4):  # four noise draws of the 40 views (the RMS test keeps ~1 in 4)
            noisy = replace(batch, ranges=_redraw(batch.ranges, seed))
            obs = _det(**extra).detect_batch(noisy)
            k = _on_disc(obs, rel)
            k = k[k >= 0]
            err.extend(2.0 * obs.radii[k] - 0.2)
            sd.extend(2.0 * np.sqrt(obs.covs[k, 2, 2]))
        assert len(err) >= V // 2
        z[name] = float(np.median(np.abs(err) / np.array(sd)))
    assert z["off"] > 1.2  # the fit's own: too small
    assert 0.3 < z["noise"] < 1.0  # at the noise present: about calibrated


def test_an_averaging_scanner_keeps_the_fit_covariance():
    # the averaging edge model (the compiled path, the simulator, Victoria Park-class SICKs):
    # the option reads first-echo fits only, bit for bit (the averaging centre terms, which
    # carry the outline term to the centre, off in both: test_centre_cov_averaging.py)
    batch, _ = _batch(2.5, "averaging")
    own = {"centre_sd_footprint": 0.0, "centre_sd_across_averaging": 0.0, "dbh_sd_footprint": 0}
    on = _det("averaging", **own).detect_batch(batch)
    off = _det("averaging", **OFF, **own).detect_batch(batch)
    assert np.array_equal(on.covs, off.covs) and np.array_equal(on.radii, off.radii)
