"""A real cloud cut into LAS tiles gives the single-file run's stems and height reference.

All seven real clouds of ../shared/datasets (Dec 5, after the detector was made independent
of the point order): every stem's position, DBH and point count equal to the single file's,
with the default chunks and with 2 m chunks (docs/algorithms/engine.md); tested here on
archi Tree_1, pine_plot, spruce and the lidR slice.

Before (main at 88c3073) a tile run of archi Tree_1 (a tree exported without ground) stated
no base z, and its stem differed from the single file's by 0.8 mm in position and 0.6 mm in
DBH; TreeLS pine_plot in four 5 m tiles differed by up to 7 mm in position and 8.8 mm in DBH
(63 points fewer in one stem), the lidR slice by 0.2 mm: each chunk anchored the detector's
grids at the catalog's corner (a single run anchors them at its band's minimum), the pilot
measured the noise floor with those grids, each chunk decided ground / no ground and a
slice's z range on its own points. docs/algorithms/engine.md, "Tile runs against one file".
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stemmap.cloud import StemConfig, detect_stems_file
from stemmap.cloud.ground import BASE_GROUND, BASE_STEM
from stemmap.cloud.result import CloudStems
from stemmap.engine import Catalog, run_stems_catalog

#: Positions and diameters agree to rounding: the tiles hold the file's points (the same
#: integers, scales and offsets) in another order, which the detector puts back in its
#: canonical order (stemmap.cloud.canonical), so positions and diameters come out equal;
#: only the ground's plane fits run relative to each chunk's raster corner (z: measured
#: <= 4.3e-14 m on pine_plot with 2 m chunks).
TOL_M = 1e-9


def cut_tiles(src: Path, out: Path, size: float) -> Path:
    """``src`` cut into square LAS tiles of ``size`` metres (same scales, offsets, points)."""
    import laspy

    las = laspy.read(src)
    x, y = np.asarray(las.x), np.asarray(las.y)
    ij = np.floor((np.column_stack((x, y)) - [x.min(), y.min()]) / size).astype(np.int64)
    out.mkdir(parents=True)
    for key in np.unique(ij, axis=0):
        tile = laspy.LasData(las.header)
        tile.points = las.points[np.all(ij == key, axis=1)]
        tile.write(str(out / f"t_{key[0]}_{key[1]}.las"))
    return out


def _sorted(s: CloudStems) -> CloudStems:
    return s.select(np.lexsort((s.xy[:, 1], s.xy[:, 0])))


def _same(tiles: CloudStems, one: CloudStems) -> None:
    a, b = _sorted(tiles), _sorted(one)
    assert len(a) == len(b) > 0
    np.testing.assert_allclose(a.xy, b.xy, rtol=0, atol=TOL_M)
    np.testing.assert_allclose(a.diameter, b.diameter, rtol=0, atol=TOL_M)
    np.testing.assert_allclose(a.z, b.z, rtol=0, atol=TOL_M)
    np.testing.assert_array_equal(a.n_points, b.n_points)
    np.testing.assert_array_equal(a.n_slices, b.n_slices)


def _run(tiles: Path, work: Path, client: Any, config: StemConfig, **kw: Any) -> Any:
    return run_stems_catalog(Catalog.from_inputs([tiles]), config, work, client=client, **kw)


def _tiles_and_file(
    datasets_dir: Path, factory: pytest.TempPathFactory, name: str, size: float
) -> tuple[Path, CloudStems]:
    """The cloud ``name`` cut into ``size`` m tiles, and its single-file stems: built once
    per module for the tests that run its tiles with several chunk sizes (read only)."""
    src = datasets_dir / name
    return cut_tiles(src, factory.mktemp("tiles") / "t", size), detect_stems_file(src)


@pytest.fixture(scope="module")
def tree_1_tiles(
    datasets_dir: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, CloudStems]:
    return _tiles_and_file(datasets_dir, tmp_path_factory, "archi/Tree_1_point_cloud.las", 5.0)


@pytest.fixture(scope="module")
def spruce_tiles(
    datasets_dir: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, CloudStems]:
    return _tiles_and_file(datasets_dir, tmp_path_factory, "treels/spruce.laz", 1.0)


@pytest.mark.parametrize("chunk", [None, 2.0])
def test_tree_without_ground_in_tiles(
    tree_1_tiles: tuple[Path, CloudStems], tmp_path: Path, client: Any, chunk: float | None
) -> None:
    """archi Tree_1 in 5 m tiles, one chunk and 2 m chunks (chunks of crown only, which
    on their own points would take their lowest branches for a stem base): the single
    file's stem, from the same flat base."""
    tiles, one = tree_1_tiles
    run = _run(tiles, tmp_path / "w", client, StemConfig(), chunk_size=chunk)
    assert run.stems is not None
    _same(run.stems, one)
    assert one.base == run.stems.base == BASE_STEM
    assert run.stems.base_z == one.base_z == pytest.approx(0.69013, abs=1e-9)


@pytest.mark.parametrize("axis_fallback", [False, True])
def test_plot_in_tiles(
    datasets_dir: Path, tmp_path: Path, client: Any, axis_fallback: bool
) -> None:
    """TreeLS pine_plot in four 5 m tiles: the single file's 16 stems; with the shared-axis
    fit too, whose 0.5-3 m returns the prepared chunks now carry."""
    src = datasets_dir / "treels" / "pine_plot.laz"
    cfg = StemConfig(axis_fallback=axis_fallback)
    one = detect_stems_file(src, cfg)
    run = _run(cut_tiles(src, tmp_path / "t", 5.0), tmp_path / "w", client, cfg)
    assert run.stems is not None and run.stems.base == BASE_GROUND
    _same(run.stems, one)


def test_slice_in_tiles(datasets_dir: Path, tmp_path: Path, client: Any) -> None:
    """The lidR slice (10 cm tall) in 0.3 m tiles: the single file's stem. (Before the
    detector was made independent of the point order (Dec 5) it was the single run on the
    same points in the catalog's order, 0.1 mm / 0.2 mm and 3 of 950 points from the file's;
    docs/algorithms/engine.md "Tile runs against one file".)"""
    src = datasets_dir / "lidr_dbh" / "dbh.laz"
    run = _run(cut_tiles(src, tmp_path / "t", 0.3), tmp_path / "w", client, StemConfig())
    assert run.stems is not None
    one = detect_stems_file(src)
    _same(run.stems, one)
    assert run.stems.z[0] == one.z[0]  # the slice's middle


@pytest.mark.parametrize("chunk", [None, 2.0])
def test_spruce_in_tiles(
    spruce_tiles: tuple[Path, CloudStems], tmp_path: Path, client: Any, chunk: float | None
) -> None:
    """TreeLS spruce in 1 m tiles: the single file's stem. Before Dec 5 its DBH was 10.8 mm
    off (24.64 cm and 663 points for 23.56 cm and 540): the tiles hold the file's points in
    another order, and the ground's ties and the band's fits followed the order."""
    tiles, one = spruce_tiles
    run = _run(tiles, tmp_path / "w", client, StemConfig(), chunk_size=chunk)
    assert run.stems is not None and run.stems.base == one.base == BASE_GROUND
    _same(run.stems, one)


def test_chunk_of_a_slice_takes_the_catalog_z_range() -> None:
    """A chunk of a tilted 0.8 m slice holds 0.1 m of it: on its own z range its stem's
    breast height (the slice's middle) and sub-slices would be its own; given the whole
    slice's z range they are the whole's."""
    from stemmap.cloud import detect_prepared, detect_stems, prepare_cloud

    rng = np.random.default_rng(4)
    rings = []
    for cx in (2.0, 10.0, 18.0):  # three 30 cm trunks along a 4 % slope
        a = rng.uniform(0, 2 * np.pi, 1500)
        z0 = 1.0 + 0.04 * cx
        rings.append(
            np.column_stack(
                (cx + 0.15 * np.cos(a), 0.15 * np.sin(a), z0 + rng.uniform(-0.05, 0.05, a.size))
            )
        )
    xyz = np.concatenate(rings)
    cfg = StemConfig(slice_mode="always")
    whole = detect_stems(xyz, cfg)
    part = xyz[xyz[:, 0] < 6.5]  # the lowest trunk and 4.5 m of buffer
    told = detect_prepared(
        prepare_cloud(part, cfg, z_range=(xyz[:, 2].min(), xyz[:, 2].max())), cfg
    )
    alone = detect_prepared(prepare_cloud(part, cfg), cfg)
    k = int(np.argmin(whole.xy[:, 0]))
    assert len(told) == 1 and told.z[0] == whole.z[k]
    np.testing.assert_allclose(told.diameter, whole.diameter[k], rtol=0, atol=1e-12)
    assert abs(alone.z[0] - whole.z[k]) > 0.05


def test_prepared_chunk_keeps_the_axis_reach(datasets_dir: Path) -> None:
    """A chunk prepared apart (prepared.npz) keeps the 0.5-3 m returns of the shared-axis
    fit (``band.reach``); main dropped them, so axis_reach did nothing on a tile run."""
    from stemmap.cloud import PreparedCloud, prepare_cloud
    from stemmap.io.clouds import read_cloud

    xyz = read_cloud(datasets_dir / "treels" / "pine_plot.laz").xyz
    prep = prepare_cloud(xyz, StemConfig(axis_fallback=True))
    assert prep.band is not None and prep.band.reach is not None
    back = PreparedCloud.from_columns(prep.to_columns())
    assert back.band is not None and back.band.reach is not None
    for a, b in zip(back.band.reach, prep.band.reach, strict=True):
        np.testing.assert_array_equal(a, b)


def test_crown_chunk_takes_the_catalog_base(datasets_dir: Path) -> None:
    """A chunk of Tree_1's crown alone: on its own points its lowest branches look like
    ground (or a stem's cut); given the catalog's base it measures from the stem's cut."""
    from stemmap.cloud import prepare_cloud
    from stemmap.io.clouds import read_cloud

    xyz = read_cloud(datasets_dir / "archi" / "Tree_1_point_cloud.las").xyz
    crown = xyz[xyz[:, 0] < 0.0]  # 5 m from the stem (x = 4.4): branches only
    own = prepare_cloud(crown, StemConfig())
    assert own.band is not None
    z0 = float(xyz[:, 2].min())
    told = prepare_cloud(crown, StemConfig(), base=(BASE_STEM, z0))
    assert told.band is not None and told.band.base == BASE_STEM and told.band.base_z == z0
    assert (own.band.base, own.band.base_z) != (BASE_STEM, z0)
