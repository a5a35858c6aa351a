"""The jackknife DBH standard error of first-echo detections (``dbh_sd_jackknife``; issue 11,
Dec 6, "Junction merges on lidR" in docs/algorithms/scan-detection.md).

Constructed arcs, scanned by a first-echo beam (each beam's nearest surface along its centre
ray, 0.25 deg, from 4 m): a 30 cm stem whose arc runs on at its far end into a branch leaving
the stem at a shallow angle without a range jump (two surfaces, the lidR junction), against
the same stem with cm-scale random bark (one circle, rough). The jackknife must see the first
and not inflate the second beyond its noise."""

import math

import numpy as np
import pytest
from tests.scan.test_max_dbh_sd import STEP, _batch

from stemmap.errors import ConfigError
from stemmap.scan._dbh_jackknife import group_ids, jackknife_radius_var
from stemmap.scan._segment_fits import _fit_segments
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.segment import Segments, extract_points

R, D = 0.15, 4.0  # stem radius, range to its centre (m)
STEP_RAD = math.radians(0.25)


def _rays(n: int = 81) -> np.ndarray:
    return (np.arange(n) - n // 2) * STEP_RAD


def _circle_ranges(th: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    u = np.column_stack((np.cos(th), np.sin(th)))
    b = u @ c
    disc = b * b - (c @ c - r * r)
    out = np.where(disc >= 0, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
    return np.asarray(out)


def _segment_ranges(th: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Range along each ray to the segment p0-p1 (inf where it misses)."""
    u = np.column_stack((np.cos(th), np.sin(th)))
    d = p1 - p0
    den = u[:, 0] * (-d[1]) - u[:, 1] * (-d[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p0[0] * (-d[1]) - p0[1] * (-d[0])) / den
        s = (u[:, 0] * p0[1] - u[:, 1] * p0[0]) / den
    return np.where((t > 0) & (s >= 0) & (s <= 1), t, np.inf)


def _segments(ranges: np.ndarray, th: np.ndarray) -> Segments:
    keep = np.isfinite(ranges)
    pts = extract_points(np.where(keep, ranges, np.inf), th, STEP_RAD)
    n = len(pts)
    f = np.zeros(1, dtype=bool)
    return Segments(pts, np.array([0]), np.array([n]), np.array([0]), f, f, f, f)


def _junction(rng: np.random.Generator, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """The stem, and a 6 cm branch root leaving its far flank (bearing > 0) at 30 deg to the
    ray, joined to the outline: a continuous arc of two surfaces."""
    th = _rays()
    c = np.array([D, 0.0])
    r = _circle_ranges(th, c, R)
    a = math.radians(80.0)  # where the branch leaves the stem, from the sensor direction
    p0 = c + R * np.array([-math.cos(a), math.sin(a)])
    p1 = p0 + 0.12 * np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0))])
    r = np.fmin(r, _segment_ranges(th, p0, p1))
    r = np.where(np.isfinite(r), r + noise * rng.standard_normal(r.size), r)
    return r, th


def _rough(rng: np.random.Generator, rough: float) -> tuple[np.ndarray, np.ndarray]:
    th = _rays()
    r = _circle_ranges(th, np.array([D, 0.0]), R)
    r = np.where(np.isfinite(r), r + rough * rng.standard_normal(r.size), r)
    return r, th


def test_groups_are_consecutive_runs_of_returns():
    g = group_ids(np.array([4, 25]), groups=10)
    assert g[:4].tolist() == [0, 1, 2, 3]  # few returns: delete-one
    assert np.all(np.diff(g[4:]) >= 0) and g[4] == 0 and g[-1] == 9
    assert np.bincount(g[4:]).min() >= 2  # every group holds returns


def test_a_two_surface_arc_has_a_larger_jackknife_than_a_rough_circle():
    """Over 20 draws at the same residual scale (the branch's arc at 5 mm noise, the rough
    circle at 1 cm of bark): the junction makes the radius depend on whether the branch
    returns are in the fit, which the jackknife reads; the rough circle's radius does not."""
    rng = np.random.default_rng(3)
    sj, sr, fit_sd = [], [], []
    for _ in range(20):
        r, th = _junction(rng, 0.005)
        segs = _segments(r, th)
        sj.append(math.sqrt(jackknife_radius_var(segs, np.array([0.01]))[0]))
        r, th = _rough(rng, 0.01)
        segs = _segments(r, th)
        sr.append(math.sqrt(jackknife_radius_var(segs, np.array([0.01]))[0]))
        covs = _fit_segments(segs, "ours", np.array([0.01]))[2]
        fit_sd.append(math.sqrt(covs[0, 2, 2]))
    assert np.median(sj) > 2.0 * np.median(sr)
    # on one rough circle the jackknife is of the order of the fit's own std (Efron-Stein:
    # an upward-biased variance estimate), not an inflation by itself
    assert 0.5 < np.median(sr) / np.median(fit_sd) < 4.0


def test_detections_unchanged_and_only_the_radius_variance_grows():
    batch, _ = _batch(5.0)  # the 20 cm disc at 5 m, 3 cm of noise (test_max_dbh_sd)
    off = ScanTrunkDetector(DetectorConfig.preset("stemmap", beam_footprint_deg=STEP))
    on = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", beam_footprint_deg=STEP, dbh_sd_jackknife=1.0)
    )
    a, b = off.detect_batch(batch), on.detect_batch(batch)
    assert len(a) > 0
    for name in ("centers", "radii", "n_points", "arc_deg", "widths", "quality", "index"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    ca, cb = a.covs.reshape(-1, 3, 3), b.covs.reshape(-1, 3, 3)
    assert np.array_equal(ca[:, :2, :], cb[:, :2, :])
    assert np.array_equal(ca[:, 2, :2], cb[:, 2, :2])
    assert np.all(cb[:, 2, 2] >= ca[:, 2, 2])
    assert np.any(cb[:, 2, 2] > ca[:, 2, 2])
    assert np.all(np.linalg.eigvalsh(cb) > 0)


def test_off_by_default_and_an_averaging_scanner_is_untouched():
    assert DetectorConfig().dbh_sd_jackknife == 0.0
    assert DetectorConfig.preset("stemmap").dbh_sd_jackknife == 0.0
    with pytest.raises(ConfigError, match="dbh_sd_jackknife"):
        DetectorConfig(dbh_sd_jackknife=-1.0)
    batch, _ = _batch(5.0, "averaging")
    a = ScanTrunkDetector(DetectorConfig.preset("stemmap")).detect_batch(batch)
    b = ScanTrunkDetector(DetectorConfig.preset("stemmap", dbh_sd_jackknife=1.0)).detect_batch(
        batch
    )
    assert np.array_equal(a.covs, b.covs)


def _loop_reference(segs: Segments, sigma: np.ndarray, groups: int = 10) -> np.ndarray:
    """The jackknife one segment and one group at a time (Segments.drop), for comparison."""
    out = np.full(len(segs), np.nan)
    for j in range(len(segs)):
        one = segs.select(np.arange(len(segs)) == j)
        n = int(one.counts[0])
        g_n = min(n, groups)
        gid = (np.arange(n) * g_n) // n
        radii = []
        for g in range(g_n):
            drop = gid == g
            if n - drop.sum() < 3:
                continue
            flagged = Segments(
                one.points,
                one.start,
                one.stop,
                one.scan,
                one.occluded_start | drop[0],
                one.occluded_end | drop[-1],
                one.truncated_start,
                one.truncated_end,
            ).drop(~drop)
            _, r, _, ok = _fit_segments(flagged, "ours", sigma[j : j + 1])
            if ok[0]:
                radii.append(r[0])
        a = np.array(radii)
        if a.size >= 3:
            out[j] = (a.size - 1) / a.size * np.sum((a - a.mean()) ** 2)
    return out


def test_the_batched_refits_equal_one_refit_at_a_time():
    """Two scans in one table: the junction arc (more returns than groups: groups of 2-3) and
    a rough arc cut to 6 returns (delete-one)."""
    rng = np.random.default_rng(11)
    r1, th = _junction(rng, 0.005)
    r2, _ = _rough(rng, 0.01)
    r2 = np.where(np.cumsum(np.isfinite(r2)) <= 6, r2, np.inf)
    pts = extract_points(np.vstack((r1, r2)), th, STEP_RAD)
    n1 = int(np.isfinite(r1).sum())
    n = len(pts)
    f = np.zeros(2, dtype=bool)
    segs = Segments(pts, np.array([0, n1]), np.array([n1, n]), np.array([0, 1]), f, f, f, f)
    assert segs.counts[0] > 10 and segs.counts[1] == 6
    sigma = np.array([0.01, 0.01])
    got = jackknife_radius_var(segs, sigma)
    assert np.all(np.isfinite(got))
    assert np.allclose(got, _loop_reference(segs, sigma), rtol=1e-9, atol=1e-12)
