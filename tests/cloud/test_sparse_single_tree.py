"""treels spruce.laz randomly subsampled to 50 % (benchmarks/cloud_robustness.py
``subsample_50``; docs/algorithms/cloud.md "Single trees at lower density (Dec 3)"): its band
is mostly needles, so half the 90th-percentile spacing (66 mm) is a RANSAC tolerance in which
circles through the branch whorls win every slice. The tighter refits of a rejected cluster
(:func:`stemmap.cloud.measure._tighter_refits`) find the stem again.

The reference is the ring of the cloud as shipped at the detected stem (as the benchmark):
on this spruce it moves with its start circle (23.3-23.9 cm for starts within 1 cm of the
stem's radius and 3 cm of its height, docs/algorithms/cloud.md "Single trees: noise and
crown circles"), and the detection as shipped moved from 24.51 to 23.74 cm with the core
refits, its ring from 23.78 to 23.37 cm: tolerances at 20 / 10 % leave 0.4 cm for that."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cloud_robustness import TRANSFORMS, Context, Prepared, write_las
from stemmap.cloud.reference import stem_references
from stemmap.cloud.result import CloudStems
from stemmap.cloud.stems import StemConfig, detect_stems, detect_stems_file
from stemmap.io.clouds import read_cloud


def _detect(prep: Prepared, cfg: StemConfig, tmp: Path) -> CloudStems:
    """``prep`` through a LAS file (0.1 mm scale) and ``detect_stems_file``, as the
    benchmark: on these sparse clouds the result depends even on that rounding (in memory
    the 20 % cloud of seed 0 gives 28.0 cm, through the file 25.5 cm)."""
    path = tmp / "cloud.las"
    write_las(path, prep.xyz, prep.scale, prep.offset_round)
    return detect_stems_file(path, cfg)


def _subsampled_dbh_error(
    datasets_dir: Path, tmp: Path, transform: str, seed: int = 0, check_off: bool = True
) -> float:
    """|DBH - ring| (m) of the spruce after ``transform`` (random seed ``seed``), against
    the full-ring reference of the cloud as shipped (as the benchmark); asserts that with
    the tighter refits exactly one stem is found, and (``check_off``) none without them."""
    path = datasets_dir / "treels/spruce.laz"
    xyz = read_cloud(path).xyz
    (ref,) = stem_references(xyz, detect_stems_file(path, StemConfig()))
    assert ref is not None and ref.full
    prep = TRANSFORMS[transform](Context(xyz, None, seed))
    assert prep is not None
    if check_off:
        # without the tighter refits every slice fits a whorl: no stem
        assert len(_detect(prep, StemConfig(tighter_refits=False), tmp)) == 0
    det = _detect(prep, StemConfig(), tmp)
    assert len(det) == 1
    return abs(float(det.diameter[0]) - ref.diameter)


@pytest.mark.slow
def test_half_density_spruce_keeps_its_stem(datasets_dir: Path, tmp_path: Path) -> None:
    assert _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_50") < 0.015


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
def test_fifth_density_spruce_keeps_its_stem(datasets_dir: Path, tmp_path: Path) -> None:
    """At 20 % (seed 0; spacing 100 mm, three 0.4 m slices) the stem is found. Its DBH is
    25.5 cm, 1.7 / 2.1 cm off the ring (the two references above): the issue's 1.5 cm is not
    met. The lowest slice (0.8-1.2 m) holds the stem's one scanned side (about 200 degrees)
    and branch stubs 17-25 cm from its axis; at this density even the reference's own ring
    fit, started on the true circle, gives 27.3 cm at 0.8-1.0 m (25.1 cm as shipped): the
    data, not the fit, puts the lowest slice 1-1.5 cm too large. 2.5 cm = the 2.1 cm
    measured + the reference's 0.4 cm."""
    assert _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_20") < 0.025


@pytest.mark.slow
def test_tenth_density_spruce_is_found_with_thin_slices(datasets_dir: Path, tmp_path: Path) -> None:
    """At 10 % (spacing 153 mm: three 0.4 m slices, the middle one all whorl) the stem is
    found only from the default 20 cm slices. Its DBH is 1.7 / 2.1 cm off the ring (as at
    20 %, the lowest slice): found, but the issue's 1.5 cm target is not met there
    (docs/algorithms/cloud.md); 2.5 cm as at 20 %."""
    assert _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_10") < 0.025


@pytest.mark.slow
def test_tenth_density_spruce_is_not_a_crown(datasets_dir: Path, tmp_path: Path) -> None:
    """At 10 % with seed 3 the first round accepts three circles through the branch whorls
    (r 31-72 cm, RMS 61-97 mm) as a 1.41 m stem: the single-tree cloud's noise floor is its
    own. Choosing over the whole tighter-refit ladder (:func:`stemmap.cloud.measure.
    _single_tree_stem`) gives the stem, within 2.5 cm as above (measured 0.9 cm); without
    it the crown stays."""
    assert (
        _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_10", seed=3, check_off=False)
        < 0.025
    )
    xyz = read_cloud(datasets_dir / "treels/spruce.laz").xyz
    prep = TRANSFORMS["subsample_10"](Context(xyz, None, 3))
    assert prep is not None
    off = _detect(prep, StemConfig(single_tree_ladder=False), tmp_path)
    assert len(off) == 1 and off.diameter[0] > 1.0
