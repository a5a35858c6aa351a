"""The first-echo centre covariance (``centre_sd_along``, ``centre_sd_across``; issue 11, Dec 6,
"First-echo centre covariance" in docs/algorithms/scan-detection.md).

The reported covariance's centre block is scaled by the noise factor the DBH std already uses,
the outline's radius error moves the centre along the line of sight, and an across term is
added; the detections (positions, diameters, returns, quality) do not change. The scene: the
20 cm disc of ``test_max_dbh_sd`` at 2.5 m with 3 cm of range noise (no scan has a noise
estimate of its own: the fit weights by the configured 1 cm)."""

from dataclasses import replace

import numpy as np
import pytest
from tests.scan.test_dbh_sd_first_echo import _det, _redraw
from tests.scan.test_max_dbh_sd import _batch, _on_disc

from stemmap.errors import ConfigError
from stemmap.scan._centre_cov import centre_covs
from stemmap.scan.detect import DetectorConfig

ON = {"centre_sd_along": 1.3, "centre_sd_across": 0.004}  # the preset's
OFF = {"centre_sd_along": 0.0, "centre_sd_across": 0.0}


def test_the_preset_turns_it_on_and_the_dataclass_leaves_it_off():
    plain = DetectorConfig()
    assert plain.centre_sd_along == 0.0 and plain.centre_sd_across == 0.0
    preset = DetectorConfig.preset("stemmap")
    assert preset.centre_sd_along == pytest.approx(1.3)
    assert preset.centre_sd_across == pytest.approx(0.004)
    for name in ("centre_sd_along", "centre_sd_across"):
        with pytest.raises(ConfigError, match=name):
            DetectorConfig(**{name: -0.1})
        with pytest.raises(ConfigError, match=name):
            DetectorConfig(**{name: float("inf")})


def test_centre_covs_scale_and_add_along_and_across_the_line_of_sight():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 3, 3))
    covs = 1e-4 * (a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3))
    k = np.array([1.0, 2.0, 3.0, 1.5, np.nan])  # NaN: no factor (1)
    centers = rng.normal(size=(5, 2)) * 5.0
    b, g, c = 0.013, 1.3, 0.004
    out = centre_covs(covs, k, centers, b, g, c)
    kk = np.where(np.isfinite(k), k, 1.0)
    u = centers / np.hypot(centers[:, 0], centers[:, 1])[:, None]
    w = np.column_stack((-u[:, 1], u[:, 0]))
    q = (b / 2) ** 2

    def quad(m: np.ndarray, x: np.ndarray) -> np.ndarray:
        return np.einsum("ki,kij,kj->k", x, m[:, :2, :2], x)

    # along the line of sight: k^2 times the fit's, plus the outline's share (g b / 2)^2
    assert np.allclose(quad(out, u), kk**2 * quad(covs, u) + g * g * q)
    # across it: k^2 times the fit's plus c^2
    assert np.allclose(quad(out, w), kk**2 * quad(covs, w) + c * c)
    assert np.allclose(np.einsum("ki,kij,kj->k", u, out[:, :2, :2], w), kk**2 * quad_uw(covs, u, w))
    # the radius: C_rr as reported; the centre-radius covariance along u gains g q
    assert np.allclose(out[:, 2, 2], covs[:, 2, 2])
    assert np.allclose(np.sum(out[:, :2, 2] * u, 1), kk * np.sum(covs[:, :2, 2] * u, 1) + g * q)
    assert np.allclose(out, out.transpose(0, 2, 1))
    assert np.all(np.linalg.eigvalsh(out) > 0)  # still a covariance
    # nothing to add and k = 1: the same matrices
    same = centre_covs(covs, np.ones(5), centers, b, 0.0, 0.0)
    assert np.allclose(same, covs)


def quad_uw(m: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    return np.einsum("ki,kij,kj->k", u, m[:, :2, :2], w)


def test_the_detections_are_the_same_and_only_the_centre_block_changes():
    batch, _ = _batch(2.5)
    on = _det(**ON).detect_batch(batch)
    off = _det(**OFF).detect_batch(batch)
    assert len(on) == len(off) > 0
    for f in ("centers", "radii", "n_points", "arc_deg", "widths", "quality", "index"):
        assert np.array_equal(getattr(on, f), getattr(off, f)), f
    assert np.array_equal(on.covs[:, 2, 2], off.covs[:, 2, 2])  # the DBH std as before
    u = on.centers / np.hypot(on.centers[:, 0], on.centers[:, 1])[:, None]
    w = np.column_stack((-u[:, 1], u[:, 0]))
    for x, add in ((u, (1.3 * 0.013 / 2) ** 2), (w, 0.004**2)):
        v_on = np.einsum("ki,kij,kj->k", x, on.covs[:, :2, :2], x)
        v_off = np.einsum("ki,kij,kj->k", x, off.covs[:, :2, :2], x)
        assert np.all(v_on >= v_off + add - 1e-12)  # k >= 1 and the term on top


def test_at_3_cm_the_centre_covariance_states_the_error():
    # the fit's centre block at the configured 1 cm: median Mahalanobis distance 2.9 over four
    # noise draws (1.18 calibrated); at the noise present (the DBH std's factor, terms ~0)
    # 1.0; with the outline terms on top (a clean disc has no outline) 0.7
    batch, rel = _batch(2.5)
    med = {}
    for name, extra in (("off", OFF), ("noise", {**OFF, "centre_sd_along": 1e-9}), ("on", ON)):
        d2: list[float] = []
        for seed in range(4):
            noisy = replace(batch, ranges=_redraw(batch.ranges, seed))
            obs = _det(**extra).detect_batch(noisy)
            k = _on_disc(obs, rel)
            s = np.flatnonzero(k >= 0)
            e = obs.centers[k[s]] - rel[s]
            d2.extend(np.einsum("ki,kij,kj->k", e, np.linalg.inv(obs.covs[k[s], :2, :2]), e))
        assert len(d2) >= 20
        med[name] = float(np.median(np.sqrt(d2)))
    assert med["off"] > 2.0  # too confident
    assert 0.7 < med["noise"] < 1.6  # about calibrated
    assert med["on"] < med["noise"]  # the terms only widen it


def test_an_averaging_scanner_keeps_the_fit_covariance():
    # the first-echo terms do not reach an averaging scanner (its own: test_centre_cov_averaging)
    batch, _ = _batch(2.5, "averaging")
    own = {"centre_sd_footprint": 0.0, "centre_sd_across_averaging": 0.0, "dbh_sd_footprint": 0}
    on = _det("averaging", **ON, **own).detect_batch(batch)
    off = _det("averaging", **OFF, **own).detect_batch(batch)
    assert np.array_equal(on.covs, off.covs) and np.array_equal(on.centers, off.centers)
