"""treels spruce.laz randomly subsampled to 50 % (benchmarks/cloud_robustness.py
``subsample_50``; docs/algorithms/cloud.md "Single trees at lower density (Dec 3)"): its band
is mostly needles, so half the 90th-percentile spacing (66 mm) is a RANSAC tolerance in which
circles through the branch whorls win every slice. The tighter refits of a rejected cluster
(:func:`stemmap.cloud._ladder._tighter_refits`) find the stem again.

The reference is the ring of the cloud as shipped at the detected stem (as the benchmark):
on this spruce it moves with its start circle (23.3-23.9 cm for starts within 1 cm of the
stem's radius and 3 cm of its height, docs/algorithms/cloud.md "Single trees: noise and
crown circles"), and the detection as shipped moved from 24.51 to 23.74 cm with the core
refits, its ring from 23.78 to 23.37 cm (the benchmark's fixed reference since). At 20 /
10 % the issue's 1.5 cm is asserted since the annulus refits about a found stem take its own
scatter where the noise floor is the whorls' ("Single trees: the annulus about a found
stem")."""

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
    """At 50 % the stem is found within the issue's 1.5 cm. (Without the tighter refits no
    stem was found before Dec 5; with the locally optimised RANSAC start, docs/algorithms/
    cloud.md "RANSAC draws", the first round finds it, 24.83 cm, so only the stem is
    asserted.)"""
    err = _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_50", check_off=False)
    assert err < 0.015


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
    """At 20 % (seed 0; spacing 100 mm, three 0.4 m slices) the stem is found by the
    single-tree ladder. Before, the annulus refits about it took the whorls' noise floor
    (71 mm) as their scale and failed, and the thick-slice stem stood: 25.5 cm, its lowest
    slice (0.8-1.2 m) across the root flare, 2.1 cm off the ring. In the stem's own scale
    (:func:`stemmap.cloud.slicestem._annulus_noise`, 4.4 mm) the thin-slice rung at 12.5 mm
    refits 1.3 and 1.7 m to the stem: 5 slices, 23.99 cm, 0.62 cm off; the issue's 1.5 cm."""
    assert _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_20") < 0.015


@pytest.mark.slow
def test_tenth_density_spruce_is_found_with_thin_slices(datasets_dir: Path, tmp_path: Path) -> None:
    """At 10 % (spacing 153 mm, three 0.4 m slices, noise floor 124 mm: the whorls') the
    thick rung at 9.6 mm has the stem at 1.4 and 1.8 m (12.4 / 10.9 cm) and its 1.0 m slice
    refitted in their scale (4.1 mm): 23.77 cm, 0.40 cm off. Before, that refit failed and
    the thin-slice stem through the 0.9 m flare slice stood (25.46 cm, 2.1 cm off)."""
    assert _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_10") < 0.015


@pytest.mark.slow
def test_tenth_density_spruce_is_not_a_crown(datasets_dir: Path, tmp_path: Path) -> None:
    """At 10 % with seed 3 the first round accepts three circles through the branch whorls
    (r 31-72 cm, RMS 61-97 mm) as a 1.41 m stem: the single-tree cloud's noise floor is its
    own. Choosing over the whole tighter-refit ladder (:func:`stemmap.cloud._ladder.
    _single_tree_stem`) gives the stem, within 2.5 cm (measured 0.9 cm); without it the
    crown stayed. (Since Dec 5 the RANSAC draws are those of the canonical point order,
    docs/algorithms/cloud.md "Point order": on this cloud the first round no longer takes
    the whorls, with or without the ladder, 23.6 cm; the crown was a draw of the file's
    order, so only the stem is asserted.)"""
    assert (
        _subsampled_dbh_error(datasets_dir, tmp_path, "subsample_10", seed=3, check_off=False)
        < 0.025
    )
