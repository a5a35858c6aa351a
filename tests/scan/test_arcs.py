"""The largest consistent arc of a non-convex candidate (``arc_refit``, issue 11, fourth round):
a trunk whose segment runs on into a branch is found again with its own radius."""

import math

import numpy as np
import pytest
from tests.scan.test_gaps_refit import INC
from tests.scan.test_gaps_refit import _scan as _circles_scan

from stemmap.errors import ConfigError
from stemmap.scan._arcs import largest_arc
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.types import ScanBatch

TRUNK = (5.0, 0.0, 0.15)


def _branch(p0, p1, rad=0.03, step=0.01):
    """A branch as a chain of small circles from ``p0`` to ``p1`` (a continuous surface)."""
    n = int(math.hypot(p1[0] - p0[0], p1[1] - p0[1]) / step) + 1
    t = np.linspace(0.0, 1.0, n)
    return [(p0[0] + s * (p1[0] - p0[0]), p0[1] + s * (p1[1] - p0[1]), rad) for s in t]


def _scan(circles, noise=0.0, seed=0):
    """Thin-beam ranges of circles (cx, cy, r) on 121 beams centred on the x axis, plus
    Gaussian range noise."""
    batch = _circles_scan(circles)
    if noise > 0:
        r = batch.ranges + np.random.default_rng(seed).normal(0.0, noise, batch.ranges.shape)
        batch = ScanBatch(
            ranges=r,
            times=batch.times,
            angle_min=batch.angle_min,
            angle_increment=batch.angle_increment,
            range_max=batch.range_max,
        )
    return batch


# a trunk of 30 cm at 5 m and a branch leaving its silhouette edge towards the sensor (the
# segment is not convex: lidR, scan-detection-history.md)
TRUNK_AND_BRANCH = [TRUNK, *_branch((5.0, 0.17), (4.6, 0.8))]


def test_the_merged_segment_is_rejected_as_not_convex_without_arcs():
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", refit_pieces=False, arc_refit=False))
    batch = _scan(TRUNK_AND_BRANCH)
    assert len(det.detect_batch(batch)) == 0
    assert "depth" in det.rejected(batch)["reason"]
    # the default's validated corner split (eleventh round) cuts the branch off
    no_arcs = DetectorConfig.preset("stemmap", arc_refit=False)
    assert len(ScanTrunkDetector(no_arcs).detect_batch(batch)) == 1


def test_the_arc_of_the_trunk_is_found_with_its_radius():
    arcs = {"arc_refit": True, "arc_sigmas": 2.0}
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", refit_pieces=False, **arcs))
    obs = det.detect_batch(_scan(TRUNK_AND_BRANCH))
    assert len(obs) == 1
    # with the default's corner split too: one trunk, not the split's piece and the arc
    both = ScanTrunkDetector(DetectorConfig.preset("stemmap", **arcs))
    assert len(both.detect_batch(_scan(TRUNK_AND_BRANCH))) == 1
    # noise-free returns on an exact circle: the arc's fit recovers it to a millimetre
    assert obs.radii[0] == pytest.approx(TRUNK[2], abs=0.002)
    assert np.hypot(*(obs.centers[0] - TRUNK[:2])) < 0.003


def test_an_accepted_fit_pulled_by_a_stub_gives_way_to_its_arc():
    # a 6 cm stub touching the trunk's silhouette edge: the segment stays convex and its fit
    # passes, 5 cm too wide; with arc_replace the trunk's own arc replaces it
    batch = _scan([TRUNK, (5.02, 0.19, 0.03)])
    plain = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_replace=math.inf)
    )
    assert plain.detect_batch(batch).radii[0] > TRUNK[2] + 0.03
    det = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_replace=2.0)
    )
    obs = det.detect_batch(batch)
    assert len(obs) == 1
    # the 0.5 deg beams leave ~2 mm between the last trunk return and the silhouette
    assert obs.radii[0] == pytest.approx(TRUNK[2], abs=0.003)


def test_arc_replace_leaves_a_clean_trunk_alone():
    batch = _scan([TRUNK], noise=0.01, seed=3)
    base = ScanTrunkDetector(DetectorConfig.preset("stemmap")).detect_batch(batch)
    det = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_replace=2.0)
    )
    obs = det.detect_batch(batch)
    assert len(obs) == len(base) == 1
    assert obs.radii[0] == base.radii[0]


def test_largest_arc_stops_where_the_branch_leaves_the_circle():
    batch = _scan(TRUNK_AND_BRANCH)
    r = batch.ranges[0]
    ok = np.isfinite(r)
    ang = batch.angle_min + INC * np.arange(r.shape[0])
    x, y = (r * np.cos(ang))[ok], (r * np.sin(ang))[ok]
    on_trunk = np.abs(np.hypot(x - TRUNK[0], y - TRUNK[1]) - TRUNK[2]) < 1e-6
    got = largest_arc(x, y, 0.01, 2.0, 4, 0.02, 0.8)
    assert got is not None
    a, b = got
    # every trunk return and no branch return (the trunk returns come first in beam order)
    assert np.flatnonzero(on_trunk).tolist() == list(range(a, b))


def test_an_arc_in_the_middle_of_a_segment_does_not_count():
    # a bulge in the middle of a long wall-like run: no arc reaching an end
    t = np.linspace(-0.5, 0.5, 41)
    x = 5.0 + 0.0 * t
    y = t.copy()
    mid = np.abs(t) < 0.08
    x[mid] -= np.sqrt(0.1**2 - t[mid] ** 2) - math.sqrt(0.1**2 - 0.08**2)
    got = largest_arc(x, y, 0.005, 2.0, 4, 0.02, 0.8)
    assert got is None or got[0] == 0 or got[1] == x.shape[0]
    assert got is None or not (mid[got[0] : got[1]].all() and got[1] - got[0] < 20)


def test_arc_refit_runs_on_the_compiled_path():
    # compiled since the fourteenth round (tests/scan/test_detect_fast.py: same detections)
    for extra in ({}, {"arc_replace": 3.0}, {"arc_short_steps": True}):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", arc_refit=True, **extra))
        assert det._compiled(None, None)


def _kasa_reference(s):
    n, sx, sy, sxx, syy, sxy, sz, sxz, syz = s
    a = np.array([[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, n]])
    try:
        u, v, w = np.linalg.solve(a, np.array([sxz, syz, sz]))
    except np.linalg.LinAlgError:
        return None
    cx, cy = 0.5 * u, 0.5 * v
    r2 = w + cx * cx + cy * cy
    return (cx, cy, math.sqrt(r2)) if r2 > 0 and math.isfinite(r2) else None


def _largest_arc_reference(x, y, floor, k, seed, r_min, r_max):
    """The fourth round's numpy search (np.median, np.linalg.solve), kept as the oracle of the
    compiled one in stemmap.scan._fast_arcs."""
    n = x.shape[0]
    if n < seed:
        return None
    ox, oy = x.mean(), y.mean()
    lx, ly = x - ox, y - oy
    z = lx * lx + ly * ly
    t = np.stack((np.ones_like(lx), lx, ly, lx * lx, ly * ly, lx * ly, z, lx * z, ly * z), 1)
    starts = range(n - seed + 1)
    if len(starts) > 24:
        starts = range(0, n - seed + 1, math.ceil((n - seed + 1) / 24))
    best = None
    for a0 in starts:
        a, b = a0, a0 + seed
        s = t[a:b].sum(axis=0)
        c = _kasa_reference(s)
        if c is None or not (r_min <= c[2] <= r_max):
            continue
        if math.hypot(c[0] + ox, c[1] + oy) <= math.hypot(lx[a:b].mean() + ox, ly[a:b].mean() + oy):
            continue
        while True:
            e = np.hypot(lx[a:b] - c[0], ly[a:b] - c[1]) - c[2]
            tol = max(k * 1.4826 * float(np.median(np.abs(e - np.median(e)))), floor)
            cand = [
                (abs(math.hypot(lx[i] - c[0], ly[i] - c[1]) - c[2]), i)
                for i in (a - 1, b)
                if 0 <= i < n and abs(math.hypot(lx[i] - c[0], ly[i] - c[1]) - c[2]) <= tol
            ]
            if not cand:
                break
            _, i = min(cand)
            c2 = _kasa_reference(s + t[i])
            if c2 is None or not (r_min <= c2[2] <= r_max):
                break
            s, c = s + t[i], c2
            a, b = (i, b) if i < a else (a, i + 1)
        if a > 0 and b < n:
            continue
        e = np.hypot(lx[a:b] - c[0], ly[a:b] - c[1]) - c[2]
        key = (b - a, -float(np.sqrt(np.mean(e * e))))
        if best is None or key > best[0]:
            best = (key, a, b)
    return None if best is None else (best[1], best[2])


def test_compiled_arc_search_equals_the_numpy_search():
    # noisy trunks of 5-40 cm seen over 60-180 deg, some running on into a straight branch at
    # one end, and random blobs: the compiled search (Gaussian elimination, quickselect
    # medians, loop sums) finds the same run as the fourth round's numpy search. (On returns
    # exactly on a circle both neighbours have residuals of ~1e-16 and round-off picks the
    # side that joins first: 7 of 1 500 such noise-free cases took another path.)
    rng = np.random.default_rng(8)
    found = 0
    for trial in range(600):
        r = rng.uniform(0.05, 0.4)
        d = rng.uniform(1.0, 10.0)
        m = int(rng.integers(4, 40))
        th = np.linspace(-1, 1, m) * rng.uniform(0.5, 1.5) + math.pi
        x = d + r * np.cos(th)
        y = r * np.sin(th)
        if trial % 3 == 0:  # a branch off the last return
            k = int(rng.integers(2, 20))
            step = rng.uniform(0.01, 0.05) * np.arange(1, k + 1)
            x = np.r_[x, x[-1] - step * rng.uniform(0.2, 1.0)]
            y = np.r_[y, y[-1] + step]
        elif trial % 3 == 1:  # random blob
            x = d + rng.normal(0, 0.1, m)
            y = np.sort(rng.normal(0, 0.2, m))
        noise = rng.choice([0.003, 0.01])
        x = x + rng.normal(0, noise, x.shape)
        y = y + rng.normal(0, noise, y.shape)
        args = (0.01, 2.0, 4, 0.02, 0.8)
        got = largest_arc(x, y, *args)
        assert got == _largest_arc_reference(x, y, *args), trial
        found += got is not None
    assert found > 300


def test_arc_replace_must_exceed_one():
    with pytest.raises(ConfigError, match="arc_replace"):
        DetectorConfig.preset("stemmap", arc_replace=1.0)


@pytest.mark.parametrize("field", ["arc_sigmas", "arc_floor_sigmas"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.inf])
def test_arc_thresholds_are_validated(field, value):
    with pytest.raises(ConfigError, match=field):
        DetectorConfig.preset("stemmap", **{field: value})


def _four_return_stem_and_a_nearer_one(step):
    """A 20 cm stem at 5.45 m seen by exactly 4 beams of 0.5 deg, and three returns of another
    object beside it, ``step`` then ``step`` + 15 cm nearer than its last return: one segment
    (the range-adaptive threshold is 0.1 + 3 r dtheta = 0.24 m there) that is not convex (the
    TreeLS plot's merged 4-return stems, scan-detection-history.md, fifth round)."""
    batch = _circles_scan([(5.45, 0.02, 0.10)])
    r = batch.ranges[0].copy()
    on = np.flatnonzero(np.isfinite(r))
    assert on.size == 4
    for j, d in enumerate((step, step + 0.15, step + 0.15), start=1):
        r[on[-1] + j] = r[on[-1]] - d
    return ScanBatch(
        ranges=r[None, :],
        times=batch.times,
        angle_min=batch.angle_min,
        angle_increment=batch.angle_increment,
        range_max=batch.range_max,
    )


def test_a_short_arc_set_off_by_a_range_step_is_found_with_arc_short_steps():
    batch = _four_return_stem_and_a_nearer_one(0.16)
    plain = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_short_steps=False)
    )
    # 4 returns < min_points_partial (5): the fourth round's arcs drop it
    assert len(plain.detect_batch(batch)) == 0
    # the stemmap preset finds it since the sixteenth round
    assert len(ScanTrunkDetector("stemmap").detect_batch(batch)) == 1
    det = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_short_steps=True)
    )
    obs = det.detect_batch(batch)
    assert len(obs) == 1
    # noise-free, but only 4 returns over ~60 deg of the stem: within 1 cm of the radius
    assert obs.radii[0] == pytest.approx(0.10, abs=0.01)
    assert np.hypot(*(obs.centers[0] - (5.45, 0.02))) < 0.02


def test_a_short_arc_without_a_range_step_is_not_a_candidate():
    # the other object starts 8 cm nearer (< max_jump = 10 cm): a smooth run, as at the end of
    # a wall or bush, is not set off from its segment
    batch = _four_return_stem_and_a_nearer_one(0.08)
    det = ScanTrunkDetector(
        DetectorConfig.preset("stemmap", arc_refit=True, arc_sigmas=2.0, arc_short_steps=True)
    )
    assert len(det.detect_batch(batch)) == 0
    assert det.rejected(batch)["reason"] == ["depth"]
