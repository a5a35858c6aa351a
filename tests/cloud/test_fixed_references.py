"""The real-cloud benchmarks' ring references are a fixed yardstick (benchmarks/_cloud_refs.py;
docs/algorithms/cloud.md "Real clouds"): seeded from the committed
benchmarks/_cloud_ring_seeds.json, converged from 15 start circles, and paired with the
detections by position, so moving the detector's stems does not move them.

Before, each reference was started from the detected circle
(:func:`stemmap.cloud.reference.stem_references`): on treels spruce a detector change moved
the reference by 0.4 cm, and a 2 cm shift of the start circle moves it by up to 1.8 cm.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from _cloud_refs import CLOUDS, fixed_references, load_seeds, reference_of_each
from stemmap.cloud.ground import GroundModel
from stemmap.cloud.reference import converged_ring_reference, ring_reference, stem_references
from stemmap.cloud.stems import StemConfig, detect_stems, detect_stems_file
from stemmap.io.clouds import read_cloud


def _ring(rng: np.random.Generator, r: float, n: int, sigma: float) -> np.ndarray:
    t = rng.uniform(0, 2 * np.pi, n)
    rr = r + rng.normal(0, sigma, n)
    return np.column_stack((rr * np.cos(t), rr * np.sin(t), rng.uniform(1.25, 1.35, n)))


def test_converged_reference_reports_its_start_spread(rng: np.random.Generator) -> None:
    """A clean 12 cm ring: every start converges to the same circle (spread below the
    fit's own noise); with a branch stub against the trunk the starts disagree and the
    spread says so, while the median stays on the trunk."""
    ring = _ring(rng, 0.12, 600, 0.002)
    ref = converged_ring_reference(ring, (0.01, -0.01), 1.3, 0.11)
    assert ref is not None and ref.starts == 15
    assert abs(ref.diameter - 0.24) < 0.002 and ref.spread < 0.001
    # a stub: 150 points in a 6 x 4 cm patch just outside the trunk
    stub = np.column_stack(
        (rng.uniform(0.12, 0.18, 150), rng.uniform(-0.02, 0.02, 150), np.full(150, 1.3))
    )
    ref2 = converged_ring_reference(np.vstack((ring, stub)), (0.0, 0.0), 1.3, 0.12)
    assert ref2 is not None
    assert abs(ref2.diameter - 0.24) < 0.005  # the median start stays on the trunk
    assert ref2.spread > 0.001  # some starts take in part of the stub (2.2 mm measured)


def test_a_diverging_fit_is_no_reference(rng: np.random.Generator) -> None:
    """A 60 degree arc started 5 cm off with half the radius: Gauss-Newton runs away (the
    benchmark once reported a 1.5e6 m ring); the fit is refused instead."""
    t = rng.uniform(0, np.pi / 3, 80)
    arc = np.column_stack((0.04 * np.cos(t), 0.04 * np.sin(t), np.full(80, 1.3)))
    for c in ((0.05, 0.0), (0.0, 0.05), (-0.05, -0.05)):
        got = ring_reference(arc, c, 1.3, 0.02)
        assert got is None or got.diameter < 2 * (1.5 * 0.02 + 0.1)


def test_every_benchmark_cloud_has_seeds() -> None:
    seeds = load_seeds()
    assert set(seeds) == set(CLOUDS)
    for key, ss in seeds.items():
        assert ss, key
        for s in ss:
            assert 0.02 < s.r < 0.5 and s.half in (0.05, 0.1)


@pytest.mark.slow
@pytest.mark.parametrize("key", ["treels_spruce", "treels_pine_plot"])
def test_references_do_not_follow_the_detector(datasets_dir: Path, key: str) -> None:
    """The detector's stems moved by 3 cm (four directions) and their diameters by +-1 cm:
    every stem pairs with the same fixed reference, of the same diameter. The detector-seeded
    reference of before moves (checked on the spruce, whose ring depends on its start).
    Each seed also reproduces its reference within 1 cm of the seed's own diameter (a stale
    seeds file, e.g. after a dataset change, would not)."""
    xyz = read_cloud(datasets_dir / CLOUDS[key]).xyz
    seeds = load_seeds()[key]
    refs = fixed_references(xyz, seeds)
    for s, r in zip(seeds, refs, strict=True):
        assert r is not None and abs(r.diameter - 2 * s.r) < 0.01
    det = detect_stems(xyz, StemConfig())
    hits = reference_of_each(refs, det.xy)
    assert sum(h is not None for h in hits) == len([r for r in refs if r is not None])
    old_moves = []
    for dx, dy, dd in ((0.03, 0, 0.01), (-0.03, 0, -0.01), (0, 0.03, 0.01), (0, -0.03, -0.01)):
        moved = replace(det, xy=det.xy + np.array([dx, dy]), diameter=det.diameter + dd)
        again = reference_of_each(refs, moved.xy)
        assert [h and h[0] for h in again] == [h and h[0] for h in hits]
        assert [h and h[1].diameter for h in again] == [h and h[1].diameter for h in hits]
        # the same fixed references recomputed from the seeds: identical numbers
        assert [r and r.diameter for r in fixed_references(xyz, seeds)] == [
            r and r.diameter for r in refs
        ]
        old = [r for r in stem_references(xyz, moved) if r is not None]
        base_old = [r for r in stem_references(xyz, det) if r is not None]
        old_moves += [abs(a.diameter - b.diameter) for a, b in zip(old, base_old, strict=False)]
    if key == "treels_spruce":
        assert max(old_moves) > 0.003  # the old yardstick moved with the detector


@pytest.mark.slow
def test_pine_plots_unchecked_stem_has_no_breast_height(datasets_dir: Path) -> None:
    """benchmarks/cloud_robustness.py counts a plot's recall over the baseline stems that
    pair with a fixed reference. On treels pine_plot that is 16 of the detector's 17: the
    17th, a 6.3 cm "stem" at (1.09, 9.68) m near the plot edge, has no ring seed, and no
    return within 15 cm of its axis between 1.30 and 1.50 m above the ground nor between
    1.75 and 2.00 m, where the 8.6 cm stem 1.6 m away has 10-20 returns in every 5 cm
    (docs/algorithms/cloud.md "pine_plot's 17th stem"): there is no breast-height section to
    measure, whatever the detector does. (Since the detector asks a stem to go on above the
    band, ``StemConfig.continues_above``, it no longer reports the object: the detector
    before it is run here.)"""
    path = datasets_dir / "treels/pine_plot.laz"
    xyz = read_cloud(path).xyz
    grounds: list[GroundModel | None] = []
    det = detect_stems_file(path, StemConfig(continues_above=False), on_ground=grounds.append)
    refs = fixed_references(xyz, load_seeds()["treels_pine_plot"])
    unchecked = [i for i, h in enumerate(reference_of_each(refs, det.xy)) if h is None]
    assert len(det) == 17 and len(unchecked) == 1
    (k,) = unchecked
    assert np.hypot(*(det.xy[k] - (1.09, 9.68))) < 0.05
    assert grounds[0] is not None
    h = grounds[0].height_of(xyz)

    def returns(centre: np.ndarray, lo: float) -> int:
        near = np.hypot(*(xyz[:, :2] - centre).T) < 0.15
        return int((near & (h >= lo) & (h < lo + 0.05)).sum())

    levels = [*np.arange(1.30, 1.50, 0.05), *np.arange(1.75, 2.0, 0.05)]
    assert all(returns(det.xy[k], lo) == 0 for lo in levels)
    (j,) = [i for i in range(len(det)) if np.hypot(*(det.xy[i] - (0.42, 8.24))) < 0.05]
    assert all(returns(det.xy[j], lo) >= 10 for lo in levels)


def _leaning_tapered_stem(rng: np.random.Generator, lean_deg: float) -> np.ndarray:
    """A stem from 0 to 3.5 m, radius 0.12 m at 1.3 m narrowing 1 cm per metre, its axis
    leaning ``lean_deg`` towards +x; 4 mm noise."""
    h = rng.uniform(0.0, 3.5, 40_000)
    t = rng.uniform(0, 2 * np.pi, h.size)
    r = 0.12 - 0.01 * (h - 1.3) + rng.normal(0, 0.004, h.size)
    ax = np.tan(np.radians(lean_deg)) * h
    return np.column_stack((ax + r * np.cos(t), r * np.sin(t), h))


def test_tracked_reference_follows_a_leaning_stem(rng: np.random.Generator) -> None:
    """A crop's DBH is measured higher up the stem: the reference at that height follows the
    stem from the committed seed (1.3 m) in 10 cm steps and gives the stem's section there;
    the seed's circle used directly at 2.4 m is 19 cm off a 10 degree lean and has no ring."""
    from _cloud_refs import RingSeed, tracked_reference

    xyz = _leaning_tapered_stem(rng, 10.0)
    x13 = np.tan(np.radians(10.0)) * 1.3
    seed = RingSeed(x13, 0.0, 1.3, 0.12, 0.05)
    got = tracked_reference(xyz, seed, 2.4)
    true_d = 2 * (0.12 - 0.011) * np.cos(np.radians(10.0))  # the leaning section's minor axis
    assert got is not None and got.full
    # a horizontal section of a leaning cylinder is an ellipse: its fitted circle lies
    # between the axes (d cos-1 and d), 2.2 mm apart here
    assert true_d - 0.001 < got.diameter < true_d / np.cos(np.radians(10.0)) ** 2 + 0.001
    assert abs(got.x - np.tan(np.radians(10.0)) * 2.4) < 0.005
    direct = converged_ring_reference(xyz, (seed.x, seed.y), 2.4, seed.r)
    assert direct is None or abs(direct.diameter - got.diameter) > 0.01
    # at the seed's own height it is the fixed reference
    same = tracked_reference(xyz, seed, 1.3)
    ref = converged_ring_reference(xyz, (seed.x, seed.y), 1.3, seed.r, half_thickness=0.05)
    assert same is not None and ref is not None and same.diameter == ref.diameter
