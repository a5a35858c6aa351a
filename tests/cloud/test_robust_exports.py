"""The real clouds as a user's export would have them (benchmarks/cloud_robustness.py;
docs/algorithms/cloud.md, "Robustness to user exports"): each fix pinned on the cloud and
the transform that failed before it.

* ground cells without ground (canopy over the edge of a tilted plot): treels pine_plot
  tilted 10 degrees had heights off by up to 12 m at its edges;
* coincident points: every point twice gave no spacing, hence no stem, on every cloud;
* weighted radius consensus and guided refits: treels spruce lost its stem when written at a
  UTM offset with 1 mm resolution or rotated 30 degrees about z;
* float32 coordinates at UTM offsets: the reader warns.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from cloud_robustness import TRANSFORMS, Context, write_las, write_ply_float32
from stemmap.cloud.ground import GroundAccumulator, fit_ground
from stemmap.cloud.reference import stem_references
from stemmap.cloud.slicefit import _band_spacing
from stemmap.cloud.stems import StemConfig, detect_stems_file
from stemmap.io.clouds import read_cloud


def _overhang(seed: int) -> np.ndarray:
    """A 10 x 10 m ground sloping 20 % in x, and a crown (5-15 m) over x in 10-13 m where no
    ground was scanned."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(0, 10, (20_000, 2))
    ground = np.column_stack((g, 0.2 * g[:, 0] + rng.normal(0, 0.01, g.shape[0])))
    c = np.column_stack((rng.uniform(10, 13, 5000), rng.uniform(0, 10, 5000)))
    crown = np.column_stack((c, rng.uniform(5, 15, c.shape[0])))
    return np.vstack((ground, crown))


def test_canopy_over_the_ground_edge_is_no_ground() -> None:
    p = _overhang(0)
    g = fit_ground(p)
    edge = np.column_stack((np.full(50, 9.5), np.linspace(0.5, 9.5, 50)))
    # without the test the edge cells' planes lean towards the crown's minima (5 m up)
    np.testing.assert_allclose(g.ground_at(edge), 0.2 * 9.5, atol=0.05)
    assert g.observed is not None and g.observed.sum() == 13 * 10  # the crown cells held points


def test_a_steep_slope_is_ground() -> None:
    """A 40 degree slope (0.84 m per 1 m cell) is ground everywhere: the test allows 45."""
    rng = np.random.default_rng(1)
    g = rng.uniform(0, 10, (20_000, 2))
    p = np.column_stack((g, 0.84 * g[:, 0]))
    acc = GroundAccumulator(1.0)
    acc.update(p)
    model = acc.model()
    q = rng.uniform(1, 9, (200, 2))
    np.testing.assert_allclose(model.ground_at(q), 0.84 * q[:, 0], atol=0.03)


def test_coincident_points_leave_the_spacing_alone() -> None:
    rng = np.random.default_rng(2)
    xy, h = rng.uniform(0, 1, (3000, 2)), rng.uniform(0.8, 2.0, 3000)
    once = _band_spacing(xy, h)
    twice = _band_spacing(np.repeat(xy, 2, axis=0), np.repeat(h, 2))
    assert np.isfinite(twice) and abs(twice - once) < 0.1 * once


def test_float32_coordinates_far_from_zero_warn(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 10, (100, 3))
    for name, shift, warns in (("near.ply", 0.0, False), ("utm.ply", 6_200_000.0, True)):
        caplog.clear()
        write_ply_float32(tmp_path / name, p + shift)
        with caplog.at_level(logging.WARNING, logger="stemmap.io.clouds"):
            read_cloud(tmp_path / name)
        assert ("float32" in caplog.text) == warns


def _transformed(datasets_dir: Path, tmp_path: Path, rel: str, name: str) -> tuple[Path, Path]:
    src = datasets_dir / rel
    xyz = read_cloud(src).xyz
    grounds: list = []
    detect_stems_file(src, StemConfig(), on_ground=grounds.append)
    prep = TRANSFORMS[name](Context(xyz, grounds[0]))
    assert prep is not None
    f = tmp_path / f"t{prep.suffix}"
    write_las(f, prep.xyz, prep.scale, prep.offset_round)
    return src, f


@pytest.mark.slow
def test_tilted_plot_keeps_its_ground(datasets_dir: Path, tmp_path: Path) -> None:
    """treels pine_plot tilted 10 degrees: heights above ground as untilted (before: 1 % of
    the points 12 m off, from crowns over the tilted plot's edge), and every stem found."""
    src, f = _transformed(datasets_dir, tmp_path, "treels/pine_plot.laz", "tilt_10")
    xyz = read_cloud(src).xyz
    prep = TRANSFORMS["tilt_10"](Context(xyz, None))
    assert prep is not None
    h0 = fit_ground(xyz).height_of(xyz)
    h1 = fit_ground(prep.xyz).height_of(prep.xyz)
    low = h0 < 2.5  # the band and below (crowns move over other ground when tilted)
    assert np.quantile(np.abs(h1 - h0)[low], 0.99) < 0.15
    assert len(detect_stems_file(f, StemConfig())) >= 16  # every trunk (16; 17 before the
    # continues-above test dropped a 1.7 m sapling, docs/algorithms/cloud.md)


@pytest.mark.slow
def test_every_point_twice_gives_the_same_stem(datasets_dir: Path, tmp_path: Path) -> None:
    src, f = _transformed(datasets_dir, tmp_path, "treels/pine.laz", "duplicate")
    base = detect_stems_file(src, StemConfig())
    det = detect_stems_file(f, StemConfig())
    assert len(det) == len(base) == 1
    assert abs(det.diameter[0] - base.diameter[0]) < 0.001


@pytest.mark.slow
@pytest.mark.parametrize("name", ["utm_las", "rotate_z_30"])
def test_spruce_survives_a_utm_export_and_a_rotation(
    datasets_dir: Path, tmp_path: Path, name: str
) -> None:
    """treels spruce (branches down to the ground) lost its stem under both before the
    weighted radius consensus and the guided refits."""
    _, f = _transformed(datasets_dir, tmp_path, "treels/spruce.laz", name)
    det = detect_stems_file(f, StemConfig())
    assert len(det) == 1
    (ref,) = stem_references(read_cloud(f).xyz, det)
    assert ref is not None and ref.full
    assert abs(det.diameter[0] - ref.diameter) < 0.015


@pytest.mark.slow
@pytest.mark.parametrize("rise", [0.3, 0.8])
def test_a_cropped_tree_is_the_shipped_tree_at_that_height(datasets_dir: Path, rise: float) -> None:
    """archi Tree_1 without its lowest ``rise`` m (a segmented export): the base moves up by
    the cut, and the DBH is the shipped cloud's at the same absolute height (slices and breast
    height raised by the rise; within 0.05 cm on the real tree, docs/algorithms/cloud.md
    "archi Tree_1 cropped at 0.3 m"): a crop changes where DBH is measured, nothing else. A
    regression guard (it held before), pinned because the benchmark's crop yardstick fails
    this cell for another reason (a branch swelling in its ring)."""
    from dataclasses import replace

    from stemmap.cloud.stems import detect_stems

    xyz = read_cloud(datasets_dir / "archi/Tree_1_point_cloud.las").xyz
    base = detect_stems(xyz)
    z0 = float(base.z[0] - base.dbh_height[0])
    crop = detect_stems(xyz[xyz[:, 2] >= z0 + rise])
    got = float(crop.z[0] - crop.dbh_height[0]) - z0
    assert abs(got - rise) < 0.01
    cfg = StemConfig()
    raised = replace(
        cfg,
        slice_centers=tuple(h + got for h in cfg.slice_centers),
        breast_height=cfg.breast_height + got,
    )
    same = detect_stems(xyz, raised)
    assert len(crop) == len(same) == 1
    assert abs(crop.diameter[0] - same.diameter[0]) < 0.003
