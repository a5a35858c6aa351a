"""The first-echo run searches try many run lengths in one fit (issue 11, Dec 5, "Speed of the
first-echo trims" in docs/algorithms/scan-detection.md): the result must not depend on how
the lengths are grouped, and the compiled / shared noise helpers they read must give the
numbers of the plain numpy they replace.

``BLOCK_RETURNS = 1`` makes every block one run length, for every candidate still searched:
the search of one fit per length that the blocks replaced. The scenes are the run tests' own
(the flank bar of ``test_stub_runs``, the needle tuft of ``test_stub_runs_worst``) with range
noise, several bearings in one batch, so end runs, inner runs and candidates that find none
meet in one call."""

import math

import numpy as np
import pytest
from tests.scan.test_edge_protrusion import STEP
from tests.scan.test_stub_runs import _scan
from tests.scan.test_stub_runs_worst import _tuft_scan

from stemmap.scan import _stub_runs
from stemmap.scan._fast_robust import segment_step_medians
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import scan_noise, scan_noise_estimates
from stemmap.types import ScanBatch


def _scenes(noise: float, seed: int) -> ScanBatch:
    """Bar and tuft scenes from 24 bearings (0.5 deg first-echo scans), ``noise`` m of
    Gaussian range noise, in one batch."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(12):
        b = 0.3 + k * math.radians(STEP) * 5.3 / 12
        rows.append(_scan(1.5 + 0.2 * k, b, 0.06)[0].ranges[0])
        rows.append(_tuft_scan(b, -25.0 - k, 0.015, 0.06)[0].ranges[0])
    r = np.array(rows)
    r = r + noise * rng.standard_normal(r.shape)
    first = _scan(1.5, 0.3, 0.06)[0]
    return ScanBatch(
        r, np.arange(r.shape[0], dtype=np.float64), first.angle_min, first.angle_increment
    )


def _rows(det: ScanTrunkDetector, batch: ScanBatch) -> np.ndarray:
    obs = det.detect_batch(batch)
    return np.column_stack((obs.index, obs.centers, obs.radii, obs.n_points, obs.quality))


@pytest.mark.parametrize(("noise", "seed"), [(0.0, 0), (0.003, 1), (0.01, 2)])
def test_the_detections_do_not_depend_on_the_block_size(monkeypatch, noise, seed):
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", beam_footprint_deg=STEP))
    assert det.config.stub_runs and det.config.stub_runs_inner  # the preset's trims run
    batch = _scenes(noise, seed)
    calls = {"outward": 0, "inner": 0, "end_runs": 0, "inner_runs": 0}
    outward, inner = _stub_runs.outward_runs, _stub_runs.inner_runs

    def count_outward(*a):
        got = outward(*a)
        calls["outward"] += 1
        calls["end_runs"] += int(np.count_nonzero(got[0]) + np.count_nonzero(got[1]))
        return got

    def count_inner(*a):
        got = inner(*a)
        calls["inner"] += 1
        calls["inner_runs"] += int(np.count_nonzero(got[1]))
        return got

    monkeypatch.setattr(_stub_runs, "outward_runs", count_outward)
    monkeypatch.setattr(_stub_runs, "inner_runs", count_inner)
    default = _rows(det, batch)
    found = dict(calls)
    for block in (1, 97, 2000):  # one length per block; a few lengths; most at once
        monkeypatch.setattr(_stub_runs, "BLOCK_RETURNS", block)
        got = _rows(det, batch)
        assert got.shape == default.shape
        assert np.array_equal(got, default, equal_nan=True)  # bit for bit
    # the searches ran and found runs of both kinds (else the comparison proves nothing)
    assert found["outward"] > 0 and found["inner"] > 0
    assert found["end_runs"] > 0 and found["inner_runs"] > 0


def test_segment_step_medians_is_the_median_absolute_step():
    rng = np.random.default_rng(5)
    for trial in range(200):
        counts = rng.integers(1, 30, size=rng.integers(0, 12))
        stop = np.cumsum(counts).astype(np.int64)
        start = stop - counts
        r = rng.uniform(1.0, 20.0, int(counts.sum()))
        if trial % 2:
            r = np.round(r, 2)  # ties
        got = segment_step_medians(r, start, stop)
        want = np.array(
            [
                np.median(np.abs(np.diff(r[a:b]))) if b - a >= 2 else 0.0
                for a, b in zip(start, stop, strict=True)
            ]
        )
        assert np.array_equal(got, want)  # a median selects: the same value to the bit


@pytest.mark.parametrize("rms_noise_from_fit", [0.0, 2.0])
def test_scan_noise_estimates_are_the_separate_calls(rms_noise_from_fit):
    rng = np.random.default_rng(3)
    r = rng.uniform(2.0, 8.0, (30, 200))
    r[:, 50:120] = 5.0 + 0.01 * rng.standard_normal((30, 70))  # one wall per scan
    r[rng.random(r.shape) < 0.2] = np.nan
    cfg = DetectorConfig.preset("stemmap", rms_noise_from_fit=rms_noise_from_fit)
    estimate = scan_noise_estimates(r, cfg)
    for missing in (0.0, math.nan):
        for pool in (False, True):
            for batch_min in (math.inf, 0.0, 0.004):
                want = scan_noise(
                    r,
                    cfg.scan_noise_jump,
                    cfg.scan_noise_surface,
                    missing,
                    pool=pool,
                    batch_min=batch_min,
                    batch_scale=cfg.batch_noise_scale,
                )
                got = estimate(missing, pool, batch_min)
                assert np.array_equal(got, want, equal_nan=True)
                assert estimate(missing, pool, batch_min) is got  # asked twice: once
