"""The precision gate (``max_dbh_sd``; issue 11, Dec 5, "Noisy first-echo rows" in
docs/algorithms/scan-detection.md).

A first-echo candidate whose circle fit's own diameter standard deviation ``2 sqrt(C_rr)``
exceeds ``max_dbh_sd`` is rejected with the reason ``"precision"``. The scene: a 20 cm disc
seen from 40 bearings by the benchmark's first-echo virtual scanner (0.25 deg) with 3 cm of
range noise, one scan per bearing, so no scan has a noise estimate of its own and
``scan_noise_batch`` gives the tests the batch's (about 3 cm)."""

import functools
import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.eval.real_slices import noisy_batch, virtual_scans
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

R = 0.10  # disc radius, m
STEP = 0.25  # degrees
V = 40  # scans (bearings)


@functools.cache
def _batch(d: float, model: str = "nearest"):
    a = np.linspace(-math.pi, math.pi, 3000, endpoint=False)
    xy = np.column_stack((R * np.cos(a), R * np.sin(a)))
    b = np.linspace(0.0, 2.0 * math.pi, V, endpoint=False)
    vp = d * np.column_stack((np.cos(b), np.sin(b)))
    ranges, _ = virtual_scans(
        xy,
        np.zeros(a.size, dtype=np.int64),
        vp,
        resolution_deg=STEP,
        model=model,
        centers=np.zeros((1, 2)),
    )
    return noisy_batch(ranges, STEP, 0.03, np.random.default_rng(1)), -vp


def _det(model: str = "nearest", **extra) -> ScanTrunkDetector:
    # the gate reads the fit's own covariance: the detections report it here too (not the
    # preset's std at the measured noise plus the outline term, test_dbh_sd_first_echo.py)
    foot = {"beam_footprint_deg": STEP} if model == "nearest" else {}
    own = {"dbh_sd_noise": False, "dbh_sd_outline": 0.0}
    return ScanTrunkDetector(
        DetectorConfig.preset("stemmap", scan_noise_batch=2.5, **foot, **own, **extra)
    )


def _on_disc(obs, rel) -> np.ndarray:
    """Per scan the detection on the disc (index into ``obs``) or -1."""
    out = np.full(V, -1)
    for s in range(V):
        m = np.flatnonzero((obs.index == s) & (np.hypot(*(obs.centers - rel[s]).T) < 0.1))
        if m.size:
            out[s] = m[0]
    return out


def test_the_diameter_std_grows_with_range():
    # fewer returns and a wider beam spacing on the stem: the fit's own DBH std grows
    sd = {}
    for d in (2.5, 9.0):
        batch, rel = _batch(d)
        obs = _det().detect_batch(batch)
        k = _on_disc(obs, rel)
        assert np.count_nonzero(k >= 0) >= V // 2
        sd[d] = float(np.median(2.0 * np.sqrt(obs.covs[k[k >= 0], 2, 2])))
    # measured: 0.47 cm at 2.5 m (19 returns), 1.55 cm at 9 m (7 returns)
    assert sd[9.0] > 2.0 * sd[2.5]


@pytest.mark.parametrize("d", [2.5, 9.0])
def test_the_gate_drops_exactly_the_imprecise_fits(d):
    batch, rel = _batch(d)
    free = _det().detect_batch(batch)
    k = _on_disc(free, rel)
    sd = np.where(k >= 0, 2.0 * np.sqrt(free.covs[np.maximum(k, 0), 2, 2]), np.nan)
    gate = float(np.nanmedian(sd))  # half the views above it
    det = _det(max_dbh_sd=gate)
    obs = det.detect_batch(batch)
    kept = _on_disc(obs, rel) >= 0
    # a view the gate keeps is the ungated fit (same radius); a view it drops had sd > gate
    assert np.array_equal(kept, (k >= 0) & (sd <= gate))
    for s in np.flatnonzero(kept):
        j = _on_disc(obs, rel)[s]
        assert obs.radii[j] == pytest.approx(free.radii[k[s]], abs=1e-12)
    rej = det.rejected(batch)
    assert (
        np.count_nonzero(np.asarray(rej["reason"]) == "precision")
        >= np.count_nonzero((k >= 0) & (sd > gate))
        > 0
    )


def test_an_averaging_scanner_is_not_gated():
    # the gate reads first-echo fits only: the averaging edge model (compiled path) is unchanged
    batch, _ = _batch(6.0, "averaging")
    a = _det("averaging").detect_batch(batch)
    b = _det("averaging", max_dbh_sd=1e-6).detect_batch(batch)
    assert np.array_equal(a.radii, b.radii) and np.array_equal(a.index, b.index)


def test_the_gate_must_be_positive():
    with pytest.raises(ConfigError):
        DetectorConfig(max_dbh_sd=0.0)
