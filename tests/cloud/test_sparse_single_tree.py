"""treels spruce.laz randomly subsampled to 50 % (benchmarks/cloud_robustness.py
``subsample_50``; docs/algorithms/cloud.md "Single trees at lower density (Dec 3)"): its band
is mostly needles, so half the 90th-percentile spacing (66 mm) is a RANSAC tolerance in which
circles through the branch whorls win every slice. The tighter refits of a rejected cluster
(:func:`stemmap.cloud.measure._tighter_refits`) find the stem again."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloud_robustness import TRANSFORMS, Context
from stemmap.cloud.reference import stem_references
from stemmap.cloud.stems import StemConfig, detect_stems
from stemmap.io.clouds import read_cloud


def _subsampled_dbh_error(datasets_dir: Path, transform: str) -> float:
    """|DBH - ring| (m) of the spruce after ``transform``, against the full-ring reference of
    the cloud as shipped (as the benchmark); asserts that without the tighter refits no stem
    is found and with them exactly one."""
    xyz = read_cloud(datasets_dir / "treels/spruce.laz").xyz
    (ref,) = stem_references(xyz, detect_stems(xyz, StemConfig()))
    assert ref is not None and ref.full
    prep = TRANSFORMS[transform](Context(xyz, None))
    assert prep is not None
    # without the tighter refits every slice fits a whorl: no stem
    assert len(detect_stems(prep.xyz, StemConfig(tighter_refits=False))) == 0
    det = detect_stems(prep.xyz, StemConfig())
    assert len(det) == 1
    return abs(float(det.diameter[0]) - ref.diameter)


@pytest.mark.slow
def test_half_density_spruce_keeps_its_stem(datasets_dir: Path) -> None:
    assert _subsampled_dbh_error(datasets_dir, "subsample_50") < 0.015


def test_tighter_refits_leave_a_clean_stem_alone() -> None:
    """A clean synthetic stem passes at the first tolerance: identical with and without."""
    rng = np.random.default_rng(4)
    z = rng.uniform(0.0, 3.0, 6000)
    a = rng.uniform(0, 2 * np.pi, z.shape[0])
    r = 0.15 + rng.normal(0, 0.003, z.shape[0])
    stem = np.column_stack((r * np.cos(a), r * np.sin(a), z))
    g = rng.uniform(-3, 3, (20_000, 2))
    cloud = np.vstack((stem, np.column_stack((g, rng.normal(0, 0.01, g.shape[0])))))
    on = detect_stems(cloud, StemConfig())
    off = detect_stems(cloud, StemConfig(tighter_refits=False))
    assert len(on) == len(off) == 1
    assert on.diameter[0] == off.diameter[0]


@pytest.mark.slow
def test_tenth_density_spruce_is_found_with_thin_slices(datasets_dir: Path) -> None:
    """At 10 % (spacing 153 mm: three 0.4 m slices, the middle one all whorl) the stem is
    found only from the default 20 cm slices. Its DBH is 1.7 cm off the ring: found, but the
    issue's 1.5 cm target is not met there (docs/algorithms/cloud.md)."""
    assert _subsampled_dbh_error(datasets_dir, "subsample_10") < 0.02
